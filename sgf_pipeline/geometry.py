"""Small SE(2)/SE(3) helpers on 4x4 homogeneous matrices."""

from __future__ import annotations

import math

import numpy as np


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def pose_from_xyz_rpy(x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> np.ndarray:
    """4x4 pose from a translation and roll, pitch, yaw (rad)."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_rpy(roll, pitch, yaw)
    pose[:3, 3] = (x, y, z)
    return pose


def rpy_from_rotation(rot: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of a rotation matrix, the inverse of :func:`rotation_rpy`."""
    pitch = math.asin(max(-1.0, min(1.0, -float(rot[2, 0]))))
    roll = math.atan2(float(rot[2, 1]), float(rot[2, 2]))
    yaw = math.atan2(float(rot[1, 0]), float(rot[0, 0]))
    return roll, pitch, yaw


def pose_from_xy_yaw(x: float, y: float, yaw: float) -> np.ndarray:
    """4x4 planar pose."""
    return pose_from_xyz_rpy(x, y, 0.0, 0.0, 0.0, yaw)


def xy_yaw(pose: np.ndarray) -> tuple[float, float, float]:
    """Planar part ``(x, y, yaw)`` of a 4x4 pose."""
    return float(pose[0, 3]), float(pose[1, 3]), math.atan2(float(pose[1, 0]), float(pose[0, 0]))


def invert(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid homogeneous transform: 4x4 (3-D) or 3x3 (planar)."""
    n = pose.shape[0] - 1
    inv = np.eye(n + 1)
    rot = pose[:n, :n]
    inv[:n, :n] = rot.T
    inv[:n, n] = -rot.T @ pose[:n, n]
    return inv


def relative(pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """Pose of ``b`` in the frame of ``a``: ``inv(a) @ b``."""
    return invert(pose_a) @ pose_b


def wrap_angle(angle: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def quaternion_from_rotation(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix (TUM order)."""
    m = rot
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 0.5 / math.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) * s, (m[0, 2] - m[2, 0]) * s, (m[1, 0] - m[0, 1]) * s, 0.25 / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    quat = np.asarray(q, dtype=np.float64)
    quat /= np.linalg.norm(quat)
    return quat if quat[3] >= 0 else -quat


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``(x, y, z, w)``."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
