"""Timed pose sequences and their file formats (TUM)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sgf_pipeline.geometry import quaternion_from_rotation, rotation_from_quaternion
from sgf_pipeline.io import atomic_write_text


class TrajectoryError(ValueError):
    """A trajectory file or array that cannot be used, with what is wrong in it."""


@dataclass(frozen=True)
class Trajectory:
    """Poses (N, 4, 4) at strictly increasing timestamps (N,) in seconds."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        ts = np.asarray(self.timestamps, dtype=np.float64)
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise TrajectoryError(f"poses must have shape (N, 4, 4), got {poses.shape}")
        if ts.shape != (poses.shape[0],):
            raise TrajectoryError(f"{ts.shape[0] if ts.ndim else 0} timestamps for {poses.shape[0]} poses")
        if not np.all(np.isfinite(ts)) or not np.all(np.isfinite(poses)):
            bad = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)) | ~np.isfinite(ts))
            raise TrajectoryError(f"non-finite pose or timestamp at row(s) {bad[:5].tolist()}")
        if ts.size > 1 and np.any(np.diff(ts) <= 0):
            row = int(np.flatnonzero(np.diff(ts) <= 0)[0]) + 1
            raise TrajectoryError(f"timestamps must increase strictly; row {row} has {ts[row]!r} after {ts[row - 1]!r}")
        object.__setattr__(self, "timestamps", ts)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) positions."""
        return self.poses[:, :3, 3]

    @property
    def length(self) -> float:
        """Path length in metres."""
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


def write_tum(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines atomically."""
    lines = []
    for t, pose in zip(trajectory.timestamps, trajectory.poses, strict=True):
        q = quaternion_from_rotation(pose[:3, :3])
        x, y, z = pose[:3, 3]
        lines.append(f"{t:.9f} {x:.9f} {y:.9f} {z:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM trajectory (``#`` comments allowed)."""
    p = Path(path)
    if not p.is_file():
        raise TrajectoryError(f"trajectory file not found: {p}")
    rows = []
    for number, line in enumerate(p.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise TrajectoryError(f"{p}:{number}: a TUM line has 8 fields (t x y z qx qy qz qw), got {len(fields)}")
        try:
            rows.append([float(f) for f in fields])
        except ValueError as exc:
            raise TrajectoryError(f"{p}:{number}: {exc}") from None
    if not rows:
        raise TrajectoryError(f"{p}: no poses")
    data = np.asarray(rows)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    for i, row in enumerate(data):
        if not np.all(np.isfinite(row)):
            raise TrajectoryError(f"{p}: non-finite value in pose {i}")
        poses[i, :3, :3] = rotation_from_quaternion(row[4:8])
        poses[i, :3, 3] = row[1:4]
    try:
        return Trajectory(data[:, 0], poses)
    except TrajectoryError as exc:
        raise TrajectoryError(f"{p}: {exc}") from None
