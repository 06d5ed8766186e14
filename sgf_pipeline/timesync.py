"""Associating sensor streams by timestamp: poses and IMU attitude sampled at camera times.

A robot's camera, wheel odometry and IMU tick on their own clocks. The adapters look each
camera timestamp up in the other streams: a sample taken at exactly that time is used as it is;
otherwise, with ``interpolate``, the two samples around it are blended (translation linearly,
rotation by slerp) as long as the nearer is within ``max_diff`` seconds; without it the
nearest sample within ``max_diff`` is used. Just before the first or after the last sample the
end sample is used if it is within ``max_diff``; further out there is no value.
"""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.geometry import quaternion_from_rotation, rotation_from_quaternion


def _slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions ``(x, y, z, w)`` at weight ``w`` in [0, 1]."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + w * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(1.0, dot))
    s = math.sin(theta)
    return (math.sin((1.0 - w) * theta) * q0 + math.sin(w * theta) * q1) / s


def interpolate_pose(pose0: np.ndarray, pose1: np.ndarray, w: float) -> np.ndarray:
    """The pose a fraction ``w`` of the way from ``pose0`` to ``pose1`` (linear translation, slerp rotation)."""
    out = np.eye(4)
    q = _slerp(quaternion_from_rotation(pose0[:3, :3]), quaternion_from_rotation(pose1[:3, :3]), w)
    out[:3, :3] = rotation_from_quaternion(q)
    out[:3, 3] = (1.0 - w) * pose0[:3, 3] + w * pose1[:3, 3]
    return out


class _Series:
    """Samples at strictly increasing timestamps (seconds)."""

    def __init__(self, timestamps: np.ndarray, name: str) -> None:
        ts = np.asarray(timestamps, dtype=np.float64)
        if ts.ndim != 1:
            raise ValueError(f"{name}: timestamps must be one-dimensional")
        if ts.size > 1 and np.any(np.diff(ts) <= 0):
            raise ValueError(f"{name}: timestamps must increase strictly")
        self.timestamps = ts
        self.name = name

    def __len__(self) -> int:
        return int(self.timestamps.size)

    def span(self) -> tuple[float, float] | None:
        """First and last timestamp, or ``None`` when empty."""
        return (float(self.timestamps[0]), float(self.timestamps[-1])) if len(self) else None

    def _locate(self, t: float, max_diff: float, interpolate: bool) -> tuple[int, int, float] | None:
        """``(i, j, w)``: the value at ``t`` is sample ``i`` blended with ``j`` at weight ``w``."""
        ts = self.timestamps
        n = ts.size
        if n == 0:
            return None
        j = int(np.searchsorted(ts, t, side="left"))
        if j < n and ts[j] == t:
            return j, j, 0.0
        before = j - 1 if j > 0 else None
        after = j if j < n else None
        d_before = t - ts[before] if before is not None else math.inf
        d_after = ts[after] - t if after is not None else math.inf
        if min(d_before, d_after) > max_diff:
            return None
        if interpolate and before is not None and after is not None:
            return before, after, float(d_before / (ts[after] - ts[before]))
        nearest = before if d_before <= d_after else after
        assert nearest is not None
        return nearest, nearest, 0.0


class PoseSeries(_Series):
    """A stream of timed 4x4 poses (odometry, ground truth) that can be sampled at other times."""

    def __init__(self, timestamps: np.ndarray, poses: np.ndarray, name: str = "poses") -> None:
        super().__init__(timestamps, name)
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != (len(self), 4, 4):
            raise ValueError(f"{name}: expected ({len(self)}, 4, 4) poses, got {poses.shape}")
        self.poses = poses

    def at(self, t: float, max_diff: float, interpolate: bool = True) -> np.ndarray | None:
        """The pose at time ``t``, or ``None`` when no sample is close enough."""
        found = self._locate(t, max_diff, interpolate)
        if found is None:
            return None
        i, j, w = found
        if i == j or w == 0.0:
            return self.poses[i].copy()
        return interpolate_pose(self.poses[i], self.poses[j], w)


class ValueSeries(_Series):
    """A stream of timed vectors (IMU roll and pitch) that can be sampled at other times."""

    def __init__(self, timestamps: np.ndarray, values: np.ndarray, name: str = "values") -> None:
        super().__init__(timestamps, name)
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] != len(self):
            raise ValueError(f"{name}: expected ({len(self)}, k) values, got {values.shape}")
        self.values = values

    def at(self, t: float, max_diff: float, interpolate: bool = True) -> np.ndarray | None:
        """The value at time ``t`` (linear between samples), or ``None`` when no sample is close enough."""
        found = self._locate(t, max_diff, interpolate)
        if found is None:
            return None
        i, j, w = found
        if i == j or w == 0.0:
            return self.values[i].copy()
        return (1.0 - w) * self.values[i] + w * self.values[j]


def first_disorder(timestamps: np.ndarray) -> int | None:
    """Index of the first timestamp not strictly after its predecessor, or ``None``."""
    ts = np.asarray(timestamps, dtype=np.float64)
    if ts.size < 2:
        return None
    bad = np.flatnonzero(np.diff(ts) <= 0)
    return int(bad[0]) + 1 if bad.size else None
