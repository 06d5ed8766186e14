"""What every trajectory reader checks: a file's numeric table, its line ends, quaternions, order and duplicates."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from sgf_pipeline.geometry import rotation_from_quaternion
from sgf_pipeline.trajectory.model import Duplicates, Trajectory, TrajectoryError

#: Largest deviation of an element of ``R R^T`` from the identity's a file's rotation matrix may have.
ROTATION_TOLERANCE = 1e-3
#: Largest deviation of a file's quaternion length from 1: a quaternion written with 3 decimals is
#: within sqrt(4) * 0.0005 = 0.001 of unit length (evo's example files: at most 0.00016).
QUATERNION_TOLERANCE = 1e-3
#: Quaternions shorter than this (or of non-finite length) carry no rotation.
_MIN_QUATERNION_NORM = 1e-9
log = logging.getLogger("sgf_pipeline")


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
