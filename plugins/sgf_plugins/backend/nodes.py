"""The pose nodes along the drive: which processed frames have a node, and where the others ride on theirs.

Nodes are every processed frame, or with ``node_distance`` one every so many metres of travel
(plus the newest frame of each loop); a frame between nodes keeps its odometry offset from its
node. The chain also holds each node's (corrected) odometry and the odometry factor that reaches it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sgf_pipeline.geometry import invert
from sgf_plugins.backend.factors import FactorBuilder, X
from sgf_plugins.backend.poses import grown


class NodeChain:
    """The nodes in order (GTSAM keys sort the same way) and every processed frame's place on them."""

    def __init__(self, node_distance: float = 0.0) -> None:
        self.node_distance = node_distance
        self.frames: list[int] = []  # node frames, in order
        self.node_of_row = np.zeros(64, dtype=np.int64)  # per processed frame: its node's place in ``frames``
        self.offset = np.zeros((64, 4, 4))  # per processed frame: its pose in its node's frame (odometry)
        self.odometries: list[np.ndarray] = []  # per node, in order: its (corrected) odometry pose
        self.odometry_factors: list[Any] = []  # per node from the second: the odometry factor that reaches it
        self.spans: list[tuple[float, int]] = []  # ...and the path length and frames that factor spans
        self.last_odometry: np.ndarray | None = None
        self.pending_distance = 0.0
        self.pending_steps = 0
        self.pending_imu: tuple[float, float] | None = None

    def step(self, row: int, odometry: np.ndarray, imu_roll_pitch: tuple[float, float] | None) -> bool:
        """Record the (corrected) odometry of the processed frame at ``row``; whether it is due a node."""
        if self.last_odometry is not None:
            self.pending_distance += float(np.linalg.norm(odometry[:3, 3] - self.last_odometry[:3, 3]))
            self.pending_steps += 1
        self.last_odometry = odometry
        self.pending_imu = imu_roll_pitch
        if row == len(self.node_of_row):
            self.node_of_row = grown(self.node_of_row, row)
            self.offset = grown(self.offset, row)
        return not self.frames or self.pending_distance >= self.node_distance

    def ride(self, row: int, odometry: np.ndarray) -> np.ndarray:
        """Put the frame at ``row`` on the newest node; its offset from that node."""
        offset = invert(self.odometries[-1]) @ odometry
        self.node_of_row[row] = len(self.frames) - 1
        self.offset[row] = offset
        return offset

    def node_of(self, row: int) -> int:
        """The node frame of the processed frame at ``row``."""
        return self.frames[self.node_of_row[row]]

    def link(self, factor: Any) -> None:
        """Keep the odometry factor that reaches the next node, with the path it spans."""
        self.odometry_factors.append(factor)
        self.spans.append((self.pending_distance, self.pending_steps))

    def append(self, index: int, row: int, odometry: np.ndarray) -> None:
        """Make the processed frame ``index`` at ``row`` the newest node, at ``odometry``."""
        self.frames.append(index)
        self.node_of_row[row] = len(self.frames) - 1
        self.offset[row] = np.eye(4)
        self.odometries.append(odometry)
        self.pending_distance = 0.0
        self.pending_steps = 0

    def set_odometry(self, corrected: np.ndarray, rows: dict[int, int], build: FactorBuilder) -> dict[int, Any]:
        """New odometry (N, 4, 4) of the processed frames; the new odometry factors by the id of those they replace."""
        size = len(corrected)
        self.odometries = [corrected[rows[node]] for node in self.frames]
        nodes = np.array(self.odometries)
        self.offset[:size] = np.matmul(np.linalg.inv(nodes[self.node_of_row[:size]]), corrected)
        self.last_odometry = corrected[-1]
        replaced: dict[int, Any] = {}
        for i, (old_factor, (distance, steps)) in enumerate(zip(self.odometry_factors, self.spans, strict=True)):
            relative = invert(self.odometries[i]) @ self.odometries[i + 1]
            model = build.odometry_noise(relative, distance, steps)
            factor = build.between(X(self.frames[i]), X(self.frames[i + 1]), relative, model)
            replaced[id(old_factor)] = factor
            self.odometry_factors[i] = factor
        return replaced

    def spread(self, node_poses: np.ndarray, size: int) -> np.ndarray:
        """The poses of the first ``size`` processed frames from their nodes' poses (N, 4, 4)."""
        if len(self.frames) == size:
            return node_poses
        return np.matmul(node_poses[self.node_of_row[:size]], self.offset[:size])
