"""The SGFs the loop stage has seen: one record per SGF, for the neighbour consensus and the gate's look-alike test."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sgf_pipeline.geometry import xy_yaw
from sgf_pipeline.types import GroupAssignment, SgfDescriptor
from sgf_plugins.shared.polar import shifted_distances


@dataclass
class RememberedSgf:
    """One SGF seen on the run: where the odometry put it, when along the path, its descriptor and its group."""

    descriptor: SgfDescriptor  # without its BEV pixels
    group: int  # the association's group (its final group once the run is over)
    symmetric: bool  # the association holds it in a symmetric group (a round manhole)
    distance: float  # m of odometry path when it was seen
    xy: np.ndarray  # its centroid (x, y) in the odometry frame
    yaw: float  # the heading of the frame that saw it, in the odometry frame
    matrix: np.ndarray  # its descriptor (eq. 10's matrix)
    centroid: np.ndarray  # its centroid (x, y) in the frame that saw it

    @property
    def frame(self) -> int:
        """The frame that saw it."""
        return self.descriptor.sgf.frame_index

    @property
    def track(self) -> int:
        """Its track across frames."""
        return self.descriptor.sgf.track_id


class SgfMemory:
    """Every SGF seen so far, in the order seen; ``k`` names the ``k``-th."""

    def __init__(self) -> None:
        self.sgfs: list[RememberedSgf] = []

    def __len__(self) -> int:
        return len(self.sgfs)

    def __getitem__(self, k: int) -> RememberedSgf:
        return self.sgfs[k]

    def remember(self, a: GroupAssignment, distance: float) -> None:
        """Keep an SGF's odometry-frame position, path distance ``distance`` (m) and descriptor."""
        d = a.descriptor
        self.sgfs.append(
            RememberedSgf(
                descriptor=d,
                group=a.group_id,
                symmetric=a.symmetric,
                distance=distance,
                xy=odometry_xy(d),
                yaw=odometry_yaw(d),
                matrix=np.asarray(d.matrix),
                centroid=np.asarray(d.centroid, dtype=np.float64)[:2],
            )
        )

    def xy(self) -> np.ndarray:
        """Every SGF's odometry-frame centroid, (N, 2)."""
        return np.asarray([s.xy for s in self.sgfs])

    def distances(self) -> np.ndarray:
        """Every SGF's path distance (m), (N,)."""
        return np.asarray([s.distance for s in self.sgfs])

    def headings(self) -> np.ndarray:
        """The heading (rad) of the frame that saw each SGF, (N,)."""
        return np.asarray([s.yaw for s in self.sgfs])

    def groups(self) -> np.ndarray:
        """Every SGF's group, (N,)."""
        return np.asarray([s.group for s in self.sgfs], dtype=np.int64)

    def other_groups_distances(self, matrix: np.ndarray, group_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Every SGF seen so far outside ``group_id`` (its index), and eq. 10 of ``matrix`` to it (best shift)."""
        others = np.flatnonzero(self.groups() != group_id)
        if not len(others):
            return others, np.zeros(0)
        distances = shifted_distances(matrix, np.stack([self.sgfs[m].matrix for m in others])).min(axis=1)
        return others, distances

    def regroup(self, group_of: dict[tuple[int, int], int]) -> None:
        """Count every SGF in its final group (``group_of`` by frame and track; unlisted SGFs keep theirs)."""
        for s in self.sgfs:
            s.group = group_of.get((s.frame, s.track), s.group)


def odometry_xy(descriptor: SgfDescriptor) -> np.ndarray:
    """An SGF's centroid (x, y) in the odometry frame of the run that saw it."""
    odometry = np.asarray(descriptor.sgf.odometry, dtype=np.float64)
    return odometry[:2, :2] @ np.asarray(descriptor.centroid, dtype=np.float64)[:2] + odometry[:2, 3]


def odometry_yaw(descriptor: SgfDescriptor) -> float:
    """The heading (rad) of the frame that saw an SGF, in the odometry frame of its run."""
    return float(xy_yaw(np.asarray(descriptor.sgf.odometry, dtype=np.float64))[2])
