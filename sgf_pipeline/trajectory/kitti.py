"""KITTI trajectory files: the row-major 3x4 pose per line, timestamps from a separate times file or the row numbers."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sgf_pipeline.io import atomic_write_text
from sgf_pipeline.trajectory.checks import ROTATION_TOLERANCE, _checked, _table
from sgf_pipeline.trajectory.model import Trajectory, TrajectoryError


def _format_seconds(t: float) -> str:
    return f"{t:.9f}"


def read_times(path: str | os.PathLike[str]) -> np.ndarray:
    """A KITTI ``times.txt``: one timestamp (s) per line, strictly increasing."""
    p = Path(path)
    data, lines = _table(p, ",", (1,), "times")
    ts = data[:, 0].copy()
    if not np.all(np.isfinite(ts)):
        raise TrajectoryError(f"{p}: non-finite timestamp on line {lines[int(np.flatnonzero(~np.isfinite(ts))[0])]}")
    steps = np.diff(ts)
    if np.any(steps <= 0):
        row = int(np.flatnonzero(steps <= 0)[0]) + 1
        kind = "duplicated" if steps[row - 1] == 0 else "out of order"
        raise TrajectoryError(
            f"{p}:{lines[row]}: timestamp {float(ts[row])!r} is {kind}; timestamps must increase strictly"
        )
    return ts


def read_kitti(path: str | os.PathLike[str], times: str | os.PathLike[str] | np.ndarray | None = None) -> Trajectory:
    """Read KITTI poses (3x4 row-major per line); timestamps from ``times`` or else the row numbers.

    A 3x3 block that is not a rotation (an element of ``R R^T - I`` beyond :data:`ROTATION_TOLERANCE`,
    or ``det R < 0``) is refused.
    """
    p = Path(path)
    data, lines = _table(p, ",", (12,), "KITTI pose (12 numbers, row-major 3x4)")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :4] = data.reshape(-1, 3, 4)
    _check_rotations(p, poses, lines)
    if times is None:
        ts = np.arange(len(data), dtype=np.float64)
    else:
        ts = times if isinstance(times, np.ndarray) else read_times(times)
        if len(ts) != len(data):
            raise TrajectoryError(
                f"{p} has {len(data)} poses but the times ({times if not isinstance(times, np.ndarray) else 'array'}) "
                f"have {len(ts)}; give the times file of this sequence"
            )
    return _checked(p, np.asarray(ts, dtype=np.float64), poses, lines)


def _check_rotations(path: Path, poses: np.ndarray, lines: list[int]) -> None:
    """Refuse 3x4 matrices whose left 3x3 block is not a rotation (KITTI files carry the matrix itself)."""
    with np.errstate(invalid="ignore", over="ignore"):
        rotations = poses[:, :3, :3]
        deviation = np.abs(rotations @ rotations.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
        determinant = np.linalg.det(np.nan_to_num(rotations, nan=0.0, posinf=0.0, neginf=0.0))
    finite = np.isfinite(poses).all(axis=(1, 2))
    bad = np.flatnonzero(finite & ((deviation > ROTATION_TOLERANCE) | (determinant < 0.0)))
    if bad.size:
        i = int(bad[0])
        raise TrajectoryError(
            f"{path}:{lines[i]}: the pose's 3x3 block is not a rotation (|R R^T - I| = {deviation[i]:.3g}, more "
            f"than {ROTATION_TOLERANCE:g}, det R = {determinant[i]:.3g}): a cut or corrupt number? A KITTI line "
            "is a row-major 3x4 pose [R | t] whose R is orthonormal"
        )


def write_kitti(
    path: str | os.PathLike[str], trajectory: Trajectory, times_path: str | os.PathLike[str] | None = None
) -> None:
    """Write KITTI poses (and, if ``times_path`` is given, the timestamps beside them) atomically."""
    rows = [" ".join(f"{v:.9e}" for v in pose[:3, :4].reshape(-1)) for pose in trajectory.poses]
    atomic_write_text(path, "\n".join(rows) + "\n")
    if times_path is not None:
        atomic_write_text(times_path, "\n".join(_format_seconds(t) for t in trajectory.timestamps) + "\n")
