"""The BEV region follows the camera: a car's camera, a sideways camera, one that sees no ground."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from sgf_plugins.ipm import InversePerspectiveMapping, IpmParams, MotionCompensatedIPM, MotionCompensatedIpmParams
from sgf_plugins.odometry.scale import BevMotionParams, BevMotionScale
from sgf_plugins.shared.bev_region import MIN_SEEN, ground_visible, nearest_region, seen_fraction

from sgf_pipeline import ConfigError, RunContext
from sgf_pipeline.calibration import Calibration, Intrinsics, camera_to_base_from_mounting
from sgf_pipeline.types import BevGrid, CameraImage, Frame

KITTI = Intrinsics(fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, width=1241, height=376)
CAMPUS = Intrinsics(fx=400.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)
DEFAULT = IpmParams().grid


def _nearest_ahead(height: float, tilt: float) -> float:
    """Where the bottom image row's middle meets the road: h / tan(tilt + atan((H - 1 - cy) / fy))."""
    return height / math.tan(tilt + math.atan((KITTI.height - 1 - KITTI.cy) / KITTI.fy))


def _frame(calibration: Calibration, index: int = 0) -> Frame:
    k = calibration.intrinsics
    return Frame(index, 0.1 * index, np.zeros((k.height, k.width), np.uint8), np.eye(4), calibration, (0.0, 0.0))


@pytest.mark.parametrize("tilt_deg", [0.0, 1.0])
def test_a_car_camera_gets_the_nearest_road_ahead_of_the_same_size(tilt_deg: float, caplog: pytest.LogCaptureFixture):
    calibration = Calibration.from_mounting(KITTI, 1.65, math.radians(tilt_deg))
    assert seen_fraction(calibration, DEFAULT) == 0.0  # 0.5 - 5.62 m ahead: all below the image
    stage = MotionCompensatedIPM(MotionCompensatedIpmParams())
    stage.begin(RunContext(run_dir=None))
    caplog.set_level(logging.INFO, logger="sgf_pipeline.ipm")
    bevs = [stage.process(_frame(calibration, i), CameraImage(np.zeros((376, 1241, 3), np.uint8), i)) for i in range(3)]
    grid = bevs[0].grid
    assert all(b.grid == grid for b in bevs)
    # the same size and lattice, moved to the nearest road in view: the near row's middle is seen, the row before not
    assert (grid.width, grid.height, grid.y_min, grid.y_max) == (DEFAULT.width, DEFAULT.height, -2.56, 2.56)
    assert (grid.x_min - DEFAULT.x_min) / 0.02 == pytest.approx(round((grid.x_min - DEFAULT.x_min) / 0.02), abs=1e-6)
    near = grid.x_min + 0.01
    assert ground_visible(calibration, np.array([near, near - 0.02]), np.zeros(2)).tolist() == [True, False]
    assert near - 0.02 < _nearest_ahead(1.65, math.radians(tilt_deg)) <= near
    assert bevs[0].valid.mean() == seen_fraction(calibration, grid) > 0.99  # the road ahead fills the BEV
    moved = [r for r in caplog.records if "using x in [" in r.getMessage()]
    assert len(moved) == 1 and "the camera sees 0 % of the configured region" in moved[0].getMessage()
    context = RunContext(run_dir=None)
    stage.finalize(context)
    assert context.metrics["ipm"]["region"]["x_min"] == grid.x_min
    assert context.metrics["ipm"]["region"]["configured"] == [0.5, 5.62, -2.56, 2.56]
    # fixed: the configured region, and an error naming what the camera sees
    fixed = InversePerspectiveMapping(IpmParams(region="fixed"))
    with pytest.raises(
        ConfigError,
        match=r"no pixel of the ipm region x in \[0.5, 5.62\] m.*1\.65 m high.*"
        r"the nearest ground it sees ahead is about [56]\.\d\d m from the base origin",
    ):
        fixed.process(_frame(calibration), CameraImage(np.zeros((376, 1241, 3), np.uint8), 0))


def test_the_delivery_robot_keeps_its_configured_region():
    calibration = Calibration.from_mounting(CAMPUS, 0.6, math.radians(25.0))
    assert seen_fraction(calibration, DEFAULT) >= MIN_SEEN  # 79 %: its near corners lie outside the image
    stage = InversePerspectiveMapping(IpmParams())
    stage.begin(RunContext(run_dir=None))
    bev = stage.process(_frame(calibration), CameraImage(np.zeros((480, 640, 3), np.uint8), 0))
    assert bev.grid == DEFAULT
    context = RunContext(run_dir=None)
    stage.finalize(context)
    assert "ipm" not in context.metrics  # nothing to report: the configured region


def test_a_sideways_camera_is_described_as_one_and_gets_the_ground_beside_the_robot():
    calibration = Calibration(intrinsics=KITTI, camera_to_base=camera_to_base_from_mounting(1.65, 0.0, yaw=math.pi / 2))
    fixed = InversePerspectiveMapping(IpmParams(region="fixed"))
    with pytest.raises(
        ConfigError,
        match=r"turned 90 deg from the robot's forward axis \(looking to the left\); the "
        r"nearest ground it sees to the left is about 6\.2\d m",
    ):
        fixed.process(_frame(calibration), CameraImage(np.zeros((376, 1241), np.uint8), 0))
    grid = nearest_region(calibration, DEFAULT)
    assert grid is not None
    # beside the robot, centred on the camera along x, its near edge the nearest ground seen to the left
    assert (grid.x_min, grid.x_max) == pytest.approx((-2.56, 2.56)) and grid.y_max - grid.y_min == pytest.approx(5.12)
    assert grid.y_min + 0.01 >= _nearest_ahead(1.65, 0.0) > grid.y_min - 0.01
    assert seen_fraction(calibration, grid) > 0.99
    behind = Calibration(intrinsics=KITTI, camera_to_base=camera_to_base_from_mounting(1.65, 0.0, yaw=math.pi))
    back = nearest_region(behind, DEFAULT)
    assert back is not None and back.x_max == pytest.approx(-grid.y_min) and back.y_min == -2.56


def test_a_camera_that_sees_no_ground_is_an_error():
    upward = Calibration.from_mounting(KITTI, 1.65, math.radians(-40.0))
    stage = InversePerspectiveMapping(IpmParams())
    with pytest.raises(
        ConfigError,
        match=r"the camera sees no ground .*optical axis 40\.0 deg above the horizon.*"
        r"check the camera's mounting",
    ):
        stage.process(_frame(upward), CameraImage(np.zeros((376, 1241), np.uint8), 0))


def test_odometry_scale_makes_the_same_check(caplog: pytest.LogCaptureFixture):
    """Its near ground (0.5 - 3 m ahead) is out of a car camera's view: it measures further out, not nothing."""
    calibration = Calibration.from_mounting(KITTI, 1.65, math.radians(1.0))
    stage = BevMotionScale(BevMotionParams())
    stage.begin(RunContext(run_dir=None))
    caplog.set_level(logging.INFO, logger="sgf_pipeline.ipm")
    stage.process(_frame(calibration), CameraImage(np.zeros((376, 1241, 3), np.uint8), 0))
    grid = stage.grid
    assert (grid.x_max - grid.x_min, grid.y_min, grid.y_max) == pytest.approx((2.5, -1.25, 1.25))
    assert grid.x_min - 0.01 < _nearest_ahead(1.65, math.radians(1.0)) <= grid.x_min + 0.01
    assert stage._valid.mean() > 0.99
    assert sum("odometry_scale: the camera sees 0 %" in r.getMessage() for r in caplog.records) == 1
    context = RunContext(run_dir=None)
    stage.finalize(context)
    assert context.metrics["odometry_scale"]["region"]["x_min"] == grid.x_min
    fixed = BevMotionScale(BevMotionParams(region="fixed"))
    fixed.begin(RunContext(run_dir=None))
    with pytest.raises(ConfigError, match=r"no pixel of the odometry_scale region x in \[0.5, 3\] m"):
        fixed.process(_frame(calibration), CameraImage(np.zeros((376, 1241, 3), np.uint8), 0))
    campus = BevMotionScale(BevMotionParams())
    campus.begin(RunContext(run_dir=None))
    campus.process(
        _frame(Calibration.from_mounting(CAMPUS, 0.6, math.radians(25.0))),
        CameraImage(np.zeros((480, 640, 3), np.uint8), 0),
    )
    assert campus.grid == BevGrid(0.02, 0.5, 3.0, -1.25, 1.25)
