"""SGF groups and the flat index of their members that the spatial gate searches."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sgf_pipeline.stage import SettledGroup
from sgf_pipeline.types import SgfDescriptor
from sgf_plugins.shared.polar import ColumnSet, align, best_shift, shifted_distances, symmetry_spread

#: Frames whose odometry and travelled distance are remembered at least (older ones only for group members).
HISTORY_FRAMES = 20_000


@dataclass
class SgfGroup:
    """An SGF group: descriptors of one physical ground feature, aligned to the first member's orientation.

    ``offsets[i]`` turns member i into the group's orientation (``align(matrix, offset)``);
    ``descriptor`` is the mean of the aligned members (D^sg of eq. 10). ``anchors[i]`` is a fixed
    map position (x, y) of member i for groups loaded from a saved map, or None for members whose
    position follows the current pose estimate.
    """

    group_id: int
    members: list[SgfDescriptor] = field(default_factory=list)
    offsets: list[int] = field(default_factory=list)
    anchors: list[np.ndarray | None] = field(default_factory=list)
    descriptor: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    spread: float = 0.0
    symmetric: bool = False
    aliased: bool = False

    def add(self, member: SgfDescriptor, offset: int, anchor: np.ndarray | None = None) -> None:
        """Append a member turned by ``offset`` columns into the group's orientation (kept without its BEV pixels)."""
        self.members.append(member.without_pixels())
        self.offsets.append(int(offset) % member.matrix.shape[1])
        self.anchors.append(None if anchor is None else np.asarray(anchor, dtype=np.float64).reshape(2))

    def refresh(self, columns: ColumnSet, symmetry_threshold: float) -> None:
        """Recompute the group descriptor (mean of aligned members) and its rotational symmetry."""
        aligned = [align(m.matrix, o) for m, o in zip(self.members, self.offsets, strict=True)]
        self.descriptor = np.mean(aligned, axis=0)
        self.spread = symmetry_spread(self.descriptor, columns)
        self.symmetric = self.spread < symmetry_threshold

    @property
    def matrices(self) -> np.ndarray:
        """The members' own (unaligned) descriptors, (M, N_r, N_s)."""
        return np.stack([m.matrix for m in self.members])


@dataclass(frozen=True)
class Ranking:
    """How eq. 10 (plus the position weight) ranked the gated groups for one query, before it joined one.

    ``groups`` holds each gated group's id and how many members it had then (its first members in
    the groups of the run); ``score`` their ranking scores, lowest first.
    """

    query: SgfDescriptor
    groups: tuple[tuple[int, int], ...]
    score: np.ndarray


@dataclass(frozen=True)
class GatedGroup:
    """A group inside the query's spatial gate: its nearest member's map distance, and whether it repeats."""

    group: SgfGroup
    nearest: float
    repeated: bool
    ratio: float = 0.0
    repeating: np.ndarray | None = None  # indices of the members seen moments ago elsewhere (when ``repeated``)


class MemberIndex:
    """Every group member in flat arrays (group, frame, centroid, odometry, travelled, anchor) for the spatial gate.

    The gate then costs a few numpy passes over all members instead of Python work per member;
    map positions are computed once per pose estimate (one per frame) and extended as members join.
    """

    def __init__(self) -> None:
        self.size = 0
        self.group = np.zeros(64, dtype=np.int64)
        self.frame = np.zeros(64, dtype=np.int64)
        self.centroid = np.zeros((64, 2))
        self.odometry = np.zeros((64, 4, 4))
        self.travelled = np.zeros(64)
        self.anchor = np.zeros((64, 2))
        self.positions = np.zeros((0, 2))
        self.estimate: object = NO_ESTIMATE
        self.members: list[SgfDescriptor] = []

    def add(self, group: int, member: SgfDescriptor, travelled: float | None, anchor: np.ndarray | None) -> None:
        """Append one member of the group at position ``group`` in the group list."""
        if self.size == len(self.group):
            for name in ("group", "frame", "centroid", "odometry", "travelled", "anchor"):
                old = getattr(self, name)
                grown = np.zeros((2 * len(old), *old.shape[1:]), dtype=old.dtype)
                grown[: self.size] = old[: self.size]
                setattr(self, name, grown)
        k = self.size
        self.group[k] = group
        self.frame[k] = member.sgf.frame_index
        self.centroid[k] = np.asarray(member.centroid, dtype=np.float64)[:2]
        self.odometry[k] = np.asarray(member.sgf.odometry, dtype=np.float64)
        self.travelled[k] = math.nan if travelled is None else travelled
        self.anchor[k] = math.nan if anchor is None else anchor
        self.members.append(member)
        self.size += 1


#: Marks a cache computed for no estimate yet.
NO_ESTIMATE = object()


def settled(groups: Iterable[SgfGroup]) -> tuple[SettledGroup, ...]:
    """The groups as the end of the run hands them on (members frozen as they are now)."""
    return tuple(SettledGroup(g.group_id, tuple(g.members), g.symmetric) for g in groups)


def odometry_position(member: SgfDescriptor) -> np.ndarray:
    """Map position of a member's centroid under its own odometry pose (the frame of the session that saw it)."""
    pose = np.asarray(member.sgf.odometry, dtype=np.float64)
    return pose[:2, :2] @ np.asarray(member.centroid[:2], dtype=np.float64) + pose[:2, 3]


def groups_from_map(sgf_map: Any, columns: ColumnSet = "intersection") -> list[SgfGroup]:
    """SGF groups of a saved map, members anchored at their optimized map positions (for ``seed_groups``)."""
    groups = []
    for map_group in sgf_map.groups:
        group = SgfGroup(map_group.group_id)
        first = None
        for view in map_group.views:
            member = view.descriptor()
            offset = 0
            if first is None:
                first = member
            else:
                offset = best_shift(shifted_distances(member.matrix, first.matrix[None], columns)[0])
            anchor = (
                member.map_pose[:2, :2] @ np.asarray(member.centroid, dtype=np.float64)[:2] + member.map_pose[:2, 3]
            )
            group.add(member, offset, anchor)
        if group.members:
            groups.append(group)
    return groups
