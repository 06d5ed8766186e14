"""The Trajectory type: poses at increasing timestamps, checked on construction, and its error."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

TrajectoryFormat = Literal["tum", "kitti", "euroc"]
#: Poses at a repeated timestamp: refused (``error``), the first kept (``drop``), or all kept (``keep``, as evo does).
Duplicates = Literal["error", "drop", "keep"]
#: The formats ``read_trajectory`` and ``write_trajectory`` know.
FORMATS: tuple[TrajectoryFormat, ...] = ("tum", "kitti", "euroc")


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
