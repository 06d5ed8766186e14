"""EuRoC/ASL state CSV files: integer ns timestamps, position, quaternion w first (extra columns read past)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sgf_pipeline.geometry import quaternion_from_rotation
from sgf_pipeline.io import atomic_write_text
from sgf_pipeline.trajectory.checks import _check_ended, _check_quaternions, _checked, _rotation, _text
from sgf_pipeline.trajectory.model import Duplicates, Trajectory, TrajectoryError

_EUROC_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


def seconds_from_ns(ns: np.ndarray) -> np.ndarray:
    """Seconds of integer nanoseconds, without losing the digits a float64 product would."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000).astype(np.float64) * 1e-9


def _ns_from_seconds(t: float) -> int:
    whole = int(np.floor(t))
    return whole * 1_000_000_000 + round((t - whole) * 1e9)


def read_euroc_csv(path: str | os.PathLike[str], duplicates: Duplicates = "error") -> Trajectory:
    """Read an EuRoC/ASL state CSV (ns timestamps, position, quaternion w x y z, optional extra columns).

    A quaternion off unit length by more than :data:`QUATERNION_TOLERANCE` is refused.
    """
    p = Path(path)
    if not p.is_file():
        raise TrajectoryError(f"EuRoC CSV file not found: {p}")
    rows: list[tuple[int, list[float]]] = []
    lines: list[int] = []
    text = _text(p)
    _check_ended(p, text)
    for number, line in enumerate(text.split("\n"), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) < 8:
            raise TrajectoryError(
                f"{p}:{number}: an EuRoC state line has at least 8 comma-separated fields "
                f"(t[ns], x, y, z, qw, qx, qy, qz), got {len(fields)}"
            )
        try:
            stamp = int(fields[0]) if fields[0].lstrip("-").isdigit() else int(float(fields[0]))
            rows.append((stamp, [float(f) for f in fields[1:8]]))
        except ValueError:
            raise TrajectoryError(f"{p}:{number}: not a number in {line[:80]!r}") from None
        except OverflowError:
            raise TrajectoryError(f"{p}:{number}: timestamp {fields[0][:40]!r} is not a finite time in ns") from None
        if not _INT64_MIN <= stamp <= _INT64_MAX:
            raise TrajectoryError(f"{p}:{number}: timestamp {fields[0][:40]!r} ns is out of range (64-bit ns)")
        lines.append(number)
    if not rows:
        raise TrajectoryError(f"{p}: no poses")
    ns = np.array([r[0] for r in rows], dtype=np.int64)
    values = np.array([r[1] for r in rows], dtype=np.float64)
    _check_quaternions(p, values[:, 3:7], lines, "qw qx qy qz")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for i, v in enumerate(values):
        q = v[3:7]
        poses[i, :3, :3] = _rotation(np.array([q[1], q[2], q[3], q[0]]))
        poses[i, :3, 3] = v[:3]
    return _checked(p, seconds_from_ns(ns), poses, lines, duplicates)


def write_euroc_csv(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """Write an EuRoC/ASL state CSV (position and quaternion w x y z) atomically."""
    lines = [_EUROC_HEADER]
    for t, pose in zip(trajectory.timestamps, trajectory.poses, strict=True):
        q = quaternion_from_rotation(pose[:3, :3])
        x, y, z = pose[:3, 3]
        lines.append(
            f"{_ns_from_seconds(float(t))},{x:.9f},{y:.9f},{z:.9f},{q[3]:.9f},{q[0]:.9f},{q[1]:.9f},{q[2]:.9f}"
        )
    atomic_write_text(path, "\n".join(lines) + "\n")
