"""The robot's roll and pitch from an IMU: from its orientation output, or from gyro and accelerometer.

MC-IPM (paper Sec. III-A) needs the base's roll and pitch relative to gravity. An IMU with an
on-board filter reports an orientation (ROS ``sensor_msgs/Imu.orientation``); a raw IMU (EuRoC's
``imu0``) reports angular velocity and specific force only, and :func:`roll_pitch_from_inertial`
integrates them with a complementary filter: the gyro carries the fast motion, the accelerometer's
gravity direction pulls the slow drift back. Yaw is not observable from gravity and is not used.
"""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.geometry import rotation_from_quaternion, rpy_from_rotation

GRAVITY = 9.80665


def shrink_noise(deviation: float, sigma: float) -> float:
    """``d^3 / (d^2 + sigma^2)``: a deviation ``d`` with the noise of standard deviation ``sigma`` shrunk out.

    Deviations of the noise's size are mostly dropped, large ones (a speed bump's pitch) kept whole;
    ``sigma <= 0`` keeps every deviation.
    """
    if sigma <= 0.0:
        return deviation
    return deviation * deviation * deviation / (deviation * deviation + sigma * sigma)


def steadied(own: float, smooth: float, sigma: float) -> float:
    """``smooth`` plus ``own``'s deviation from it through :func:`shrink_noise` (the angle steadied)."""
    return smooth + shrink_noise(own - smooth, sigma)


def steadied_roll_pitch(roll_pitch: np.ndarray, centre: int, sigma: float) -> tuple[float, float]:
    """Roll and pitch (rad) of sample ``centre`` of (N, 2) samples around it, the IMU's white noise shrunk out.

    The median of the samples, plus the centre's own deviation from it through :func:`shrink_noise`:
    on steady ground the noise averages away, on a bump the centre keeps its own attitude.
    """
    samples = np.asarray(roll_pitch, dtype=np.float64).reshape(-1, 2)
    median = np.median(samples, axis=0)
    roll, pitch = (steadied(float(samples[centre, k]), float(m), sigma) for k, m in enumerate(median))
    return roll, pitch


def roll_pitch_of_base(imu_orientation: np.ndarray, imu_to_base: np.ndarray | None = None) -> tuple[float, float]:
    """Roll and pitch (rad) of the base from an IMU orientation ``(x, y, z, w)`` in a z-up world frame.

    ``imu_to_base`` is the 3x3 (or 4x4) pose of the IMU frame in the base frame (identity when the
    IMU axes are the base's: x forward, y left, z up).
    """
    world_imu = rotation_from_quaternion(np.asarray(imu_orientation, dtype=np.float64))
    base_imu = np.eye(3) if imu_to_base is None else np.asarray(imu_to_base, dtype=np.float64)[:3, :3]
    roll, pitch, _ = rpy_from_rotation(world_imu @ base_imu.T)
    return roll, pitch


def _exp_so3(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-12:
        return np.eye(3)
    k = omega / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def roll_pitch_from_inertial(
    timestamps: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    gain: float = 1.0,
    imu_to_base: np.ndarray | None = None,
    accel_tolerance: float = 0.15,
) -> np.ndarray:
    """(N, 2) roll and pitch (rad) of the base from gyro (rad/s) and accelerometer (m/s^2) samples.

    A complementary filter on SO(3): the attitude follows the gyro, and the measured gravity
    direction corrects it at ``gain`` rad/s per rad of tilt error (time constant ``1/gain`` s),
    only while the specific force is within ``accel_tolerance`` of 1 g (no strong acceleration).
    The first sample's accelerometer gives the initial roll and pitch.
    """
    ts = np.asarray(timestamps, dtype=np.float64)
    rot = np.eye(3) if imu_to_base is None else np.asarray(imu_to_base, dtype=np.float64)[:3, :3]
    w = np.asarray(gyro, dtype=np.float64) @ rot.T
    a = np.asarray(accel, dtype=np.float64) @ rot.T
    n = ts.size
    out = np.zeros((n, 2))
    if n == 0:
        return out
    a0 = a[0] / max(np.linalg.norm(a[0]), 1e-9)
    roll0 = math.atan2(a0[1], a0[2])
    pitch0 = math.atan2(-a0[0], math.hypot(a0[1], a0[2]))
    attitude = np.array(
        [
            [math.cos(pitch0), math.sin(pitch0) * math.sin(roll0), math.sin(pitch0) * math.cos(roll0)],
            [0.0, math.cos(roll0), -math.sin(roll0)],
            [-math.sin(pitch0), math.cos(pitch0) * math.sin(roll0), math.cos(pitch0) * math.cos(roll0)],
        ]
    )
    out[0] = (roll0, pitch0)
    for i in range(1, n):
        dt = ts[i] - ts[i - 1]
        omega = 0.5 * (w[i] + w[i - 1])
        norm = float(np.linalg.norm(a[i]))
        if gain > 0.0 and abs(norm - GRAVITY) <= accel_tolerance * GRAVITY:
            up_estimated = attitude[2]  # world z in base coordinates: third row of R_world_base
            omega = omega + gain * np.cross(a[i] / norm, up_estimated)
        attitude = attitude @ _exp_so3(omega * dt)
        roll, pitch, _ = rpy_from_rotation(attitude)
        out[i] = (roll, pitch)
    return out
