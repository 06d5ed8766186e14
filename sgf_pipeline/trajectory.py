"""Timed pose sequences and their file formats: TUM, KITTI (with a times file) and EuRoC state CSV.

Every reader checks what evo would silently accept or reject late: each line's field count,
finite numbers, strictly increasing timestamps, unit quaternions (within
:data:`QUATERNION_TOLERANCE`), rotation matrices (within :data:`ROTATION_TOLERANCE`), and a last
line that ends (a file cut off mid-number does not); errors name the file and line. Writers are
atomic. ``read_trajectory``/``write_trajectory`` pick the format from a name or the file.

Formats:

* TUM: ``timestamp tx ty tz qx qy qz qw`` (seconds; ``#`` comments).
* KITTI: 12 numbers per line, the row-major 3x4 pose; no timestamps in the file. The times
  come from a separate file (one number per line, KITTI's ``times.txt``); without one the
  timestamps are the row numbers 0, 1, 2, ... so that two KITTI files pair up row by row.
* EuRoC: ``#timestamp [ns],p_RS_R_x [m],p_RS_R_y,p_RS_R_z,q_RS_w [],q_RS_x,q_RS_y,q_RS_z[,...]``
  (integer nanoseconds, quaternion w first; the velocity and bias columns of
  ``state_groundtruth_estimate0/data.csv`` are read past and not written).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from sgf_pipeline.geometry import quaternion_from_rotation, rotation_from_quaternion
from sgf_pipeline.io import atomic_write_text

TrajectoryFormat = Literal["tum", "kitti", "euroc"]
#: Largest deviation of an element of ``R R^T`` from the identity's a file's rotation matrix may have.
ROTATION_TOLERANCE = 1e-3
#: Largest deviation of a file's quaternion length from 1: a quaternion written with 3 decimals is
#: within sqrt(4) * 0.0005 = 0.001 of unit length (evo's example files: at most 0.00016).
QUATERNION_TOLERANCE = 1e-3
#: Quaternions shorter than this (or of non-finite length) carry no rotation.
_MIN_QUATERNION_NORM = 1e-9
#: Poses at a repeated timestamp: refused (``error``), the first kept (``drop``), or all kept (``keep``, as evo does).
Duplicates = Literal["error", "drop", "keep"]
#: The formats ``read_trajectory`` and ``write_trajectory`` know.
FORMATS: tuple[TrajectoryFormat, ...] = ("tum", "kitti", "euroc")
log = logging.getLogger("sgf_pipeline")
_EUROC_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"


class TrajectoryError(ValueError):
    """A trajectory file or array that cannot be used, with what is wrong in it."""


@dataclass(frozen=True)
class Trajectory:
    """Poses (N, 4, 4) at strictly increasing timestamps (N,) in seconds.

    ``repeated_stamps`` admits equal consecutive timestamps (a file read with ``duplicates="keep"``,
    for evaluation only: evo pairs such poses as they are).
    """

    timestamps: np.ndarray
    poses: np.ndarray
    repeated_stamps: bool = False

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
        steps = np.diff(ts)
        backwards = steps < 0 if self.repeated_stamps else steps <= 0
        if ts.size > 1 and np.any(backwards):
            row = int(np.flatnonzero(backwards)[0]) + 1
            order = "increase" if self.repeated_stamps else "increase strictly"
            raise TrajectoryError(f"timestamps must {order}; row {row} has {ts[row]!r} after {ts[row - 1]!r}")
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


# -- parsing helpers ------------------------------------------------------------------------


def _table(
    path: Path, separators: str, columns: tuple[int, ...], what: str, whole: bool = True
) -> tuple[np.ndarray, list[int]]:
    """Numeric rows of a text file (``#`` comments and blank lines skipped) and their line numbers.

    ``whole``: refuse a last data line without a line end (:func:`_check_ended`).
    """
    if not path.is_file():
        raise TrajectoryError(f"{what} file not found: {path}")
    rows: list[list[float]] = []
    lines: list[int] = []
    text = _text(path)
    if whole:
        _check_ended(path, text)
    for number, line in enumerate(text.split("\n"), start=1):
        line = line.strip()
        if not line or line.startswith("#") or line.startswith("%"):
            continue
        for sep in separators:
            line = line.replace(sep, " ")
        fields = line.split()
        if len(fields) not in columns:
            want = " or ".join(map(str, columns))
            raise TrajectoryError(f"{path}:{number}: a {what} line has {want} fields, got {len(fields)}: {line[:80]!r}")
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            raise TrajectoryError(f"{path}:{number}: not a number in {line[:80]!r}") from None
        lines.append(number)
    if not rows:
        raise TrajectoryError(f"{path}: no poses")
    width = len(rows[0])
    for row, number in zip(rows, lines, strict=True):
        if len(row) != width:
            raise TrajectoryError(
                f"{path}:{number}: a line of {len(row)} fields after lines of {width} (line {lines[0]}); "
                "every line of a trajectory file has the same fields"
            )
    return np.asarray(rows, dtype=np.float64), lines


def _text(path: Path) -> str:
    """A file's text; a binary file gives a clear error instead of a decoding exception."""
    try:
        return path.read_bytes().decode("utf-8")  # no newline translation: a line ends at "\n" only
    except UnicodeDecodeError as exc:
        line = path.read_bytes()[: exc.start].count(b"\n") + 1
        raise TrajectoryError(f"{path}:{line}: not a text file (is it an image or a bag?)") from None
    except OSError as exc:
        raise TrajectoryError(f"{path}: cannot be read: {exc.strerror or exc}") from None


def _check_ended(path: Path, text: str) -> None:
    """Refuse a file whose last data line has no line end: it may be cut off in the middle of a number."""
    lines = text.split("\n")
    last = lines[-1].strip()
    if last and not last.startswith(("#", "%")):
        raise TrajectoryError(
            f"{path}:{len(lines)}: the last line has no line end, so the file may be cut off in the middle of a "
            f"number (an interrupted write or copy): {last[:80]!r}; if that line is whole, end it with a newline "
            "(echo >> FILE)"
        )


def _off_unit_length(quaternions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which finite, non-zero quaternions are off unit length beyond :data:`QUATERNION_TOLERANCE`; their lengths."""
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(quaternions, axis=1)
        off = np.abs(norms - 1.0)
    return np.isfinite(norms) & (norms > _MIN_QUATERNION_NORM) & (off > QUATERNION_TOLERANCE), norms


def _check_quaternions(path: Path, quaternions: np.ndarray, lines: list[int], order: str) -> None:
    """Refuse quaternions whose length is off 1 by more than :data:`QUATERNION_TOLERANCE` (zero or NaN: later)."""
    mask, norms = _off_unit_length(quaternions)
    bad = np.flatnonzero(mask)
    if bad.size:
        i = int(bad[0])
        values = " ".join(f"{v:.9g}" for v in quaternions[i])
        raise TrajectoryError(
            f"{path}:{lines[i]}: the quaternion ({order}) = ({values}) has length {norms[i]:.6g}, off 1 by more "
            f"than {QUATERNION_TOLERANCE:g}: a cut or corrupt number? A pose's quaternion has unit length"
            + (f" ({bad.size} such lines)" if bad.size > 1 else "")
        )


def _rotation(quaternion: np.ndarray) -> np.ndarray:
    """The rotation of an ``(x, y, z, w)`` quaternion, or NaNs when it has no usable length."""
    with np.errstate(over="ignore", invalid="ignore"):
        norm = float(np.linalg.norm(quaternion)) if np.all(np.isfinite(quaternion)) else math.nan
    if not (math.isfinite(norm) and norm > _MIN_QUATERNION_NORM):
        return np.full((3, 3), np.nan)
    return rotation_from_quaternion(quaternion / norm)


def _checked(
    path: Path | str,
    timestamps: np.ndarray,
    poses: np.ndarray,
    lines: list[int],
    duplicates: Duplicates = "error",
    unit: str = "line",
) -> Trajectory:
    """A Trajectory, with errors that name the file's line (or the topic's message: ``unit``) instead of the row."""
    if duplicates not in ("error", "drop", "keep"):
        raise TrajectoryError(f"duplicates must be 'error', 'drop' or 'keep', got {duplicates!r}")
    repeated = np.flatnonzero(np.diff(timestamps) == 0) + 1 if timestamps.size > 1 else np.zeros(0, dtype=int)
    if duplicates == "drop" and repeated.size:
        log.warning(
            "%s: dropped %d pose(s) whose timestamp repeats the previous %s's (%s(s) %s)",
            path,
            repeated.size,
            unit,
            unit,
            [lines[i] for i in repeated[:5]],
        )
        keep = np.ones(timestamps.size, dtype=bool)
        keep[repeated] = False
        timestamps, poses = timestamps[keep], poses[keep]
        lines = [n for n, k in zip(lines, keep, strict=True) if k]
    elif duplicates == "keep" and repeated.size:
        log.info("%s: kept %d pose(s) whose timestamp repeats the previous %s's", path, repeated.size, unit)
    finite = np.isfinite(poses).all(axis=(1, 2)) & np.isfinite(timestamps)
    if not finite.all():
        bad = [lines[i] for i in np.flatnonzero(~finite)[:5]]
        raise TrajectoryError(
            f"{path}:{bad[0]}: non-finite pose (NaN or inf) or zero-length quaternion on {unit}(s) {bad}"
        )
    steps = np.diff(timestamps)
    wrong = steps < 0 if duplicates == "keep" else steps <= 0
    if np.any(wrong):
        row = int(np.flatnonzero(wrong)[0]) + 1
        kind = "duplicated" if steps[row - 1] == 0 else "out of order"
        raise TrajectoryError(
            f"{path}:{lines[row]}: timestamp {float(timestamps[row])!r} is {kind} (previous "
            f"{float(timestamps[row - 1])!r} on {unit} {lines[row - 1]}); timestamps must increase strictly"
            + (
                "; duplicates=drop keeps the first of equal timestamps, duplicates=keep all of them (as evo does)"
                if kind == "duplicated"
                else ""
            )
        )
    return Trajectory(timestamps, poses, repeated_stamps=duplicates == "keep" and bool(repeated.size))


def checked_trajectory(
    source: str, timestamps: np.ndarray, poses: np.ndarray, numbers: list[int], duplicates: Duplicates = "error"
) -> Trajectory:
    """A Trajectory of poses read from messages (``numbers``: each pose's message number, for errors)."""
    return _checked(
        source,
        np.asarray(timestamps, dtype=np.float64),
        np.asarray(poses, dtype=np.float64),
        numbers,
        duplicates,
        "message",
    )


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


def _format_seconds(t: float) -> str:
    return f"{t:.9f}"


# -- TUM ------------------------------------------------------------------------------------


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


# -- KITTI ----------------------------------------------------------------------------------


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


# -- EuRoC ----------------------------------------------------------------------------------


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


# -- any format -----------------------------------------------------------------------------


def detect_format(path: str | os.PathLike[str]) -> TrajectoryFormat:
    """The format of a trajectory file: ``.tum``, ``.kitti``, ``.csv`` (EuRoC) by name, else from its first line."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".tum":
        return "tum"
    if suffix == ".kitti":
        return "kitti"
    if suffix == ".csv":
        return "euroc"
    if not p.is_file():
        raise TrajectoryError(f"trajectory file not found: {p}")
    try:
        with p.open("rb") as fh:
            head = fh.read(65536)
    except OSError as exc:
        raise TrajectoryError(f"{p}: cannot be read: {exc.strerror or exc}") from None
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        raise TrajectoryError(f"{p}: not a text file, so not a trajectory") from None
    for line in text.split("\n"):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if "," in line and len(line.split(",")) >= 8:
            return "euroc"
        n = len(line.replace(",", " ").split())
        if n == 8:
            return "tum"
        if n == 12:
            return "kitti"
        raise TrajectoryError(
            f"{p}: cannot tell the format from a line of {n} fields; TUM lines have 8, KITTI lines 12, "
            "EuRoC CSV lines 8 or more comma-separated; name the format explicitly"
        )
    raise TrajectoryError(f"{p}: no poses")


def read_trajectory(
    path: str | os.PathLike[str],
    format: TrajectoryFormat | Literal["auto"] = "auto",
    times: str | os.PathLike[str] | None = None,
    duplicates: Duplicates = "error",
) -> Trajectory:
    """Read a trajectory in any known format (``times``: the KITTI times file, if any).

    ``duplicates="drop"`` keeps the first of poses with equal timestamps (real motion-capture files
    have them) instead of refusing the file; ``"keep"`` keeps them all, as evo does (for evaluation).
    """
    fmt = detect_format(path) if format == "auto" else format
    if fmt == "tum":
        return read_tum(path, duplicates)
    if fmt == "kitti":
        return read_kitti(path, times)
    if fmt == "euroc":
        return read_euroc_csv(path, duplicates)
    raise TrajectoryError(f"unknown trajectory format {format!r}; known: auto, {', '.join(FORMATS)}")


def write_trajectory(
    path: str | os.PathLike[str],
    trajectory: Trajectory,
    format: TrajectoryFormat = "tum",
    times_path: str | os.PathLike[str] | None = None,
) -> None:
    """Write a trajectory in one of the known formats (KITTI writes ``times_path`` if given)."""
    if format == "tum":
        write_tum(path, trajectory)
    elif format == "kitti":
        write_kitti(path, trajectory, times_path)
    elif format == "euroc":
        write_euroc_csv(path, trajectory)
    else:
        raise TrajectoryError(f"unknown trajectory format {format!r}; known: {', '.join(FORMATS)}")
