"""The ipm stages: registration, configs, BEV contents, instance masks, errors, the attitude source."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from ipm_scene import GroundScene, render, scene_calibration, truth_mask
from pydantic import ValidationError
from sgf_plugins.ipm import (
    HindsightMotionCompensatedIPM,
    InversePerspectiveMapping,
    IpmParams,
    MotionCompensatedIPM,
    MotionCompensatedIpmParams,
    PlaneMotionCompensatedIPM,
    PlaneMotionCompensatedIpmParams,
)
from sgf_testing import conf_node

from sgf_pipeline import ConfigError, DataError, Dataset, Pipeline, RunContext, hookimpl, load_plugins
from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.geometry import pose_from_xyz_rpy
from sgf_pipeline.types import Bev, CameraImage, Frame

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene() -> GroundScene:
    return GroundScene()


@pytest.fixture(scope="module")
def view(scene: GroundScene) -> tuple[np.ndarray, np.ndarray]:
    return render(scene, scene_calibration(), 0.0)


def _frame(image: np.ndarray, ids=None, imu=(0.0, 0.0), odometry=None, index: int = 0) -> Frame:
    pose = np.eye(4) if odometry is None else odometry
    return Frame(index, 0.1 * index, image, pose, scene_calibration(), imu, instance_ids=ids)


def test_both_variants_are_registered_with_their_parameters() -> None:
    registry = load_plugins(allow=["ipm"]).registry
    assert {v.name for v in registry.variants("ipm")} == {"plain", "mc", "mc_plane", "mc_hindsight"}
    assert registry.get("ipm", "mc").cls is MotionCompensatedIPM
    assert registry.get("ipm", "mc_plane").cls is PlaneMotionCompensatedIPM
    assert registry.get("ipm", "mc_hindsight").cls is HindsightMotionCompensatedIPM
    assert registry.get("ipm", "plain").signature.output_types == (Bev,)


def test_mc_ahead_config_is_mc_with_its_extensions() -> None:
    from sgf_plugins.ipm.stages import AHEAD_MC

    node = conf_node("ipm/mc_ahead")
    assert node.pop("name") == "mc"
    assert node == {**MotionCompensatedIpmParams().model_dump(), **AHEAD_MC}
    assert AHEAD_MC == {"reference_fit": "line", "lookahead": 2.0, "attitude_noise": 0.005}


def test_the_noise_scale_shrinks_small_deviations_and_keeps_bumps(view) -> None:
    image, _ = view
    stage = MotionCompensatedIPM(MotionCompensatedIpmParams(attitude_noise=0.005))
    for k in range(10):
        stage.compensation(_frame(image, imu=(0.0, 0.0), index=k))
    small = stage.compensation(_frame(image, imu=(0.0025, -0.0025), index=10))
    d = 0.0025 * 10 / 11  # the reference averages the new pose in: 1/11 of it
    assert small == pytest.approx((-(d**3) / (d**2 + 0.005**2), -(d**3) / (d**2 + 0.005**2)))
    assert abs(small[1]) < 0.2 * d  # d^3 / (d^2 + sigma^2): 17 % of a noise-sized deviation is left
    bump = stage.compensation(_frame(image, imu=(0.0, 0.05), index=11))
    assert stage.last_reference is not None
    d = 0.05 - stage.last_reference.pitch  # the bump's pose is an outlier: left out of the reference
    assert bump[1] == pytest.approx(d**3 / (d**2 + 0.005**2)) and bump[1] > 0.99 * d  # 99 % of a bump's pitch


def test_default_config_runs_mc_ipm() -> None:
    config = yaml.safe_load((ROOT / "conf" / "config.yaml").read_text())
    assert {"ipm": "mc"} in config["defaults"]
    assert config["pipeline"].index("ipm") == config["pipeline"].index("enhance") + 1


def test_paper_defaults() -> None:
    p = MotionCompensatedIpmParams()
    assert (p.queue_size, p.pitch_threshold) == (50, 0.025)
    grid = p.grid
    assert (grid.width, grid.height, grid.resolution) == (256, 256, 0.02)
    assert grid.pixel_to_ground(np.zeros(1), np.zeros(1)) == pytest.approx((5.61, 2.55))


@pytest.mark.parametrize(
    "bad,message",
    [
        ({"x_min": 3.0, "x_max": 2.0}, "x_max"),
        ({"y_max": 2.57}, "whole number"),
        ({"resolution": 0.0}, "greater than 0"),
        ({"backend": "kornia", "interpolation": "cubic"}, "cubic"),
        ({"queue": 10}, "Extra inputs"),
    ],
)
def test_bad_parameters_are_refused(bad: dict, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        MotionCompensatedIpmParams(**bad)


def test_plain_bev_is_metric_and_masks_are_aligned(scene: GroundScene, view) -> None:
    image, ids = view
    stage = InversePerspectiveMapping(IpmParams())
    bev = stage.process(_frame(image, ids), CameraImage(image, 0))
    assert bev.image.shape == (256, 256, 3) and bev.image.dtype == np.uint8
    assert bev.valid.shape == (256, 256) and 0.5 < bev.valid.mean() < 0.8
    assert not bev.image[~bev.valid].any()  # nothing outside the visible ground
    assert not bev.valid[-1].any() and bev.valid[0].all()  # 0.5 m ahead is below the image; 5.6 m is seen
    truth = truth_mask(scene, stage.grid, 0.0)
    assert bev.instance_ids is not None
    seen = (bev.instance_ids > 0) & bev.valid
    expected = (truth > 0) & bev.valid
    iou = (seen & expected).sum() / (seen | expected).sum()
    assert iou > 0.93
    paint = (bev.image[:, :, 0] > 165) & bev.valid
    assert (paint & seen).sum() / (paint | seen).sum() > 0.9  # the instance mask lies on the painted pixels
    same_instance = bev.instance_ids[seen] == truth[seen]
    assert same_instance.mean() > 0.97
    assert (bev.frame_index, bev.timestamp, bev.roll, bev.pitch) == (0, 0.0, 0.0, 0.0)


def test_grey_images_and_nearest_and_cubic_interpolation(view) -> None:
    image, _ = view
    linear = InversePerspectiveMapping(IpmParams()).process(_frame(image), CameraImage(image, 0))
    for interpolation in ("nearest", "cubic"):
        other = InversePerspectiveMapping(IpmParams(interpolation=interpolation))
        bev = other.process(_frame(image), CameraImage(image, 0))
        diff = np.abs(bev.image.astype(int) - linear.image.astype(int))[linear.valid]
        assert diff.mean() < 4.0
    grey = InversePerspectiveMapping(IpmParams()).process(_frame(image[:, :, 0]), CameraImage(image[:, :, 0], 0))
    assert grey.image.shape == (256, 256)
    assert np.array_equal(grey.image, linear.image[:, :, 0])


def test_mc_equals_plain_when_the_robot_is_level(view) -> None:
    image, ids = view
    plain = InversePerspectiveMapping(IpmParams())
    mc = MotionCompensatedIPM(MotionCompensatedIpmParams())
    for k in range(5):
        frame = _frame(image, ids, imu=(0.0, 0.0), index=k)
        a, b = plain.process(frame, CameraImage(image, k)), mc.process(frame, CameraImage(image, k))
        assert np.array_equal(a.image, b.image) and np.array_equal(a.valid, b.valid)
        assert a.instance_ids is not None and b.instance_ids is not None
        assert np.array_equal(a.instance_ids, b.instance_ids)


def test_mc_compensates_a_pitched_frame(scene: GroundScene) -> None:
    calibration = scene_calibration()
    stage = MotionCompensatedIPM(MotionCompensatedIpmParams())
    plain = InversePerspectiveMapping(IpmParams())
    level_image, _ = render(scene, calibration, 0.0)
    for k in range(10):
        stage.process(_frame(level_image, imu=(0.0, 0.0), index=k), CameraImage(level_image, k))
    image, ids = render(scene, calibration, 0.0, roll=0.0, pitch=0.05)
    frame = _frame(image, ids, imu=(0.0, 0.05), index=10)
    bev = stage.process(frame, CameraImage(image, 10))
    assert stage.last_reference is not None
    assert (stage.last_reference.inliers, stage.last_reference.queued) == (10, 11)  # the bump pose is left out
    assert (bev.roll, bev.pitch) == (0.0, 0.05)
    assert bev.homography is not None  # the mapping it warped with, for lifting SGF pixels later
    assert np.allclose(bev.homography, stage.homography(calibration, 0.0, 0.05))
    assert not np.allclose(bev.homography, plain.homography(calibration))
    truth = truth_mask(scene, stage.grid, 0.0) > 0
    for out, low, high in ((bev, 0.9, 1.0), (plain.process(frame, CameraImage(image, 10)), 0.0, 0.5)):
        paint = (out.image[:, :, 0] > 165) & out.valid
        iou = (paint & truth).sum() / (paint | (truth & out.valid)).sum()
        assert low < iou < high


def test_begin_resets_the_pose_queue(view) -> None:
    image, _ = view
    stage = MotionCompensatedIPM(MotionCompensatedIpmParams())
    for k in range(30):
        stage.process(_frame(image, imu=(0.0, -0.08), index=k), CameraImage(image, k))
    assert len(stage.queue) == 30
    stage.begin(RunContext(run_dir=None))
    assert len(stage.queue) == 0
    bev = stage.process(_frame(image, imu=(0.0, 0.0)), CameraImage(image, 0))
    assert bev.pitch == 0.0


def test_attitude_sources(view) -> None:
    image, _ = view
    odometry = pose_from_xyz_rpy(3.0, 1.0, 0.2, 0.01, -0.03, 0.7)
    imu_frame = _frame(image, imu=(0.02, 0.04), odometry=odometry)
    no_imu = Frame(0, 0.0, image, odometry, scene_calibration(), None)
    auto = MotionCompensatedIPM(MotionCompensatedIpmParams())
    assert auto.attitude(imu_frame) == (0.02, 0.04)
    assert auto.attitude(no_imu) == pytest.approx((0.01, -0.03))
    from_odometry = MotionCompensatedIPM(MotionCompensatedIpmParams(attitude="odometry"))
    assert from_odometry.attitude(imu_frame) == pytest.approx((0.01, -0.03))
    strict = MotionCompensatedIPM(MotionCompensatedIpmParams(attitude="imu"))
    with pytest.raises(DataError, match="no IMU roll/pitch"):
        strict.process(no_imu, CameraImage(image, 0))


def test_compensation_switches_for_ablations(view) -> None:
    image, _ = view
    stages = {
        flags: MotionCompensatedIPM(MotionCompensatedIpmParams(compensate_roll=flags[0], compensate_pitch=flags[1]))
        for flags in ((True, True), (False, True), (True, False))
    }
    for stage in stages.values():
        for k in range(5):
            stage.compensation(_frame(image, imu=(0.0, 0.0), index=k))
    out = {flags: stage.compensation(_frame(image, imu=(0.04, 0.06), index=5)) for flags, stage in stages.items()}
    assert out[(True, True)] == pytest.approx((-0.04, 0.06))  # psi = -(roll - roll_ref) (eq. 1's sense)
    assert out[(False, True)] == pytest.approx((0.0, 0.06))
    assert out[(True, False)] == pytest.approx((-0.04, 0.0))


def test_clear_errors_for_bad_input(view) -> None:
    image, ids = view
    stage = MotionCompensatedIPM(MotionCompensatedIpmParams())
    with pytest.raises(DataError, match="does not match the calibration"):
        stage.process(_frame(image[:240]), CameraImage(image[:240], 0))
    with pytest.raises(DataError, match="instance id mask"):
        stage.process(_frame(image, ids[:100]), CameraImage(image, 0))
    # An IMU dropout is not an error: the odometry's attitude stands in (attitude=auto), and it is counted.
    bev = stage.process(_frame(image, imu=(float("nan"), 0.0)), CameraImage(image, 0))
    assert (bev.roll, bev.pitch) == (0.0, 0.0) and stage.counts["attitude_from_odometry"] == 1
    kitti = Intrinsics(fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, width=1241, height=376)
    far = Calibration.from_mounting(kitti, 1.65, 0.0)
    frame = Frame(0, 0.0, np.zeros((376, 1241), np.uint8), np.eye(4), far, (0.0, 0.0))
    fixed = MotionCompensatedIPM(MotionCompensatedIpmParams(region="fixed"))  # auto moves it (test_ipm_region.py)
    with pytest.raises(ConfigError, match=r"no pixel of the ipm region .* about 6\.2\d m from the base origin"):
        fixed.process(frame, CameraImage(np.zeros((376, 1241, 3), np.uint8), 0))


class _SceneDataset(Dataset):
    """Three rendered frames of the test scene, for the pipeline wiring test."""

    name = "ipm_test_scene"

    def frames(self) -> Iterator[Frame]:
        scene, calibration = GroundScene(), scene_calibration()
        for k in range(3):
            image, ids = render(scene, calibration, 0.1 * k)
            yield Frame(k, 0.1 * k, image, np.eye(4), calibration, (0.0, 0.0), instance_ids=ids)


class _ScenePlugin:
    @hookimpl
    def sgf_register_stages(self, registry) -> None:
        registry.add(_SceneDataset)


def test_runs_in_a_pipeline_after_enhance() -> None:
    plugins = load_plugins(allow=["enhance", "ipm"], extra=[("ipm_test_scene", _ScenePlugin())])
    config = {
        "pipeline": ["dataset", "enhance", "ipm"],
        "dataset": {"name": "ipm_test_scene"},
        "enhance": {"name": "clahe"},
        "ipm": {"name": "mc", "queue_size": 10},
        "run": {"progress": False, "plots": False},
    }
    pipeline = Pipeline.from_config(config, plugins=plugins)
    results = [pipeline.process(frame) for frame in pipeline.frames()]
    assert [r.outputs["bev"].frame_index for r in results] == [0, 1, 2]
    assert all(r.outputs["bev"].instance_ids is not None for r in results)
    assert results[-1].outputs["bev"].image.shape == (256, 256, 3)


@pytest.mark.parametrize(
    "override,message",
    [
        ({"plane_scales": [4, 0]}, "plane_scales must be whole downsampling factors >= 1"),
        ({"plane_min_baseline": 2.0}, r"plane_min_baseline \(2.0\) must not exceed plane_baseline \(0.6\)"),
        ({"plane_scales": []}, "plane_scales"),
    ],
)
def test_mc_plane_refuses_bad_fit_parameters(override: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PlaneMotionCompensatedIpmParams(**override)


@pytest.mark.parametrize("name", ["mc", "mc_plane", "mc_hindsight"])
@pytest.mark.parametrize("key", ["lookahead", "attitude_noise"])
def test_every_mc_variant_refuses_a_negative_lookahead_or_noise_scale(name: str, key: str) -> None:
    model = load_plugins(allow=["ipm"]).registry.get("ipm", name).params_model
    assert getattr(model(), key) >= 0.0
    with pytest.raises(ValidationError, match=key):
        model(**{key: -0.1})
