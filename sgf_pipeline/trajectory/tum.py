"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` (seconds; ``#`` comments)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sgf_pipeline.geometry import quaternion_from_rotation
from sgf_pipeline.io import atomic_write_text
from sgf_pipeline.trajectory.checks import _check_quaternions, _checked, _off_unit_length, _rotation, _table
from sgf_pipeline.trajectory.model import Duplicates, Trajectory


def parse_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Timestamps, (N, 4, 4) poses and line numbers of a TUM file, unchecked for order and NaN.

    For readers that skip bad rows of a long recording instead of refusing the file: a quaternion
    off unit length (beyond :data:`QUATERNION_TOLERANCE`) gives a NaN pose, as a zero one does.
    """
    data, lines = _tum_rows(Path(path), whole=False)
    poses = _tum_poses(data)  # a zero or non-finite quaternion gives a NaN rotation already
    poses[_off_unit_length(data[:, 4:8])[0], :3, :3] = np.nan
    return data[:, 0].copy(), poses, lines


def _tum_rows(path: Path, whole: bool) -> tuple[np.ndarray, list[int]]:
    return _table(path, ",", (8,), "TUM (t x y z qx qy qz qw)", whole)


def _tum_poses(data: np.ndarray) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    for i, row in enumerate(data):
        poses[i, :3, :3] = _rotation(row[4:8])
        poses[i, :3, 3] = row[1:4]
    return poses


def write_tum(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines atomically."""
    lines = []
    for t, pose in zip(trajectory.timestamps, trajectory.poses, strict=True):
        q = quaternion_from_rotation(pose[:3, :3])
        x, y, z = pose[:3, 3]
        lines.append(f"{t:.9f} {x:.9f} {y:.9f} {z:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_tum(path: str | os.PathLike[str], duplicates: Duplicates = "error") -> Trajectory:
    """Read a TUM trajectory (``#`` comments allowed; ``duplicates="drop"`` keeps the first of equal stamps).

    A quaternion off unit length by more than :data:`QUATERNION_TOLERANCE` is refused.
    """
    p = Path(path)
    data, lines = _tum_rows(p, whole=True)
    _check_quaternions(p, data[:, 4:8], lines, "qx qy qz qw")
    return _checked(p, data[:, 0].copy(), _tum_poses(data), lines, duplicates)
