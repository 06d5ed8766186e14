"""The pose graph of eq. 11 in GTSAM: pose nodes of processed frames, odometry and SGF loop factors.

Nodes are processed frames (``x<frame index>``): every one, or with ``node_distance`` one every so
many metres plus the newest frame of each loop; a frame between nodes keeps its odometry offset
from its node, and loops that reach it are moved onto that node (the loop's relative pose composed
with the offset, its covariance carried by the offset's adjoint). When localizing on a prior SGF map,
the map's frames that SGFs were matched to (``m<map frame index>``, held by priors at their
map poses). Poses are ``Pose2`` or ``Pose3`` (roll and pitch from the IMU as attitude factors).
With ``NoiseSettings.yaw_bias_sigma`` set, the odometry's heading bias per metre is estimated from
the loops and taken off the odometry steps that follow (:mod:`sgf_plugins.shared.heading_bias`).
The graph's factors and noise models are built by :mod:`sgf_plugins.backend.factors`, its nodes
laid out by :mod:`sgf_plugins.backend.nodes`, its poses kept in :mod:`sgf_plugins.backend.poses`
and the odometry corrected by :mod:`sgf_plugins.backend.odometry_correction`.
GTSAM is imported inside functions so that listing plugins stays fast.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from sgf_pipeline.geometry import invert
from sgf_pipeline.types import Frame, LoopConstraint
from sgf_plugins.backend.factors import FactorBuilder, M, NoiseSettings, PoseKind, X, planar
from sgf_plugins.backend.nodes import NodeChain
from sgf_plugins.backend.odometry_correction import OdometryCorrection
from sgf_plugins.backend.poses import PoseStore
from sgf_plugins.shared.heading_bias import HeadingBias

FREE_ROLL_PITCH = 0.1  # rad, first-pose prior on roll and pitch (observed by the IMU, not a gauge)


class PoseGraph:
    """The factors and current estimate of eq. 11, built frame by frame.

    New factors and values are also collected apart (``take_new``) for incremental solvers. When
    localizing on a prior map (``map_poses``), the run's frames start in the odometry frame under
    a prior on the first pose; the first inter-session factor moves them into the map frame
    (``anchor``) and drops that prior, since the map's poses then fix the gauge.
    """

    def __init__(
        self,
        pose: PoseKind,
        noise: NoiseSettings,
        map_poses: Mapping[int, np.ndarray] | None = None,
        node_distance: float = 0.0,
    ) -> None:
        import gtsam

        self.pose3 = pose == "pose3"
        self.noise = noise
        self.build = FactorBuilder(self.pose3, noise)
        self.map_poses = dict(map_poses or {})
        self.store = PoseStore(lifted=not self.pose3)
        self.timestamps: list[float] = []
        self.factors: list[Any] = []
        self.values = gtsam.Values()
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        self.map_nodes: set[int] = set()
        self.loop_factors = 0
        self.map_factors = 0
        self.anchored = not self.map_poses
        self._prior: Any = None
        self.chain = NodeChain(node_distance)
        self.odometry = OdometryCorrection(noise)

    @property
    def nodes(self) -> list[int]:
        """The node frames, in order (GTSAM keys sort the same way)."""
        return self.chain.frames

    @property
    def heading_bias(self) -> HeadingBias | None:
        """The odometry's heading bias as estimated so far (None when it is not estimated)."""
        return self.odometry.heading_bias

    def _add(self, factor: Any) -> None:
        self.factors.append(factor)
        self.new_factors.push_back(factor)

    def _insert(self, key: int, pose: np.ndarray) -> None:
        value = self.build.pose(pose)
        self.values.insert(key, value)
        self.new_values.insert(key, value)

    # -- building ---------------------------------------------------------------------------

    def add_frame(self, frame: Frame, scale: float = 1.0, camera_bias: tuple[float, float] | None = None) -> None:
        """Add a processed frame: a node (odometry factor of eq. 11, IMU attitude), or a pose riding on the last one.

        A frame gets a node once ``node_distance`` of travel has passed since the last node.
        ``scale`` multiplies the odometry's step to this frame (the odometry's scale factor known now);
        ``camera_bias`` is the camera's estimate of the heading bias and its sigma (rad/m) known now.
        """
        index = frame.index
        if index in self.store.rows:
            raise ValueError(f"frame {index} was added to the pose graph twice")
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        if odometry.shape != (4, 4) or not np.all(np.isfinite(odometry)):
            raise ValueError(f"frame {index}: odometry must be a finite 4x4 pose")
        odometry = self.odometry.correct(index, odometry, scale, camera_bias)
        lift = None
        if not self.pose3:
            # Pose2 corrects x, y, yaw; the odometry's height, roll and pitch ride along unchanged.
            lift = invert(planar(odometry)) @ odometry
            odometry = planar(odometry)
        row = self.store.size
        due = self.chain.step(row, odometry, frame.imu_roll_pitch)
        self.timestamps.append(float(frame.timestamp))
        if due:
            self.store.append(index, np.eye(4), lift)
            self._make_node(index)
        else:
            offset = self.chain.ride(row, odometry)
            node_pose = self.store.get(self.nodes[-1])
            assert node_pose is not None
            self.store.append(index, node_pose @ offset, lift)

    def is_node(self, frame_index: int) -> bool:
        """Whether the frame has its own node (else its pose rides on its node's by odometry)."""
        row = self.store.rows.get(frame_index)
        return row is not None and self.chain.node_of(row) == frame_index

    def _make_node(self, index: int) -> None:
        """Give the newest frame (already in the store) its node, odometry factor and IMU attitude."""
        chain = self.chain
        odometry = chain.last_odometry
        assert odometry is not None and self.store.frames[-1] == index
        key = X(index)
        if not self.nodes:
            initial = odometry
            # Fixes the gauge in the odometry frame (when localizing, anchoring drops it for the map's).
            # Roll and pitch are no gauge freedom: gravity (the IMU) observes them, so they stay loose.
            n = self.noise
            model = self.build.diagonal(n.prior_sigma_xy, n.prior_sigma_yaw, n.prior_sigma_xy, FREE_ROLL_PITCH)
            self._prior = self.build.prior(key, initial, model)
            self._add(self._prior)
        else:
            relative = invert(chain.odometries[-1]) @ odometry
            node_pose = self.store.get(self.nodes[-1])
            assert node_pose is not None
            initial = node_pose @ relative
            model = self.build.odometry_noise(relative, chain.pending_distance, chain.pending_steps)
            factor = self.build.between(X(self.nodes[-1]), key, relative, model)
            self._add(factor)
            chain.link(factor)
        if self.pose3 and chain.pending_imu is not None:
            self._add(self.build.attitude(key, *chain.pending_imu))
        self._insert(key, initial)
        chain.append(index, self.store.size - 1, odometry)
        self.store.set_latest(self.build.matrix(self.build.pose(initial)))

    def _on_node(
        self, frame_index: int, relative: np.ndarray, side: Literal["from", "to"]
    ) -> tuple[int, np.ndarray, np.ndarray | None]:
        """A loop's end frame: its node's frame, the relative pose moved onto that node, and the covariance's adjoint.

        The adjoint is None when the covariance stays as it is; the newest frame becomes a node.
        """
        row = self.store.rows[frame_index]
        if self.chain.node_of(row) != frame_index and frame_index == self.store.frames[-1]:
            self._make_node(frame_index)
        node = self.chain.node_of(row)
        if node == frame_index:
            return node, relative, None
        offset = self.chain.offset[row]
        if side == "from":  # T_node^-1 T_to = offset @ relative: the error (in the 'to' frame) is the same
            return node, offset @ relative, None
        # T_from^-1 T_node = relative @ offset^-1, its error is the 'to' error moved by offset's adjoint
        return node, relative @ invert(offset), np.asarray(self.build.pose(offset).AdjointMap())

    def add_loop(self, loop: LoopConstraint) -> bool:
        """Add an SGF loop factor (eq. 11, second sum); returns whether it anchored the run in the map."""
        if loop.frame_to not in self.store.rows:
            raise ValueError(f"loop constraint to frame {loop.frame_to}, which is not a processed frame")
        relative = np.asarray(loop.relative, dtype=np.float64)
        if relative.shape != (4, 4) or not np.all(np.isfinite(relative)):
            raise ValueError("a loop constraint's relative pose must be a finite 4x4 matrix")
        self.odometry.observe(loop, relative)
        if not self.pose3:
            relative = planar(relative)
        node_to, relative, adjoint = self._on_node(loop.frame_to, relative, "to")
        anchored = False
        if loop.from_map:
            if loop.frame_from not in self.map_poses:
                raise ValueError(
                    f"inter-session loop from map frame {loop.frame_from}, which the prior map does not hold "
                    "(is the back-end's prior_map the map the association matched against?)"
                )
            key_from = M(loop.frame_from)
            if loop.frame_from not in self.map_nodes:
                self._add_map_node(loop.frame_from)
            if not self.anchored:
                self.anchor(self.map_poses[loop.frame_from] @ relative, node_to)
                anchored = True
            self.map_factors += 1
        else:
            if loop.frame_from not in self.store.rows:
                raise ValueError(f"loop constraint from frame {loop.frame_from}, which is not a processed frame")
            node_from, relative, _ = self._on_node(loop.frame_from, relative, "from")
            key_from = X(node_from)
            self.loop_factors += 1
        noise = self.build.loop_noise(loop.covariance, adjoint)
        factor = self.build.between(key_from, X(node_to), relative, noise)
        self._add(factor)
        return anchored

    def hindsight_heading_bias(self) -> bool:
        """Take the heading bias now known off every odometry step from the first frame on; False if none is.

        Online, a bias corrects only the drive after the loops that measured it; at the end of a run
        the whole drive is known to share it. A loop far from the drive's start (a route whose first
        revisit comes after kilometres) otherwise has to bend all the uncorrected drive back alone.
        """
        corrected = self.odometry.in_hindsight(self.store.size)
        if corrected is None:
            return False
        self._set_odometry(corrected)
        self.rebuild_new()
        return True

    def _set_odometry(self, corrected: np.ndarray) -> None:
        """New odometry (N, 4, 4) of the processed frames: the nodes', the frames' offsets and the odometry factors."""
        if not self.pose3:
            corrected = np.stack([planar(pose) for pose in corrected])
        replaced = self.chain.set_odometry(corrected, self.store.rows, self.build)
        self.factors = [replaced.get(id(f), f) for f in self.factors]

    def dead_reckoned(self) -> Any:
        """The estimate with every node placed by the odometry from the first node's current pose.

        A start for re-solving a graph that lost loops: their pull may have left the current estimate
        far from the remaining loops' optimum. Map nodes keep their current poses.
        """
        import gtsam

        values = gtsam.Values(self.values)
        base = self.build.matrix(
            self.values.atPose3(X(self.nodes[0])) if self.pose3 else self.values.atPose2(X(self.nodes[0]))
        )
        start = invert(self.chain.odometries[0])
        for frame, odometry in zip(self.nodes, self.chain.odometries, strict=True):
            values.update(X(frame), self.build.pose(base @ start @ odometry))
        return values

    def _add_map_node(self, map_frame: int) -> None:
        n = self.noise
        pose = self.map_poses[map_frame]
        if not self.pose3:
            pose = planar(pose)
        model = self.build.diagonal(n.map_sigma_xy, n.map_sigma_yaw, n.map_sigma_xy, n.map_sigma_yaw)
        self._add(self.build.prior(M(map_frame), pose, model))
        self._insert(M(map_frame), pose)
        self.map_nodes.add(map_frame)

    def anchor(self, pose_in_map: np.ndarray, frame_index: int) -> None:
        """Move the run into the map frame so that ``frame_index`` lands on ``pose_in_map``; drop the first prior."""
        import gtsam

        current = self.store.get(frame_index)
        assert current is not None
        align = (pose_in_map if self.pose3 else planar(pose_in_map)) @ invert(current)
        if not self.pose3:
            align = planar(align)
        poses = np.einsum("ij,njk->nik", align, self.store.buffer[: self.store.size])
        self.store.replace_all(poses)
        values = gtsam.Values()
        for m in self.map_nodes:
            pose = self.map_poses[m] if self.pose3 else planar(self.map_poses[m])
            values.insert(M(m), self.build.pose(pose))
        for frame in self.nodes:
            values.insert(X(frame), self.build.pose(poses[self.store.rows[frame]]))
        self.values = values
        self.factors = [f for f in self.factors if f is not self._prior]
        self.anchored = True
        self.rebuild_new()

    def rebuild_new(self) -> None:
        """Make every factor and value 'new' (an incremental solver must then start over)."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in self.factors:
            graph.push_back(f)
        self.new_factors = graph
        self.new_values = gtsam.Values(self.values)

    def take_new(self) -> tuple[Any, Any]:
        """The factors and values added since the last call (for iSAM2)."""
        import gtsam

        graph, values = self.new_factors, self.new_values
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        return graph, values

    def graph(self) -> Any:
        """Every factor as one graph (for batch optimisation)."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in self.factors:
            graph.push_back(f)
        return graph

    # -- exchange -----------------------------------------------------------------------------

    def g2o(self) -> tuple[str, int, int]:
        """The graph at its current estimate as g2o text, with its numbers of vertices and edges.

        ``VERTEX_SE2 <frame index> x y theta`` per node (the estimate) and ``EDGE_SE2 <from> <to>
        dx dy dtheta`` plus the upper triangle of the information matrix per between factor (odometry
        and loops), then ``FIX <first node>``: the prior that holds the first pose has no g2o line.
        A loop under a robust kernel carries its information scaled by the kernel's weight at the
        estimate, so that the read-back graph (Gaussian, as g2o's edges are) has the same optimum.
        """
        import gtsam

        if self.pose3 or self.map_poses:
            raise ValueError("a g2o file holds a Pose2 graph of one session: pose=pose2 without a prior map")
        lines = []
        for frame in self.nodes:
            pose = self.values.atPose2(X(frame))
            lines.append(f"VERTEX_SE2 {frame} {pose.x()!r} {pose.y()!r} {pose.theta()!r}")
        edges = 0
        for factor in self.factors:
            if isinstance(factor, gtsam.PriorFactorPose2):
                continue
            if not isinstance(factor, gtsam.BetweenFactorPose2):  # pragma: no cover - the graph has no other
                raise ValueError(f"a {type(factor).__name__} has no g2o edge")
            keys = factor.keys()
            a, b = gtsam.Symbol(keys[0]).index(), gtsam.Symbol(keys[1]).index()
            m = factor.measured()
            info = _information(factor, self.values)
            upper = " ".join(repr(float(info[i, j])) for i in range(3) for j in range(i, 3))
            lines.append(f"EDGE_SE2 {a} {b} {m.x()!r} {m.y()!r} {m.theta()!r} {upper}")
            edges += 1
        if self.nodes:
            lines.append(f"FIX {self.nodes[0]}")
        return "\n".join(lines) + "\n", len(self.nodes), edges

    # -- estimates --------------------------------------------------------------------------

    def session_poses(self, values: Any) -> np.ndarray:
        """The (N, 4, 4) poses of the processed frames, from their nodes' poses in ``values`` (map nodes left out)."""
        out = self.build.poses(values)
        # Keys 'm...' sort before 'x...', and frame indices (so nodes) increase with insertion.
        out = out[len(out) - len(self.nodes) :]
        if len(out) != len(self.nodes):
            raise RuntimeError(f"the solver returned {len(out)} poses for {len(self.nodes)} nodes")
        return self.chain.spread(out, self.store.size)

    def set_values(self, values: Any) -> None:
        """Adopt a new full estimate (after an optimisation)."""
        self.values = values
        self.store.replace_all(self.session_poses(values))

    def set_latest(self, value: Any) -> None:
        """Adopt a solver's estimate of the newest frame only."""
        self.store.set_latest(self.build.matrix(value))

    def error(self, values: Any | None = None) -> float:
        """The total error of eq. 11 (robust kernels applied) at ``values`` (default: the current estimate)."""
        return float(self.graph().error(self.values if values is None else values))


def _information(factor: Any, values: Any) -> np.ndarray:
    """A factor's information matrix; under a robust kernel, scaled by the kernel's weight at ``values``.

    At an optimum of the robust graph, the Gaussian graph of these weights is stationary too
    (iteratively reweighted least squares), so both have the same optimum.
    """
    import gtsam

    model = factor.noiseModel()
    weight = 1.0
    if isinstance(model, gtsam.noiseModel.Robust):
        gaussian = model.noise()
        whitened = gaussian.whiten(factor.unwhitenedError(values))
        kernel = model.robust()
        weight = float(kernel.weight(float(np.linalg.norm(whitened))))  # type: ignore[attr-defined]
        model = gaussian
    sqrt_information = np.asarray(model.R(), dtype=np.float64)
    return weight * sqrt_information.T @ sqrt_information
