"""The state the parts of the online SGF grouping share, and the map positions of its members."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.types import Frame, PoseEstimate, SgfDescriptor
from sgf_plugins.odometry.frame_log import FrameLog
from sgf_plugins.sgf.association.groups import MemberIndex, Ranking, SgfGroup
from sgf_plugins.sgf.association.params import OnlineGroupsParams
from sgf_plugins.sgf.polar import yaw_to_shift


@dataclass(frozen=True)
class Closure:
    """An accepted loop closure of this run and the distance travelled up to each of its frames."""

    frame_from: int
    frame_to: int
    relative: np.ndarray
    travelled_from: float
    travelled_to: float


class AssociationState:
    """What the parts of the association share: its parameters, the groups, the members' index and the frames.

    Map positions (:meth:`pose_of`) apply the back-end's estimate of a member's frame to its
    centroid, or the odometry pose when no back-end runs.
    """

    params: OnlineGroupsParams
    _groups: list[SgfGroup]
    _frames: FrameLog
    _next_id: int
    _index: MemberIndex
    _slot: dict[int, int]
    _closures: list[Closure]
    _shortcuts: tuple[object, list[tuple[float, float]]]
    _rankings: list[Ranking]
    _estimate: PoseEstimate | None
    _bias_began: tuple[int, float] | None

    def _record(self, frame: Frame) -> None:
        """Remember the frame's odometry and the distance travelled up to it (the last HISTORY_FRAMES frames)."""
        self._frames.append(frame)  # bounded over hours: the oldest frames go, members keep theirs

    def pose_of(self, frame_index: int, odometry: np.ndarray, estimate: PoseEstimate | None) -> np.ndarray:
        """The map pose of a frame: the estimate's, else its odometry corrected like the estimate's newest frame."""
        if estimate is None:
            return odometry
        pose = estimate.poses.get(frame_index)
        if pose is not None:
            return np.asarray(pose, dtype=np.float64)
        ref = estimate.frame_index
        ref_odometry = self._frames.get_odometry(ref)
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

    def _member_positions(self, estimate: PoseEstimate | None) -> np.ndarray:
        """Map positions (x, y) of every member, cached for one estimate (members that joined since are added)."""
        index = self._index
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
                    ref_odometry = self._frames.get_odometry(ref)
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

    def _predicted_shift(self, query: SgfDescriptor, member: SgfDescriptor, estimate: PoseEstimate | None) -> float:
        """The (fractional) column shift of the query against the member that their map poses predict."""
        yaw = xy_yaw(self.map_pose(query, estimate))[2] - xy_yaw(self.map_pose(member, estimate))[2]
        return yaw_to_shift(yaw, query.matrix.shape[1])
