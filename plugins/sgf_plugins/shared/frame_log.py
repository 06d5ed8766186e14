"""Each processed frame's odometry, distance travelled and time, in flat arrays.

The association and the loop stage look up the odometry and the distance travelled of any
earlier frame (the frames their SGFs came from). Here a frame is one row of 18 floats and an
index (152 bytes, 128 more with a ground-truth pose), in arrays that grow by doubling; the dicts
of small arrays and floats they replace held 0.6 MiB per km more over the two stages
(``bench/bench_soak.py --state``).
"""

from __future__ import annotations

import numpy as np

from sgf_pipeline.types import Frame

_COLUMNS = 16 + 2  # odometry (4x4, row-major), distance travelled, timestamp
_TRANSLATION = [3, 7, 11]  # the odometry's translation in a row


class FrameLog:
    """Frames in increasing index order; a frame is found by binary search over the indices.

    With ``keep``, at least the newest ``keep`` frames are remembered: when ``2 * keep`` are held,
    the older half is dropped, so memory stays bounded over hours. With ``truth``, ground-truth
    poses are kept once a frame brings one (a finite 4x4 pose; the runner leaves others out of the
    ground-truth trajectory too), with NaN rows for frames without.
    """

    def __init__(self, keep: int | None = None, truth: bool = False) -> None:
        if keep is not None and keep < 1:
            raise ValueError(f"keep must be at least 1, got {keep}")
        self.keep = keep
        self._keep_truth = truth
        self._index = np.zeros(64, dtype=np.int64)
        self._rows = np.zeros((64, _COLUMNS))
        self._truth: np.ndarray | None = None
        self._size = 0

    def __len__(self) -> int:
        return self._size

    @property
    def last(self) -> int | None:
        """Index of the newest frame, or None before the first."""
        return int(self._index[self._size - 1]) if self._size else None

    @property
    def travelled(self) -> float:
        """Distance travelled up to the newest frame (m)."""
        return float(self._rows[self._size - 1, 16]) if self._size else 0.0

    def append(self, frame: Frame) -> None:
        """Record a frame; its index must be above the previous frame's (the same index replaces it)."""
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        last = self.last
        if last is not None and frame.index < last:
            raise ValueError(
                f"frame {frame.index} came after frame {last}: frames must reach the stage in increasing index order"
            )
        if last is not None and frame.index == last:
            self._size -= 1
            last = self.last
        if self._size == len(self._index):
            self._make_room()
        k = self._size
        step = 0.0 if last is None else float(np.linalg.norm(odometry[:3, 3] - self._rows[k - 1, _TRANSLATION]))
        self._index[k] = frame.index
        self._rows[k, :16] = odometry.reshape(16)
        self._rows[k, 16] = self.travelled + step
        self._rows[k, 17] = float(frame.timestamp)
        truth = _valid_pose(frame.ground_truth) if self._keep_truth else None
        if truth is not None and self._truth is None:
            self._truth = np.full((len(self._index), 4, 4), np.nan)
        if self._truth is not None:
            self._truth[k] = np.nan if truth is None else truth
        self._size += 1

    def _make_room(self) -> None:
        """Drop the older half when ``keep`` allows, else double the arrays."""
        n = self._size
        if self.keep is not None and n >= 2 * self.keep:
            start = n - self.keep
            for name in ("_index", "_rows", "_truth"):
                a = getattr(self, name)
                if a is not None:
                    a[: self.keep] = a[start:n]
            self._size = self.keep
            return
        capacity = 2 * n if self.keep is None else min(2 * n, 2 * self.keep)
        for name in ("_index", "_rows", "_truth"):
            a = getattr(self, name)
            if a is not None:
                grown = np.zeros((capacity, *a.shape[1:]), dtype=a.dtype)
                grown[:n] = a[:n]
                setattr(self, name, grown)

    def _row(self, frame_index: int) -> int:
        k = int(np.searchsorted(self._index[: self._size], frame_index))
        if k < self._size and self._index[k] == frame_index:
            return k
        return -1

    def __contains__(self, frame_index: object) -> bool:
        return isinstance(frame_index, (int, np.integer)) and self._row(int(frame_index)) >= 0

    def _found(self, frame_index: int) -> int:
        k = self._row(frame_index)
        if k < 0:
            raise KeyError(frame_index)
        return k

    def odometry(self, frame_index: int) -> np.ndarray:
        """The frame's odometry pose (a new 4x4 array); KeyError when the frame is not remembered."""
        return self._rows[self._found(frame_index), :16].reshape(4, 4).copy()

    def distance(self, frame_index: int) -> float:
        """Distance travelled up to the frame (m); KeyError when the frame is not remembered."""
        return float(self._rows[self._found(frame_index), 16])

    def time(self, frame_index: int) -> float:
        """The frame's timestamp (s); KeyError when the frame is not remembered."""
        return float(self._rows[self._found(frame_index), 17])

    def get_distance(self, frame_index: int) -> float | None:
        """Distance travelled up to the frame, or None when it is not remembered."""
        k = self._row(frame_index)
        return None if k < 0 else float(self._rows[k, 16])

    def get_odometry(self, frame_index: int) -> np.ndarray | None:
        """The frame's odometry pose, or None when it is not remembered."""
        k = self._row(frame_index)
        return None if k < 0 else self._rows[k, :16].reshape(4, 4).copy()

    def get_time(self, frame_index: int) -> float | None:
        """The frame's timestamp, or None when it is not remembered."""
        k = self._row(frame_index)
        return None if k < 0 else float(self._rows[k, 17])

    def odometry_since(self, frame_index: int) -> np.ndarray:
        """Odometry poses (N, 4, 4) of the remembered frames from ``frame_index`` on (a copy; empty if none)."""
        k = int(np.searchsorted(self._index[: self._size], frame_index))
        return self._rows[k : self._size, :16].reshape(-1, 4, 4).copy()

    def around(self, frame_index: int, half_width: float) -> tuple[np.ndarray, int]:
        """The remembered frames' odometry poses (N, 4, 4) within ``half_width`` metres driven of a frame.

        Also the frame's own row among them; KeyError when the frame is not remembered.
        """
        k = self._found(frame_index)
        travelled = self._rows[: self._size, 16]
        lo = int(np.searchsorted(travelled, travelled[k] - half_width, side="left"))
        hi = int(np.searchsorted(travelled, travelled[k] + half_width, side="right"))
        lo, hi = min(lo, k), max(hi, k + 1)  # a standing robot's frames share its distance: the frame itself stays
        return self._rows[lo:hi, :16].reshape(-1, 4, 4).copy(), k - lo

    def path(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every remembered frame's index (N,), odometry pose (N, 4, 4) and distance travelled (N,), as copies."""
        n = self._size
        return self._index[:n].copy(), self._rows[:n, :16].reshape(-1, 4, 4).copy(), self._rows[:n, 16].copy()

    def ground_truth(self, frame_index: int) -> np.ndarray | None:
        """The frame's ground-truth pose, or None when it is unknown or not remembered."""
        k = self._row(frame_index)
        if k < 0 or self._truth is None or np.isnan(self._truth[k, 0, 0]):
            return None
        return self._truth[k].copy()

    def has_truth(self) -> bool:
        """Whether any remembered frame has a ground-truth pose."""
        return self._truth is not None and bool((~np.isnan(self._truth[: self._size, 0, 0])).any())


def _valid_pose(pose: np.ndarray | None) -> np.ndarray | None:
    """A finite 4x4 pose as float64, else None."""
    if pose is None:
        return None
    pose = np.asarray(pose, dtype=np.float64)
    return pose if pose.shape == (4, 4) and bool(np.isfinite(pose).all()) else None
