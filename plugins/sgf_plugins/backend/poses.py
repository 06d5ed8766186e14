"""The estimated poses by frame: growing, copy-on-write storage and the read-only snapshots it hands out."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np


class PoseTable(Mapping[int, np.ndarray]):
    """A read-only snapshot of the estimated poses by frame index (a :class:`PoseEstimate`'s ``poses``).

    Snapshots share storage with the back-end: appending a pose never changes an older snapshot, and
    a re-optimised trajectory is written into a new buffer (copy on write), so a snapshot stays valid.
    With ``lift``, each planar pose is returned composed with its frame's out-of-plane offset.
    """

    def __init__(
        self, rows: dict[int, int], frames: list[int], buffer: np.ndarray, size: int, lift: np.ndarray | None = None
    ) -> None:
        self._rows = rows
        self._frames = frames
        self._buffer = buffer
        self._size = size
        self._lift = lift

    def __getitem__(self, frame_index: int) -> np.ndarray:
        row = self._rows.get(frame_index)
        if row is None or row >= self._size:
            raise KeyError(frame_index)
        pose = self._buffer[row]
        return pose @ self._lift[row] if self._lift is not None else pose.copy()

    def __contains__(self, frame_index: object) -> bool:
        row = self._rows.get(frame_index)  # type: ignore[call-overload]
        return row is not None and row < self._size

    def __iter__(self) -> Iterator[int]:
        return iter(self._frames[: self._size])

    def __len__(self) -> int:
        return self._size

    def take(self, frames: Sequence[int] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The poses of ``frames`` (NaN where absent) and the mask of found ones (see ``PoseEstimate.stack``)."""
        get = self._rows.get
        rows = np.fromiter((get(int(f), -1) for f in frames), dtype=np.int64, count=len(frames))
        found = (rows >= 0) & (rows < self._size)
        out = np.full((len(rows), 4, 4), np.nan)
        poses = self._buffer[rows[found]]
        out[found] = np.einsum("nij,njk->nik", poses, self._lift[rows[found]]) if self._lift is not None else poses
        return out, found

    def array(self) -> np.ndarray:
        """All poses as an (N, 4, 4) array, in frame order."""
        poses = self._buffer[: self._size]
        if self._lift is not None:
            return np.einsum("nij,njk->nik", poses, self._lift[: self._size])
        return poses.copy()


class PoseStore:
    """The growing, copy-on-write storage behind :class:`PoseTable` snapshots.

    With ``lifted``, every frame also keeps an out-of-plane offset (height, roll, pitch of its
    odometry), applied to its planar pose when read out, so a Pose2 graph keeps the odometry's
    third dimension in the trajectory it publishes.
    """

    def __init__(self, lifted: bool = False) -> None:
        self.rows: dict[int, int] = {}
        self.frames: list[int] = []
        self.buffer = np.zeros((64, 4, 4))
        self.lift: np.ndarray | None = np.zeros((64, 4, 4)) if lifted else None
        self.size = 0

    def append(self, frame_index: int, pose: np.ndarray, lift: np.ndarray | None = None) -> None:
        """Add the pose of a new frame (and its out-of-plane offset, when the store is lifted)."""
        if self.size == len(self.buffer):
            self.buffer = grown(self.buffer, self.size)
        if self.lift is not None and self.size == len(self.lift):
            self.lift = grown(self.lift, self.size)
        self.buffer[self.size] = pose
        if self.lift is not None:
            self.lift[self.size] = np.eye(4) if lift is None else lift
        self.rows[frame_index] = self.size
        self.frames.append(frame_index)
        self.size += 1

    def set_latest(self, pose: np.ndarray) -> None:
        """Overwrite the newest pose (no snapshot has seen it yet)."""
        self.buffer[self.size - 1] = pose

    def replace_all(self, poses: np.ndarray) -> None:
        """Replace every pose (after an optimisation) in a new buffer."""
        if poses.shape != (self.size, 4, 4):
            raise ValueError(f"expected {self.size} poses, got {poses.shape[0]}")
        buffer = np.zeros((max(64, 2 * self.size), 4, 4))
        buffer[: self.size] = poses
        self.buffer = buffer

    def snapshot(self) -> PoseTable:
        """A read-only view of the current poses."""
        return PoseTable(self.rows, self.frames, self.buffer, self.size, self.lift)

    def get(self, frame_index: int) -> np.ndarray | None:
        """The current (planar, when lifted) pose of a frame, if it has one."""
        row = self.rows.get(frame_index)
        return None if row is None else self.buffer[row]


def grown(buffer: np.ndarray, size: int) -> np.ndarray:
    """A buffer of twice the capacity holding the first ``size`` rows of ``buffer``."""
    grown = np.zeros((2 * len(buffer), *buffer.shape[1:]), dtype=buffer.dtype)
    grown[:size] = buffer[:size]
    return grown
