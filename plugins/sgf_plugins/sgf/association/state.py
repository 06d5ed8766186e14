"""The state the parts of the online SGF grouping share, and the map positions of its members."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.types import Frame, LoopConstraints, PoseEstimate, SgfDescriptor
from sgf_plugins.sgf.association.groups import HISTORY_FRAMES, MemberIndex, SgfGroup
from sgf_plugins.shared.frame_log import FrameLog
from sgf_plugins.shared.polar import yaw_to_shift


@dataclass(frozen=True)
class Closure:
    """An accepted loop closure of this run and the distance travelled up to each of its frames."""

    frame_from: int
    frame_to: int
    relative: np.ndarray
    travelled_from: float
    travelled_to: float


class AssociationState:
    """What the parts of the association share: the groups, the members' index, the frames and the loop closures.

    ``slot`` maps a group id to its place in ``groups``; ``next_id`` is the id the next new group
    gets. Map positions (:meth:`pose_of`) apply the back-end's estimate of a member's frame to its
    centroid, or the odometry pose when no back-end runs.
    """

    def __init__(self) -> None:
        self.groups: list[SgfGroup] = []
        self.frames = FrameLog(keep=HISTORY_FRAMES)
        self.next_id = 0
        self.index = MemberIndex()
        self.slot: dict[int, int] = {}
        self.closures: list[Closure] = []

    def reset(self, prior: list[SgfGroup]) -> None:
        """Start a sequence with copies of the prior groups (their members indexed at their anchors) only."""
        self.groups = [copy.copy(g) for g in prior]
        for g, p in zip(self.groups, prior, strict=True):
            g.members, g.offsets, g.anchors = list(p.members), list(p.offsets), list(p.anchors)
        self.next_id = max((g.group_id for g in prior), default=-1) + 1
        self.frames = FrameLog(keep=HISTORY_FRAMES)
        self.index = MemberIndex()
        self.slot = {g.group_id: k for k, g in enumerate(self.groups)}
        self.closures = []
        for k, group in enumerate(self.groups):
            for member, anchor in zip(group.members, group.anchors, strict=True):
                self.index.add(k, member, None, anchor)

    def record(self, frame: Frame) -> None:
        """Remember the frame's odometry and the distance travelled up to it (the last HISTORY_FRAMES frames)."""
        self.frames.append(frame)  # bounded over hours: the oldest frames go, members keep theirs

    def remember_loops(self, loops: LoopConstraints | None) -> None:
        """Keep this run's accepted loop closures (map matches are anchored by the map's own gate)."""
        for c in () if loops is None else loops.items:
            if c.from_map:
                continue
            ends = [self.travelled_at(c.frame_from), self.travelled_at(c.frame_to)]
            if all(t is not None for t in ends):
                self.closures.append(Closure(c.frame_from, c.frame_to, np.asarray(c.relative), *ends))  # type: ignore[arg-type]

    def travelled_at(self, frame_index: int) -> float | None:
        """Distance travelled up to a frame: remembered for recent frames and for group members."""
        known = self.frames.get_distance(frame_index)
        if known is not None:
            return known
        index = self.index
        hits = np.flatnonzero(index.frame[: index.size] == frame_index)
        if hits.size and not math.isnan(index.travelled[hits[0]]):
            return float(index.travelled[hits[0]])
        return None

    def pose_of(self, frame_index: int, odometry: np.ndarray, estimate: PoseEstimate | None) -> np.ndarray:
        """The map pose of a frame: the estimate's, else its odometry corrected like the estimate's newest frame."""
        if estimate is None:
            return odometry
        pose = estimate.poses.get(frame_index)
        if pose is not None:
            return np.asarray(pose, dtype=np.float64)
        ref = estimate.frame_index
        ref_odometry = self.frames.get_odometry(ref)
        if ref_odometry is None or ref not in estimate.poses:
            return odometry
        return np.asarray(estimate.poses[ref]) @ invert(ref_odometry) @ odometry

    def map_pose(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> np.ndarray:
        """The map pose of the frame a descriptor was seen from (:meth:`pose_of` its frame)."""
        sgf = descriptor.sgf
        return self.pose_of(sgf.frame_index, np.asarray(sgf.odometry, dtype=np.float64), estimate)

    def position_of(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> np.ndarray:
        """The map position (x, y) of a descriptor's centroid."""
        pose = self.map_pose(descriptor, estimate)
        c = descriptor.centroid
        return pose[:2, :2] @ np.asarray(c[:2], dtype=np.float64) + pose[:2, 3]

    def member_positions(self, estimate: PoseEstimate | None) -> np.ndarray:
        """Map positions (x, y) of every member, cached for one estimate (members that joined since are added)."""
        index = self.index
        done = len(index.positions) if index.estimate is estimate else 0
        if done < index.size:
            fresh = slice(done, index.size)
            odometry = index.odometry[fresh]
            if estimate is None:
                poses = odometry
            else:
                poses, found = estimate.stack(index.frame[fresh])
                if not found.all():
                    ref = estimate.frame_index
                    ref_odometry = self.frames.get_odometry(ref)
                    if ref_odometry is None or ref not in estimate.poses:
                        poses[~found] = odometry[~found]
                    else:
                        correction = np.asarray(estimate.poses[ref]) @ invert(ref_odometry)
                        poses[~found] = correction @ odometry[~found]
            positions = np.einsum("nij,nj->ni", poses[:, :2, :2], index.centroid[fresh]) + poses[:, :2, 3]
            anchor = index.anchor[fresh]
            anchored = ~np.isnan(anchor[:, 0])
            positions[anchored] = anchor[anchored]
            index.positions = np.concatenate([index.positions[:done], positions])
            index.estimate = estimate
        return index.positions

    def predicted_shift(self, query: SgfDescriptor, member: SgfDescriptor, estimate: PoseEstimate | None) -> float:
        """The (fractional) column shift of the query against the member that their map poses predict."""
        yaw = xy_yaw(self.map_pose(query, estimate))[2] - xy_yaw(self.map_pose(member, estimate))[2]
        return yaw_to_shift(yaw, query.matrix.shape[1])
