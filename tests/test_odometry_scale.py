"""The odometry's scale error measured from the camera (``odometry_scale=bev_motion``) and applied by the back-end."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from sgf_plugins.backend.lm import GtsamLmBackend
from sgf_plugins.backend.params import LmParams
from sgf_plugins.odometry.scale import BevMotionParams, BevMotionScale, NoOdometryScale
from sgf_plugins.shared.heading_bias import ScaledOdometry
from sgf_plugins.world import build_world

from sgf_pipeline import RunContext
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.types import CameraImage, OdometryScale


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A ground texture (sum of sines, like asphalt grain at several scales), any real (x, y) in metres."""
    rng = np.random.default_rng(7)
    out = np.zeros_like(x)
    for _ in range(40):
        k = rng.uniform(2.0, 25.0)
        a = rng.uniform(0.0, 2.0 * math.pi)
        out += np.sin(k * (math.cos(a) * x + math.sin(a) * y) + rng.uniform(0, 2 * math.pi)) / math.sqrt(k)
    return (128.0 + 40.0 * out).astype(np.float32)


def _view(stage: BevMotionScale, pose: np.ndarray, attitude: float = 0.0) -> np.ndarray:
    """The stage's near-ground view from a planar pose (3x3); ``attitude``: a pitch-like error (x, y)(1 + a x)."""
    x, y = stage._x * (1.0 + attitude * stage._x), stage._y * (1.0 + attitude * stage._x)
    return _texture(pose[0, 0] * x + pose[0, 1] * y + pose[0, 2], pose[1, 0] * x + pose[1, 1] * y + pose[1, 2])


def _planar(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    ("error", "turn_deg", "attitude", "heading_deg"),
    [(0.02, 0.0, 0.0, 0.3), (-0.015, 4.0, 0.0, -0.2), (0.01, 2.0, 0.002, 0.0)],
)
def test_the_odometrys_relative_error_is_measured_from_two_views(
    error: float, turn_deg: float, attitude: float, heading_deg: float
) -> None:
    stage = BevMotionScale(BevMotionParams())
    start, end = _planar(3.0, -1.0, 0.3), _planar(3.0, -1.0, 0.3) @ _planar(1.0, 0.05, math.radians(turn_deg))
    true = np.linalg.inv(start) @ end
    odometry = true @ _planar(0.0, 0.0, math.radians(heading_deg))  # the odometry turned this much too far
    odometry[:2, 2] *= 1.0 + error  # the wheels counted this much too far
    measured = stage.measure(_view(stage, end, attitude), _view(stage, start), odometry)
    assert measured is not None
    assert measured.scale == pytest.approx(error, abs=0.002)
    # the view's edge 1.25 m to the side moves 0.8 mm (0.04 pixels) per 0.04 degrees of turn
    length = float(np.hypot(*odometry[:2, 2]))
    assert math.degrees(measured.yaw_rate) == pytest.approx(heading_deg / length, abs=0.04)


def test_a_blank_ground_gives_no_measurement() -> None:
    stage = BevMotionScale(BevMotionParams())
    blank = np.full(stage._x.shape, 90.0, dtype=np.float32)
    assert stage.measure(blank, blank, _planar(1.0, 0.0, 0.0)) is None


def test_the_estimate_is_the_median_once_enough_measurements_agree() -> None:
    stage = BevMotionScale(BevMotionParams(min_pairs=5))
    stage.begin(RunContext(run_dir=None))
    stage.errors = [0.012, 0.011, 0.013]
    stage.yaw_rates, stage.lengths = [0.0] * 3, [1.0] * 3
    stage._measured_from, stage._travelled = 0.0, 3.0
    assert stage.estimate() == OdometryScale(1.0, math.inf, 3)  # too few: the odometry as it is
    stage.errors += [0.012, 0.5, 0.010]  # one bad fit among them does not move the median
    stage.yaw_rates += [0.0] * 3
    stage.lengths += [1.0] * 3
    stage._travelled = 6.0
    final = stage.estimate()
    assert final.factor == pytest.approx(1.0 / 1.012)
    assert 0.0 < final.sigma < 0.002
    assert final.pairs == 6


def test_the_odometrys_random_walks_are_read_from_the_spread_of_the_measurements() -> None:
    """Errors over L metres spread by sigma sqrt(L): the walks come back as upper bounds within their own error."""
    rng = np.random.default_rng(7)
    n, sigma_xy, sigma_yaw = 2000, 0.01, math.radians(0.05)
    lengths = rng.uniform(1.0, 1.6, n)
    stage = BevMotionScale(BevMotionParams())
    stage.begin(RunContext(run_dir=None))
    stage.errors = list(0.012 + rng.normal(0.0, 1.0, n) * sigma_xy / np.sqrt(lengths))
    stage.yaw_rates = list(math.radians(0.07) + rng.normal(0.0, 1.0, n) * sigma_yaw / np.sqrt(lengths))
    stage.lengths = list(lengths)
    stage._measured_from, stage._travelled = 0.0, float(n)  # n independent stretches one baseline long
    estimate = stage.estimate()
    raised = 1.0 + 2.0 * 1.1664 / math.sqrt(n)  # the spread raised by twice its standard error
    tolerance = 4.0 * 1.1664 / math.sqrt(n)  # four standard errors of a spread from n values
    assert estimate.sigma_xy / raised == pytest.approx(sigma_xy, rel=tolerance)
    assert estimate.sigma_yaw / raised == pytest.approx(sigma_yaw, rel=tolerance)
    assert estimate.factor == pytest.approx(1.0 / 1.012, abs=4.0 * 1.2533 * sigma_xy / math.sqrt(n))
    # views one baseline apart overlap: a quarter of the stretches leaves twice the factor's uncertainty
    stage._travelled = n / 4.0
    assert stage.estimate().sigma == pytest.approx(2.0 * estimate.sigma, rel=1e-12)


def test_bad_parameters_are_refused_before_any_frame() -> None:
    with pytest.raises(ValueError, match="x_max"):
        BevMotionScale(BevMotionParams(x_min=3.0, x_max=2.0))
    with pytest.raises(ValueError, match="max_baseline"):
        BevMotionScale(BevMotionParams(baseline=1.0, max_baseline=0.8))


@pytest.mark.parametrize("preset", ["campus_delivery", "campus_large_loop_night"])
def test_the_world_robots_scale_error_is_recovered_from_its_camera(preset: str) -> None:
    """On the rendered campus (sensor noise and occluders on; at night in the headlight), the over-counted distance is seen."""
    world = build_world(preset, seed=0, scale=0.3)
    stage = BevMotionScale(BevMotionParams())
    stage.begin(RunContext(run_dir=None))
    travelled = truth = 0.0
    previous = None
    for k in range(0, 200, 2):  # about 0.25 m apart, like the pipeline's keyframes
        frame = world.frame(k)
        estimate = stage.process(frame, CameraImage(frame.image, k))
        if previous is not None:
            travelled += float(np.linalg.norm(frame.odometry[:2, 3] - previous.odometry[:2, 3]))
            truth += float(np.linalg.norm(frame.ground_truth[:2, 3] - previous.ground_truth[:2, 3]))
        previous = frame
    assert estimate.pairs >= 60
    true_factor = truth / travelled
    assert true_factor < 0.995  # the world's odometry does over-count here
    assert estimate.factor == pytest.approx(true_factor, abs=0.004)
    assert NoOdometryScale(NoOdometryScale.Params()).process(frame) == OdometryScale(1.0, 0.0, 0)


@pytest.mark.parametrize("bias", [0.3, -0.3])
def test_a_robots_heading_bias_is_measured_by_its_camera_before_any_loop(bias: float) -> None:
    """A robot whose odometry turns 0.3 deg/m either way: the ground's turn between views shows it within 40 m."""
    world = build_world(
        "campus_delivery", seed=5, scale=0.3, odometry_yaw_bias_deg_per_m=bias, odometry_yaw_bias_seeded_sign=False
    )
    stage, off = BevMotionScale(BevMotionParams()), BevMotionScale(BevMotionParams(heading=False))
    stage.begin(RunContext(run_dir=None))
    off.begin(RunContext(run_dir=None))
    for k in range(0, 300, 2):
        frame = world.frame(k)
        estimate = stage.process(frame, CameraImage(frame.image, k))
        scale_only = off.process(frame, CameraImage(frame.image, k))
    sigma = math.degrees(estimate.yaw_bias_sigma)
    assert 0.0 < sigma < 0.1  # about 40 independent metres of views
    assert abs(math.degrees(estimate.yaw_bias) - bias) < 4.0 * sigma
    assert scale_only.factor == estimate.factor and scale_only.yaw_bias_sigma == math.inf  # heading=false


def test_scaled_odometry_scales_each_step_by_the_factor_of_its_time() -> None:
    scaled = ScaledOdometry()
    poses = [pose_from_xy_yaw(float(k), 0.0, 0.0) for k in range(4)]
    assert np.array_equal(scaled.correct(poses[0], 1.0), poses[0])
    assert np.array_equal(scaled.correct(poses[1], 1.0), poses[1])  # unchanged until a factor arrives
    assert scaled.correct(poses[2], 0.5)[0, 3] == pytest.approx(1.5)
    assert scaled.correct(poses[3], 0.8)[0, 3] == pytest.approx(2.3)
    with pytest.raises(ValueError, match="finite and positive"):
        scaled.correct(poses[3], float("nan"))


def test_the_back_end_adds_the_odometry_scaled() -> None:
    world = build_world("campus_delivery", seed=0, scale=0.3)
    lengths = []
    for factor in (1.0, 0.9):
        backend = GtsamLmBackend(LmParams(save_map=False))
        backend.begin(RunContext(run_dir=None))
        for k in range(0, 40, 4):
            estimate = backend.process(world.frame(k), None, OdometryScale(factor, 0.001, 50))
        poses = [estimate.poses[k] for k in range(0, 40, 4)]
        lengths.append(sum(float(np.linalg.norm(b[:2, 3] - a[:2, 3])) for a, b in itertools.pairwise(poses)))
    assert lengths[1] == pytest.approx(0.9 * lengths[0], rel=1e-6)
