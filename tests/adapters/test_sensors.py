"""IMU roll/pitch (orientation and complementary filter) and timestamp association of sensor streams."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sgf_pipeline.geometry import pose_from_xyz_rpy, quaternion_from_rotation, rotation_rpy, xy_yaw
from sgf_pipeline.imu import GRAVITY, roll_pitch_from_inertial, roll_pitch_of_base
from sgf_pipeline.timesync import PoseSeries, ValueSeries, first_disorder, interpolate_pose


def test_roll_pitch_of_a_rotated_imu():
    roll, pitch, yaw = 0.04, -0.07, 1.2
    base = rotation_rpy(roll, pitch, yaw)
    assert roll_pitch_of_base(quaternion_from_rotation(base)) == pytest.approx((roll, pitch), abs=1e-12)
    # an IMU mounted upside down and turned 90 degrees on the base reports a different orientation
    imu_to_base = rotation_rpy(math.pi, 0.0, math.pi / 2)
    world_imu = base @ imu_to_base
    got = roll_pitch_of_base(quaternion_from_rotation(world_imu), imu_to_base)
    assert got == pytest.approx((roll, pitch), abs=1e-12)


def _motion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch of a robot rocking over a bumpy path, and its yaw turning."""
    return 0.08 * np.sin(2.1 * t), 0.05 * np.sin(1.3 * t + 0.5)


def test_complementary_filter_tracks_roll_and_pitch():
    rate = 200.0
    t = np.arange(0.0, 20.0, 1.0 / rate)
    roll, pitch = _motion(t)
    yaw = 0.2 * t
    rotations = [rotation_rpy(r, p, y) for r, p, y in zip(roll, pitch, yaw, strict=True)]
    gyro = np.zeros((t.size, 3))
    for i in range(t.size - 1):  # body rates from consecutive attitudes
        delta = rotations[i].T @ rotations[i + 1]
        angle = math.acos(max(-1.0, min(1.0, (np.trace(delta) - 1) / 2)))
        axis = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]])
        gyro[i + 1] = axis / (2 * math.sin(angle)) * angle * rate if angle > 1e-12 else 0.0
    rng = np.random.default_rng(0)
    gyro += 0.002 + rng.normal(0, 0.003, gyro.shape)  # bias and noise
    accel = np.stack([r.T @ np.array([0.0, 0.0, GRAVITY]) for r in rotations]) + rng.normal(0, 0.05, (t.size, 3))
    estimate = roll_pitch_from_inertial(t, gyro, accel, gain=1.0)
    settled = t > 3.0
    error = np.abs(estimate[settled] - np.stack([roll, pitch], axis=1)[settled])
    assert error.max() < math.radians(0.6), np.degrees(error.max())
    # gyro alone drifts with the bias; accelerometer alone is noisy: the blend beats both
    gyro_only = roll_pitch_from_inertial(t, gyro, accel, gain=0.0)
    assert np.abs(gyro_only[-1] - [roll[-1], pitch[-1]]).max() > 2 * error.max()


def test_pose_series_interpolation_and_limits():
    ts = np.array([0.0, 0.1, 0.2, 0.3])
    poses = np.stack([pose_from_xyz_rpy(x, 0, 0, 0, 0, yaw) for x, yaw in [(0, 0), (1, 0.2), (2, 0.4), (3, 0.6)]])
    series = PoseSeries(ts, poses, "odometry")
    np.testing.assert_array_equal(series.at(0.1, 0.01), poses[1])  # an exact stamp: the sample itself
    mid = series.at(0.125, 0.03)
    assert mid is not None
    assert xy_yaw(mid) == pytest.approx((1.25, 0.0, 0.25), abs=1e-12)
    assert series.at(0.15, 0.04) is None  # both samples 0.05 s away
    nearest = series.at(0.12, 0.03, interpolate=False)
    np.testing.assert_array_equal(nearest, poses[1])
    np.testing.assert_array_equal(series.at(0.305, 0.01), poses[3])  # just after the end: the end sample
    assert series.at(0.32, 0.01) is None
    assert series.span() == (0.0, 0.3)
    halfway = interpolate_pose(poses[0], poses[3], 0.5)
    assert xy_yaw(halfway) == pytest.approx((1.5, 0.0, 0.3), abs=1e-12)
    values = ValueSeries(ts, np.array([[0.0, 1.0], [1.0, 3.0], [2.0, 5.0], [3.0, 7.0]]))
    assert values.at(0.05, 0.06) == pytest.approx([0.5, 2.0])
    with pytest.raises(ValueError, match="increase strictly"):
        PoseSeries(np.array([0.0, 0.0]), poses[:2])
    assert first_disorder(np.array([0.0, 1.0, 1.0, 2.0])) == 2 and first_disorder(ts) is None
