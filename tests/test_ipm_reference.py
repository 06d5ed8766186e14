"""The MC-IPM reference attitude: queue of N poses, pitch outliers left out (paper: N=50, d_theta=0.025)."""

from __future__ import annotations

import numpy as np
import pytest
from sgf_plugins.ipm import PoseQueue


def _fill(queue: PoseQueue, pitches, roll: float = 0.0) -> None:
    for p in pitches:
        queue.push(roll, p)


def test_a_bump_does_not_move_the_reference() -> None:
    queue = PoseQueue(50, 0.025)
    _fill(queue, [0.002, -0.001] * 20)
    for p in (-0.06, -0.04, 0.03, 0.06, 0.04):  # the bump: front wheels up, then down
        queue.push(0.0, p)
        reference = queue.reference()
        assert reference.pitch == pytest.approx(0.0005, abs=1e-12)  # mean of the 40 flat poses only
        assert reference.inliers == 40
        assert p - reference.pitch == pytest.approx(p - 0.0005)  # theta is the bump's own pitch


def test_a_slope_becomes_the_reference_after_half_a_queue() -> None:
    queue = PoseQueue(50, 0.025)
    _fill(queue, [0.0] * 50)
    references = []
    for _ in range(40):
        queue.push(0.0, -0.08)  # uphill
        references.append(queue.reference().pitch)
    assert np.allclose(references[:24], 0.0)  # up to 24 of 50 poses on the slope: still the flat
    assert references[24] == pytest.approx(-0.04)  # 25 of 50: the median lies between, no inlier
    assert np.allclose(references[25:], -0.08)  # from N/2 + 1 poses on: the slope


def test_the_literal_mean_centre_is_dragged_between_levels() -> None:
    """center=mean (average first, then exclude) follows the slope later than the median (documented choice)."""
    median, mean = PoseQueue(50, 0.025, "median"), PoseQueue(50, 0.025, "mean")
    for q in (median, mean):
        _fill(q, [0.0] * 50)
    followed = {}
    for name, q in (("median", median), ("mean", mean)):
        for k in range(1, 51):
            q.push(0.0, -0.08)
            if abs(q.reference().pitch + 0.08) < 1e-9:
                followed[name] = k
                break
    assert followed["median"] == 26
    assert followed["mean"] > followed["median"]


def test_roll_is_averaged_over_the_pitch_inliers_and_optionally_filtered() -> None:
    plain, filtered = PoseQueue(10, 0.025), PoseQueue(10, 0.025, roll_threshold=0.02)
    for q in (plain, filtered):
        _fill(q, [0.0] * 9, roll=0.01)
        q.push(0.05, 0.0)  # a crack under one wheel: roll only
    assert plain.reference().roll == pytest.approx((9 * 0.01 + 0.05) / 10)
    assert filtered.reference().roll == pytest.approx(0.01)
    assert filtered.reference().inliers == 9


def test_queue_keeps_the_last_n_and_resets() -> None:
    queue = PoseQueue(3, 0.025)
    _fill(queue, [0.1, 0.0, 0.0, 0.0])
    assert len(queue) == 3 and queue.reference().pitch == 0.0
    queue.reset()
    assert len(queue) == 0
    with pytest.raises(ValueError, match="empty"):
        queue.reference()
    with pytest.raises(ValueError, match="at least one"):
        PoseQueue(0)


def test_settle_follows_a_slope_after_k_poses_but_not_a_bump():
    """The settle extension: a constant new pitch (a slope) takes over after `settle` poses."""
    slope = PoseQueue(50, 0.025, settle=6)
    for _ in range(50):
        slope.push(0.0, 0.0)
    for i in range(10):
        slope.push(0.0, 0.08)
        expected = 0.08 if i >= 5 else 0.0
        assert slope.reference().pitch == pytest.approx(expected), i
    assert len(slope) == 10

    bump = PoseQueue(50, 0.025, settle=6)
    for _ in range(50):
        bump.push(0.0, 0.0)
    for pitch in (0.03, 0.07, 0.09, 0.05, 0.0, -0.05, -0.08, -0.04, 0.0):  # up the bump, then down
        bump.push(0.0, pitch)
        assert bump.reference().pitch == pytest.approx(0.0)
    assert len(bump) == 50
    with pytest.raises(ValueError, match="settle must lie in"):
        PoseQueue(10, 0.025, settle=10)


def test_a_line_follows_a_hill_without_lag_and_sees_the_ground_ahead() -> None:
    """fit=line: pitch over distance; on a grade that changes by 0.01 rad per metre the mean lags 3 m behind."""
    line, mean = PoseQueue(50, 0.025, fit="line", lookahead=2.0), PoseQueue(50, 0.025)
    rng = np.random.default_rng(0)
    for k in range(120):
        s = 0.12 * k  # metres travelled
        pitch = -0.01 * s + rng.normal(0.0, 0.0026)  # uphill, ever steeper, with the IMU's noise
        if k == 100:
            pitch += 0.06  # a bump's pose: left out of the line
        for queue in (line, mean):
            queue.push(0.0, pitch, 0.12 if k else 0.0)
    s_now = 0.12 * 119
    here, ahead = line.reference(), mean.reference()
    assert here.pitch == pytest.approx(-0.01 * s_now, abs=0.002)  # the ground under the robot, no lag
    assert here.target_pitch == pytest.approx(-0.01 * (s_now + 2.0), abs=0.003)  # and 2 m ahead
    assert here.inliers == 49  # the bump's pose is not on the line
    assert ahead.target_pitch == ahead.pitch  # the paper's mean knows no ground ahead
    assert ahead.pitch == pytest.approx(-0.01 * (s_now - 2.94), abs=0.002)  # half a queue (2.94 m) behind


def test_a_line_needs_distance_and_bounds_its_extrapolation() -> None:
    still = PoseQueue(50, 0.025, fit="line", lookahead=2.0)
    for k in range(50):
        still.push(0.0, 0.001 * k)  # the robot stands still while its pitch creeps: no slope over distance
    assert still.reference().pitch == pytest.approx(np.mean(0.001 * np.arange(50)))
    assert still.reference().target_pitch == still.reference().pitch
    steep = PoseQueue(50, 0.025, fit="line", lookahead=10.0)
    for k in range(50):
        steep.push(0.0, -0.02 * 0.1 * k, 0.1)  # 0.02 rad per metre: 0.2 rad over 10 m
    reference = steep.reference()
    assert reference.target_pitch - reference.pitch == pytest.approx(-0.025)  # bounded by pitch_threshold
    with pytest.raises(ValueError, match="fit='line'"):
        PoseQueue(50, 0.025, lookahead=1.0)
