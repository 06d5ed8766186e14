"""``ipm=mc_hindsight``: the plane of the ground ahead from the path the robot drove over it next."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sgf_plugins.ipm import (
    HindsightMotionCompensatedIPM,
    HindsightMotionCompensatedIpmParams,
    MotionCompensatedIPM,
    MotionCompensatedIpmParams,
)
from sgf_plugins.ipm.hindsight import AttitudeWindow, ground_ahead, path_profile
from sgf_plugins.ipm.stages import AHEAD_MC

from sgf_pipeline import RunContext
from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.types import Frame, PathAhead

NEAR, FAR = 0.5, 5.62
STEP = 0.1
CALIBRATION = Calibration.from_mounting(
    Intrinsics(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480), height=0.8, tilt=0.3
)


def hill(x: np.ndarray, start: float = 1.0, grade: float = 0.06) -> np.ndarray:
    """Flat ground to ``start`` metres ahead, then rising at ``grade``."""
    return np.where(x > start, grade * (x - start), 0.0)


def path_over(
    ground, yaw: float = 0.7, length: float = 7.0, roll: float = 0.0, planar: bool = False, imu: bool = True
) -> tuple[np.ndarray, PathAhead]:
    """A robot at (2, -1) heading ``yaw``, and the path it then drives straight ahead over ``ground(x)``."""
    start = pose_from_xy_yaw(2.0, -1.0, yaw)
    x = STEP * np.arange(1, round(length / STEP) + 1)
    z = ground(x)
    poses = np.repeat(start[None], len(x), axis=0)
    poses[:, 0, 3] += x * math.cos(yaw)
    poses[:, 1, 3] += x * math.sin(yaw)
    poses[:, 2, 3] = 0.0 if planar else z
    rise = np.diff(np.concatenate([[0.0], z]))
    attitude = np.stack([np.full(len(x), roll), -np.arctan(rise / STEP)], axis=1)  # pitch is nose down positive
    if not imu:
        attitude[:] = np.nan
    return start, PathAhead(poses, attitude, length, True)


def expected_grade(ground) -> float:
    """The least-squares slope through the robot of the ground between 0.2 m and the BEV's far edge."""
    x = STEP * np.arange(1, 100)
    x = x[(x >= 0.2 - 1e-9) & (x <= FAR)]
    return float((x * ground(x)).sum() / (x * x).sum())


def test_the_grade_of_a_hill_starting_ahead_is_fitted_from_the_path_driven_over_it() -> None:
    pose, path = path_over(hill, roll=0.02)
    ground = ground_ahead(pose, path, NEAR, FAR)
    assert ground is not None
    # the ground under the robot is flat: no past pose knows of the hill the BEV shows
    assert ground.grade == pytest.approx(expected_grade(hill), rel=1e-9)
    assert 0.035 < ground.grade < 0.05 and ground.pitch == pytest.approx(-math.atan(ground.grade))
    assert ground.roll == pytest.approx(0.02) and ground.reach == pytest.approx(5.6)
    driven, ahead, height = path_profile(pose, path)
    np.testing.assert_allclose(ahead, STEP * np.arange(1, 71), atol=1e-12)
    np.testing.assert_allclose(height, hill(ahead), atol=1e-12)
    assert driven[-1] == pytest.approx(np.hypot(7.0, 0.06 * 6.0), rel=2e-3)


def test_heights_come_from_the_imu_or_else_from_the_odometry() -> None:
    reference = expected_grade(hill)
    # a planar odometry (z = 0): the IMU's pitch over its horizontal steps (cos of 3.4 degrees short)
    _, planar = path_over(hill, planar=True)
    pose, _ = path_over(hill)
    ground = ground_ahead(pose, planar, NEAR, FAR)
    assert ground is not None and ground.grade == pytest.approx(reference, rel=3e-3)
    # no IMU on the path: the odometry's own heights; no roll either
    _, no_imu = path_over(hill, imu=False)
    ground = ground_ahead(pose, no_imu, NEAR, FAR)
    assert ground is not None and ground.grade == pytest.approx(reference, rel=1e-9) and ground.roll is None


def test_no_plane_without_a_path_into_the_bev() -> None:
    pose, path = path_over(hill)
    empty = PathAhead(np.zeros((0, 4, 4)), np.zeros((0, 2)), 6.5, False)
    assert ground_ahead(pose, empty, NEAR, FAR) is None
    # the sequence ends 1.5 m on
    _, short = path_over(hill, length=1.5)
    assert ground_ahead(pose, short, NEAR, FAR) is None
    # the robot turns away: its path runs sideways, never 2 m ahead of the frame's heading
    sideways = path.odometry.copy()
    sideways[:, :3, 3] = pose[:3, 3] + (sideways[:, :3, 3] - pose[:3, 3]) @ np.array(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    )
    turned = PathAhead(sideways, path.imu_roll_pitch, 6.5, True)
    assert ground_ahead(pose, turned, NEAR, FAR) is None
    # a path that leaves the BEV and comes back: what follows the exit is not used
    back = np.concatenate([path.odometry, path.odometry[::-1]])
    looped = PathAhead(back, np.concatenate([path.imu_roll_pitch] * 2), 14.0, True)
    assert ground_ahead(pose, looped, NEAR, FAR).grade == pytest.approx(expected_grade(hill), rel=1e-9)


def test_attitude_window_medians_over_metres_driven() -> None:
    window = AttitudeWindow(0.5)
    for i in range(20):
        window.add(0.1 * i, 0.01 * i, -0.02 if i == 10 else 0.003)
    window.add(0.5, 9.0, 9.0)  # not past the newest sample: ignored
    window.add(2.0, math.nan, 0.0)  # no attitude: ignored
    roll, pitch = window.median(1.0)  # samples 0.5 .. 1.5
    assert roll == pytest.approx(0.10) and pitch == pytest.approx(0.003)  # the bump's one sample is no median
    assert window.median(5.0) is None  # nothing within half a metre; older samples are dropped
    assert window.median(1.0) is None
    with pytest.raises(ValueError, match="half width"):
        AttitudeWindow(0.0)


def _frame(index: int, x: float, pitch: float, path: PathAhead | None) -> Frame:
    frame = Frame(index, 0.1 * index, np.zeros((480, 640), np.uint8), pose_from_xy_yaw(x, 0.0, 0.0), CALIBRATION)
    frame.imu_roll_pitch = (0.0, pitch)
    frame.path_ahead = path
    return frame


def test_the_stage_compensates_the_robot_against_the_plane_of_the_path_it_drove_next() -> None:
    stage = HindsightMotionCompensatedIPM(HindsightMotionCompensatedIpmParams())
    ahead = MotionCompensatedIPM(MotionCompensatedIpmParams(**AHEAD_MC))
    assert stage.read_ahead == 6.5 and ahead.read_ahead == 0.0
    stage.begin(RunContext(run_dir=None))
    ahead.begin(RunContext(run_dir=None))
    # flat ground: no path (live use) gives mc_ahead's compensation, frame for frame
    for k in range(30):
        pitch = 0.002 * (-1) ** k
        assert stage.compensation(_frame(k, STEP * k, pitch, None)) == ahead.compensation(
            _frame(k, STEP * k, pitch, None)
        )
    assert stage.hindsight_counts == {"hindsight_planes": 0, "hindsight_fallbacks": 30}
    # a hill begins 1 m ahead; the robot's own pitch is noise around the flat ground's
    _, path = path_over(hill, yaw=0.0)
    shifted = path.odometry.copy()
    shifted[:, 0, 3] += STEP * 30 - 2.0
    shifted[:, 1, 3] += 1.0
    path = PathAhead(shifted, path.imu_roll_pitch, path.distance, True)
    psi, theta = stage.compensation(_frame(30, STEP * 30, 0.002, path))
    # the robot is pitched nose down against the hill's plane by its grade's angle (its own 2 mrad shrunk out)
    assert theta == pytest.approx(math.atan(expected_grade(hill)), abs=5e-4)
    assert psi == pytest.approx(0.0, abs=1e-12)
    assert stage.last_ground is not None and stage.hindsight_counts["hindsight_planes"] == 1
    context = RunContext(run_dir=None)
    stage.finalize(context)
    assert context.metrics["ipm"]["hindsight_planes"] == 1 and context.metrics["ipm"]["frames"] == 31
    assert context.metrics["ipm"]["max_abs_pitch_compensation"] == pytest.approx(theta, abs=1e-6)


def test_the_accuracy_tool_gives_each_frame_the_path_the_runner_reads_ahead() -> None:
    from itertools import islice

    from sgf_experiments.ipm_accuracy import path_ahead
    from sgf_plugins.world import build_world

    from sgf_pipeline.runner import read_ahead

    world = build_world("campus_delivery", seed=0, scale=0.3, occluders=False, sensor_noise=False)
    frames = list(islice(read_ahead(((f, True) for f in world.frames(0, 250)), 6.5), 100))
    assert [f.index for f in frames] == list(range(100))
    for frame in frames[::9]:
        expected = path_ahead(world, frame.index, 6.5)
        assert frame.path_ahead is not None and frame.path_ahead.complete and expected.complete
        np.testing.assert_array_equal(frame.path_ahead.odometry, expected.odometry)
        np.testing.assert_array_equal(frame.path_ahead.imu_roll_pitch, expected.imu_roll_pitch)
        assert 40 < len(expected) < 100  # 6.5 m at the world's speed and 10 Hz
