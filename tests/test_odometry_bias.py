"""The odometry's heading bias from loops (sgf_plugins.shared.heading_bias): the estimate, its robustness, the correction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sgf_plugins.backend.params import Isam2Params, LmParams
from sgf_plugins.shared.heading_bias import MAX_YAW_BIAS, HeadingBias, with_heading_bias

from sgf_pipeline.geometry import invert, pose_from_xy_yaw, rotation_rpy, rpy_from_rotation, xy_yaw

BIAS = math.radians(0.07)  # rad per metre, the campus presets' bias


def circuit(laps: int, bias: float, rng: np.random.Generator, step: float = 1.0, radius: float = 80.0):
    """Ground truth and biased odometry around a circle, ``step`` m per frame (heading noise 0.001 rad/sqrt(m))."""
    n = round(laps * 2 * math.pi * radius / step)
    turn = step / radius
    gt = [pose_from_xy_yaw(0.0, 0.0, 0.0)]
    odo = [gt[0]]
    for _ in range(n - 1):
        true_step = pose_from_xy_yaw(step, 0.0, turn)
        gt.append(gt[-1] @ true_step)
        measured = pose_from_xy_yaw(step, 0.0, turn + bias * step + rng.normal(0.0, 0.001 * math.sqrt(step)))
        odo.append(odo[-1] @ measured)
    return np.stack(gt), np.stack(odo)


def feed(estimator: HeadingBias, odometry: np.ndarray) -> np.ndarray:
    return np.stack([estimator.correct(k, pose) for k, pose in enumerate(odometry)])


def two_laps() -> tuple[np.ndarray, np.ndarray, HeadingBias]:
    """Two laps of the circuit (seed 1): truth, odometry, and an estimator that has seen every frame."""
    gt, odo = circuit(2, BIAS, np.random.default_rng(1))
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5))
    feed(estimator, odo)
    return gt, odo, estimator


def test_loops_measure_the_bias_and_the_odometry_after_them_is_turned_back():
    rng = np.random.default_rng(0)
    gt, odo = circuit(3, BIAS, rng)
    lap = len(gt) // 3
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5))
    corrected = [estimator.correct(k, odo[k]) for k in range(lap + 10)]
    np.testing.assert_allclose(corrected, odo[: lap + 10], atol=1e-9)  # nothing known yet: the odometry itself
    # three loops between the first two laps, measured from the ground truth (1 degree of ICP noise)
    first_applied = None
    for a in (5, 60, 120):
        b = a + lap
        if b >= lap + 10:
            corrected += [estimator.correct(k, odo[k]) for k in range(len(corrected), b + 1)]
        yaw = xy_yaw(invert(gt[a]) @ gt[b])[2] + rng.normal(0.0, math.radians(1.0))
        assert estimator.observe(a, b, yaw, math.radians(1.0) ** 2)
        if estimator.value != 0.0 and first_applied is None:
            first_applied = len(corrected) - 1
        # ``since``: the newest frame when the bias was first applied, None while it is not
        assert estimator.since == first_applied
    assert first_applied == 60 + lap  # the second loop agrees with the first
    assert estimator.loops == 3
    assert math.degrees(estimator.value) == pytest.approx(0.07, abs=0.005)
    # from here on every step is turned back by the estimate: the third lap's heading drifts 20 times less
    start = len(corrected)
    corrected += [estimator.correct(k, odo[k]) for k in range(start, len(odo))]
    corrected_arr = np.stack(corrected)

    def heading_drift(poses: np.ndarray) -> float:
        relative = invert(poses[start]) @ poses[-1]
        truth = invert(gt[start]) @ gt[-1]
        return abs(xy_yaw(invert(truth) @ relative)[2])

    assert heading_drift(odo) == pytest.approx(BIAS * (len(odo) - 1 - start), rel=0.1)
    assert heading_drift(corrected_arr) < heading_drift(odo) / 20
    # each step keeps its length: only the heading is corrected
    steps = np.linalg.norm(np.diff(corrected_arr[:, :2, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0, atol=1e-9)


def test_a_false_loop_among_true_ones_barely_moves_the_estimate_and_alone_it_is_bounded():
    gt, odo, estimator = two_laps()
    lap = len(gt) // 2
    for a in range(0, 200, 25):
        b = a + lap
        assert estimator.observe(a, b, xy_yaw(invert(gt[a]) @ gt[b])[2], math.radians(1.0) ** 2)
    good = estimator.value
    # a false loop: the right frames' relative yaw off by 60 degrees
    a, b = 210, 210 + lap
    estimator.observe(a, b, xy_yaw(invert(gt[a]) @ gt[b])[2] + math.radians(60.0), math.radians(1.0) ** 2)
    assert abs(estimator.value - good) < 0.1 * abs(good)
    assert estimator.agreeing == 8  # the eight true loops agree with the estimate, the false one does not
    # alone, a loop over a short stretch that claims 90 degrees of turn is estimated (bounded) but not applied
    lone = HeadingBias(math.radians(0.5), math.radians(0.5))
    feed(lone, odo)
    lone.observe(10, 40, xy_yaw(invert(gt[10]) @ gt[40])[2] - math.radians(90.0), math.radians(1.0) ** 2)
    assert lone.estimate == pytest.approx(MAX_YAW_BIAS) and lone.value == 0.0 and lone.agreeing < 2
    # a second loop elsewhere that disagrees with it does not make it applied either
    lone.observe(100, 100 + lap, xy_yaw(invert(gt[100]) @ gt[100 + lap])[2], math.radians(1.0) ** 2)
    assert lone.agreeing < 2 and lone.value == 0.0


def test_a_false_loop_observed_first_does_not_decide_how_the_true_ones_are_read():
    """A turn is known modulo a full turn: each reading is a valley of the cost, and its global minimum wins."""
    gt, _, estimator = two_laps()
    lap = len(gt) // 2
    # first a look-alike laid the wrong way round, over a whole lap: 160 degrees off (campus_reverse_slope)
    a, b = 5, 5 + lap
    estimator.observe(a, b, xy_yaw(invert(gt[a]) @ gt[b])[2] - math.radians(160.0), math.radians(1.0) ** 2)
    # its turn, 35 + 160 degrees, is read the nearest way: -165 degrees
    assert math.degrees(estimator.estimate) == pytest.approx((0.07 * lap + 160.0 - 360.0) / lap, abs=0.01)
    for a in range(20, 220, 25):  # then eight true loops: read around that estimate, each would claim a turn more
        b = a + lap
        assert estimator.observe(a, b, xy_yaw(invert(gt[a]) @ gt[b])[2], math.radians(1.0) ** 2)
    assert math.degrees(estimator.value) == pytest.approx(0.07, abs=0.005)
    assert estimator.agreeing == 8


@pytest.mark.parametrize("off_deg", [-160.0, 160.0])
def test_a_false_loop_and_one_true_loop_do_not_agree_on_an_alias(off_deg: float) -> None:
    """Loops of 452, 493 and 535 m (campus_reverse_slope's first three): each turn read some way, two
    loops can meet at a bias of 0.6 deg/m. A cost that still grows with the outlier's residual (Cauchy)
    chose that alias, and the back-end turned 30 m of odometry by it; the bounded cost counts agreement."""
    gt, _, estimator = two_laps()
    applied = []
    for a, b, off in ((5, 5 + 452, off_deg), (20, 20 + 493, 0.0), (40, 40 + 535, 0.0)):
        yaw = xy_yaw(invert(gt[a]) @ gt[b])[2] + math.radians(off)
        assert estimator.observe(a, b, yaw, math.radians(1.5) ** 2)
        applied.append(math.degrees(estimator.value))
    assert applied[:2] == [0.0, 0.0]  # the two first disagree: nothing applied
    assert applied[2] == pytest.approx(0.07, abs=0.01)  # the two true loops agree, the false one does not
    assert estimator.agreeing == 2


def test_a_loop_to_an_unknown_frame_is_not_observed_and_frames_must_increase():
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5))
    estimator.correct(0, np.eye(4))
    estimator.correct(3, pose_from_xy_yaw(1.0, 0.0, 0.0))
    assert not estimator.observe(0, 5, 0.0, 1e-4) and not estimator.observe(1, 3, 0.0, 1e-4)
    assert estimator.loops == 0 and estimator.value == 0.0
    with pytest.raises(ValueError, match="frame 3 came after frame 3"):
        estimator.correct(3, pose_from_xy_yaw(2.0, 0.0, 0.0))
    assert estimator.observe(0, 3, 0.0, 1e-4) and estimator.loops == 1  # the refused frame left nothing behind


def test_a_bias_the_heading_noise_could_explain_is_estimated_but_not_applied():
    rng = np.random.default_rng(2)
    gt, odo = circuit(2, math.radians(0.01), rng)  # 0.01 deg/m: 5 degrees a lap, under the model's 11-degree noise
    lap = len(gt) // 2
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5))
    feed(estimator, odo)
    for a in (0, 50, 100):
        estimator.observe(a, a + lap, xy_yaw(invert(gt[a]) @ gt[a + lap])[2], math.radians(1.0) ** 2)
    assert estimator.agreeing == 3 and math.degrees(estimator.estimate) == pytest.approx(0.01, abs=0.005)
    assert abs(estimator.estimate) < estimator.significance * estimator.sigma and estimator.value == 0.0
    assert estimator.since is None
    # the same loops on a quieter odometry model make it significant
    quiet = HeadingBias(math.radians(0.5), math.radians(0.05))
    feed(quiet, odo)
    for a in (0, 50, 100):
        quiet.observe(a, a + lap, xy_yaw(invert(gt[a]) @ gt[a + lap])[2], math.radians(0.1) ** 2)
    assert quiet.value == quiet.estimate != 0.0


def test_a_known_bias_taken_off_from_the_first_frame_straightens_a_bent_drive() -> None:
    """``with_heading_bias``: odometry turning 0.3 deg/m on a straight, sloped drive comes out straight and level."""
    bias = math.radians(0.3)
    path, odometry = np.eye(4), []
    for k in range(200):
        pose = path.copy()
        pose[2, 3] = 0.01 * k  # height and pitch are the odometry's own and stay
        pose[:3, :3] = pose[:3, :3] @ rotation_rpy(0.0, 0.02, 0.0)
        odometry.append(pose)
        path = path @ pose_from_xy_yaw(0.5, 0.0, bias * math.hypot(0.5, 0.01))  # per metre of the 3-D path
    corrected = with_heading_bias(np.array(odometry), bias)
    x, y, yaw = np.array([xy_yaw(p) for p in corrected]).T
    np.testing.assert_allclose(x, 0.5 * np.arange(200), atol=1e-9)
    np.testing.assert_allclose(y, 0.0, atol=1e-9)
    np.testing.assert_allclose(yaw, 0.0, atol=1e-12)
    np.testing.assert_allclose(corrected[:, 2, 3], 0.01 * np.arange(200), atol=1e-12)
    assert rpy_from_rotation(corrected[100][:3, :3])[1] == pytest.approx(0.02, abs=1e-12)
    assert abs(xy_yaw(odometry[-1])[1]) > 20.0  # the drive it came from was bent far off the line


def lap_loops(reading_deg: float, seed: int) -> float:
    """27 loops one lap (1481 to 1500 m) apart, as on campus_large_loop: the bias (deg/m) the estimator reads."""
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5), reading_sigma=math.radians(reading_deg))
    for k in range(2600):
        estimator.correct(k, pose_from_xy_yaw(float(k), 0.0, 0.0))  # the turns are all in the loops below
    rng = np.random.default_rng(seed)
    for i in range(27):
        a, length = 10 + 40 * i, 1481 + int(rng.integers(0, 20))
        turn = -BIAS * length + math.radians(rng.normal(0.0, 6.0))  # the odometry turned by the bias, plus noise
        assert estimator.observe(a, a + length, -turn, math.radians(1.5) ** 2)
    return math.degrees(estimator.estimate)


def test_loops_of_one_lap_are_read_by_the_expected_bias_between_a_bias_and_its_alias() -> None:
    """Loops all one lap long cannot tell a bias b from b + 360 deg / lap (-0.07 from +0.17 deg/m).

    On campus_large_loop at full length (seed 0) the loose prior (0.5 deg/m) chose the alias, and the
    back-end turned the whole drive by it (ATE 169 m instead of 2.6); the expected bias (0.1 deg/m)
    chooses the reading, and the loose prior still refines it."""
    default = Isam2Params().heading_bias.reading_sigma_deg_per_m
    assert default == LmParams().heading_bias.reading_sigma_deg_per_m == 0.1
    loose = [lap_loops(0.5, seed) for seed in range(12)]
    assert any(b == pytest.approx(0.17, abs=0.005) for b in loose)  # the alias is there to be read
    assert all(b == pytest.approx(-0.07, abs=0.005) or b == pytest.approx(0.17, abs=0.005) for b in loose)
    assert all(lap_loops(default, seed) == pytest.approx(-0.07, abs=0.005) for seed in range(12))


def test_the_cameras_estimate_is_taken_off_before_any_loop() -> None:
    gt, odo = circuit(1, BIAS, np.random.default_rng(2))
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5))
    feed(estimator, odo[:100])
    assert estimator.value == 0.0 and estimator.since is None  # no loop, no camera: the odometry as it is
    estimator.camera(BIAS, BIAS / 4.0)  # the camera sees the bias at four sigmas
    assert estimator.value == pytest.approx(BIAS) and estimator.since == 99 and estimator.loops == 0
    assert estimator.residual_sigma == pytest.approx(BIAS / 4.0)
    # the odometry before frame 99 kept all of it: the gates count the measured bias there
    assert estimator.uncorrected_sigma == pytest.approx(math.hypot(BIAS, BIAS / 4.0))
    corrected = np.stack([estimator.correct(k, odo[k]) for k in range(100, len(odo))])

    # from then on the drive turns like the truth: the heading error stops growing
    def heading_error(poses: np.ndarray, k: int) -> float:
        return xy_yaw(invert(gt[k]) @ poses[k - 100])[2]

    drift = heading_error(corrected, len(odo) - 1) - heading_error(corrected, 100)
    raw = xy_yaw(invert(gt[-1]) @ odo[-1])[2] - xy_yaw(invert(gt[100]) @ odo[100])[2]
    assert raw == pytest.approx(BIAS * (len(odo) - 101), rel=0.1)
    assert abs(drift) < 0.1 * abs(raw)


def test_an_uncertain_camera_informs_without_correcting_and_a_vague_one_is_ignored() -> None:
    estimator = HeadingBias(math.radians(0.5), math.radians(0.5), reading_sigma=math.radians(0.1))
    feed(estimator, np.stack([pose_from_xy_yaw(float(k), 0.0, 0.0) for k in range(20)]))
    assert estimator.uncorrected_sigma == pytest.approx(math.radians(0.1))  # unmeasured: the bias expected
    estimator.camera(math.radians(1.0), math.radians(0.6))  # less certain than the prior: ignored
    estimator.camera(math.radians(0.01), math.inf)
    assert estimator.since is None and estimator.sigma == math.inf
    estimator.camera(math.radians(0.01), math.radians(0.02))  # within its own uncertainty of zero
    assert estimator.value == 0.0 and estimator.since == 19  # nothing taken off, but the bias is known small
    assert estimator.residual_sigma == pytest.approx(math.hypot(math.radians(0.02), math.radians(0.01)))
    assert estimator.uncorrected_sigma == pytest.approx(estimator.residual_sigma)  # nothing was taken off anywhere


def test_the_camera_reads_loops_of_one_lap_where_the_expected_bias_cannot() -> None:
    """Loops one lap long read a robot's bias (-0.14 deg/m) as its alias (+0.10) when zero is expected; not the camera."""
    loops = []
    rng = np.random.default_rng(3)
    for i in range(27):
        a, length = 10 + 40 * i, 1481 + int(rng.integers(0, 20))
        loops.append((a, length, -math.radians(0.14) * length + math.radians(rng.normal(0.0, 6.0))))

    def read(camera: tuple[float, float] | None) -> float:
        estimator = HeadingBias(math.radians(0.5), math.radians(0.5), reading_sigma=math.radians(0.02))
        for k in range(2600):
            estimator.correct(k, pose_from_xy_yaw(float(k), 0.0, 0.0))
        if camera is not None:
            estimator.camera(*camera)
        for a, length, turn in loops:
            estimator.observe(a, a + length, -turn, math.radians(1.5) ** 2)
        return math.degrees(estimator.estimate)

    alias = -0.14 + 360.0 / 1490.0  # one lap of 1481-1500 m
    assert read(None) == pytest.approx(alias, abs=0.01)  # an expectation of zero reads the alias
    assert read((math.radians(-0.13), math.radians(0.03))) == pytest.approx(-0.14, abs=0.005)
