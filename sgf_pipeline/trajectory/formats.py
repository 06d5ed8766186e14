"""Any known trajectory format: telling a file's format, and reading or writing by format name."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from sgf_pipeline.trajectory.euroc import read_euroc_csv, write_euroc_csv
from sgf_pipeline.trajectory.kitti import read_kitti, write_kitti
from sgf_pipeline.trajectory.model import FORMATS, Duplicates, Trajectory, TrajectoryError, TrajectoryFormat
from sgf_pipeline.trajectory.tum import read_tum, write_tum


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
