"""The pose graph of eq. 11 in GTSAM: pose nodes of processed frames, odometry and SGF loop factors.

Nodes are processed frames (``x<frame index>``): every one, or with ``node_distance`` one every so
many metres plus the newest frame of each loop; a frame between nodes keeps its odometry offset
from its node, and loops that reach it are moved onto that node (the loop's relative pose composed
with the offset, its covariance carried by the offset's adjoint). When localizing on a prior SGF map,
the map's frames that SGFs were matched to (``m<map frame index>``, held by priors at their
map poses). Poses are ``Pose2`` or ``Pose3`` (roll and pitch from the IMU as attitude factors).
With ``NoiseSettings.yaw_bias_sigma`` set, the odometry's heading bias per metre is estimated from
the loops and taken off the odometry steps that follow (:mod:`sgf_plugins.backend.heading_bias`).
GTSAM is imported inside functions so that listing plugins stays fast.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from sgf_pipeline.geometry import invert, rotation_rpy, xy_yaw
from sgf_pipeline.types import Frame, LoopConstraint
from sgf_plugins.backend.heading_bias import HeadingBias, ScaledOdometry, with_heading_bias
from sgf_plugins.odometry.drift import EXPECTED_YAW_BIAS

PoseKind = Literal["pose2", "pose3"]
FREE_ROLL_PITCH = 0.1  # rad, first-pose prior on roll and pitch (observed by the IMU, not a gauge)
Kernel = Literal["cauchy", "huber", "none"]


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
            self.buffer = _grown(self.buffer, self.size)
        if self.lift is not None and self.size == len(self.lift):
            self.lift = _grown(self.lift, self.size)
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


def _grown(buffer: np.ndarray, size: int) -> np.ndarray:
    """A buffer of twice the capacity holding the first ``size`` rows of ``buffer``."""
    grown = np.zeros((2 * len(buffer), *buffer.shape[1:]), dtype=buffer.dtype)
    grown[:size] = buffer[:size]
    return grown


@dataclass(frozen=True)
class NoiseSettings:
    """Noise models of eq. 11: odometry sigmas grow with the square root of the distance travelled."""

    odometry_sigma_xy: float = 0.05
    odometry_sigma_yaw: float = math.radians(0.5)
    odometry_sigma_z: float = 0.02
    odometry_sigma_roll_pitch: float = math.radians(2.0)
    odometry_floor_xy: float = 0.005
    odometry_floor_yaw: float = math.radians(0.05)
    imu_sigma_roll_pitch: float = math.radians(0.5)
    loop_sigma_z: float = 0.05
    loop_sigma_roll_pitch: float = math.radians(1.0)
    loop_kernel: Kernel = "cauchy"
    loop_kernel_width: float = 3.0
    prior_sigma_xy: float = 1e-3
    prior_sigma_yaw: float = 1e-4
    map_sigma_xy: float = 0.05
    map_sigma_yaw: float = math.radians(0.5)
    yaw_bias_sigma: float | None = None  # rad/m, prior sigma of the odometry's heading bias (None: not estimated)
    yaw_bias_reading_sigma: float = EXPECTED_YAW_BIAS  # rad/m, the sigma that chooses between aliased readings


FRAME_SYMBOL = "x"  # GTSAM key character of a processed frame's pose
MAP_SYMBOL = "m"  # ...and of a prior map frame's pose


def X(frame_index: int) -> int:
    """GTSAM key of a processed frame's pose."""
    import gtsam

    return int(gtsam.symbol(FRAME_SYMBOL, frame_index))


def M(map_frame: int) -> int:
    """GTSAM key of a prior map frame's pose."""
    import gtsam

    return int(gtsam.symbol(MAP_SYMBOL, map_frame))


def planar(pose: np.ndarray) -> np.ndarray:
    """The planar part of a 4x4 pose, as a 4x4 pose (z, roll and pitch dropped)."""
    x, y, yaw = xy_yaw(pose)
    out = np.eye(4)
    out[:3, :3] = rotation_rpy(0.0, 0.0, yaw)
    out[:2, 3] = (x, y)
    return out


def _orthonormal(rot: np.ndarray) -> np.ndarray:
    """The nearest rotation matrix (guards against drift in composed poses)."""
    u, _, vt = np.linalg.svd(rot)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


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
        self._loop_factor: dict[tuple[int, int, bool], list[Any]] = {}  # per loop's ends: its factors
        self.anchored = not self.map_poses
        self._prior: Any = None
        self._last_odometry: np.ndarray | None = None
        # Nodes: every frame, or with ``node_distance`` the frames this far apart (and those loops reach).
        self.node_distance = node_distance
        self.nodes: list[int] = []  # node frames, in order (GTSAM keys sort the same way)
        self._node_of_row = np.zeros(64, dtype=np.int64)  # per processed frame: its node's place in ``nodes``
        self._offset = np.zeros((64, 4, 4))  # per processed frame: its pose in its node's frame (odometry)
        self._node_odometries: list[np.ndarray] = []  # per node, in order: its (corrected) odometry pose
        self._odometry_factors: list[Any] = []  # per node from the second: the odometry factor that reaches it
        self._node_spans: list[tuple[float, int]] = []  # ...and the path length and frames that factor spans
        # For a replay of the heading bias without loops taken back: per processed frame its odometry
        # before the bias correction, and per loop the bias saw (newest frame then, ends, yaw, variance).
        self._scaled = np.zeros((64, 4, 4))
        self._camera_bias = np.full((64, 2), np.inf)  # per processed frame: the camera's heading bias and sigma
        self._bias_loops: list[tuple[int, tuple[int, int, bool], float, float]] = []
        self._pending_distance = 0.0
        self._pending_steps = 0
        self._pending_imu: tuple[float, float] | None = None
        self.scaled_odometry = ScaledOdometry()
        self.heading_bias = (
            None
            if noise.yaw_bias_sigma is None
            else HeadingBias(
                noise.yaw_bias_sigma,
                noise.odometry_sigma_yaw,
                noise.loop_kernel_width,
                reading_sigma=noise.yaw_bias_reading_sigma,
            )
        )

    # -- gtsam conversions ------------------------------------------------------------------

    def _gtsam_pose(self, pose: np.ndarray) -> Any:
        import gtsam

        if self.pose3:
            return gtsam.Pose3(gtsam.Rot3(_orthonormal(pose[:3, :3])), np.asarray(pose[:3, 3], dtype=np.float64))
        x, y, yaw = xy_yaw(pose)
        return gtsam.Pose2(x, y, yaw)

    def _matrix(self, value: Any) -> np.ndarray:
        if self.pose3:
            return np.asarray(value.matrix(), dtype=np.float64)
        return planar_from_xyt(np.array([[value.x(), value.y(), value.theta()]]))[0]

    def _diagonal(self, xy: float, yaw: float, z: float, roll_pitch: float) -> Any:
        import gtsam

        if self.pose3:
            return gtsam.noiseModel.Diagonal.Sigmas(np.array([roll_pitch, roll_pitch, yaw, xy, xy, z]))
        return gtsam.noiseModel.Diagonal.Sigmas(np.array([xy, xy, yaw]))

    def _prior_factor(self, key: int, pose: np.ndarray, model: Any) -> Any:
        import gtsam

        factor = gtsam.PriorFactorPose3 if self.pose3 else gtsam.PriorFactorPose2
        return factor(key, self._gtsam_pose(pose), model)

    def _between_factor(self, key_a: int, key_b: int, relative: np.ndarray, model: Any) -> Any:
        import gtsam

        factor = gtsam.BetweenFactorPose3 if self.pose3 else gtsam.BetweenFactorPose2
        return factor(key_a, key_b, self._gtsam_pose(relative), model)

    def _add(self, factor: Any) -> None:
        self.factors.append(factor)
        self.new_factors.push_back(factor)

    def _insert(self, key: int, pose: np.ndarray) -> None:
        value = self._gtsam_pose(pose)
        self.values.insert(key, value)
        self.new_values.insert(key, value)

    # -- building ---------------------------------------------------------------------------

    def odometry_noise(self, relative: np.ndarray, distance: float | None = None, steps: int = 1) -> Any:
        """Odometry noise: sigma^2 = steps * floor^2 + (sigma over one metre)^2 * distance (a random walk).

        ``distance`` is the path length over the ``steps`` frames the factor spans (default: one step,
        the length of ``relative``).
        """
        n = self.noise
        d = float(np.linalg.norm(relative[:3, 3])) if distance is None else distance
        xy = math.sqrt(steps * n.odometry_floor_xy**2 + n.odometry_sigma_xy**2 * d)
        yaw = math.sqrt(steps * n.odometry_floor_yaw**2 + n.odometry_sigma_yaw**2 * d)
        z = math.sqrt(steps * n.odometry_floor_xy**2 + n.odometry_sigma_z**2 * d)
        rp = math.sqrt(steps * n.odometry_floor_yaw**2 + n.odometry_sigma_roll_pitch**2 * d)
        return self._diagonal(xy, yaw, z, rp)

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
        odometry = self.scaled_odometry.correct(odometry, scale)
        scaled = odometry
        if self.heading_bias is not None:
            if camera_bias is not None:
                self.heading_bias.camera(*camera_bias)
            odometry = self.heading_bias.correct(index, odometry)
        lift = None
        if not self.pose3:
            # Pose2 corrects x, y, yaw; the odometry's height, roll and pitch ride along unchanged.
            lift = invert(planar(odometry)) @ odometry
            odometry = planar(odometry)
        if self._last_odometry is not None:
            self._pending_distance += float(np.linalg.norm(odometry[:3, 3] - self._last_odometry[:3, 3]))
            self._pending_steps += 1
        self._last_odometry = odometry
        self._pending_imu = frame.imu_roll_pitch
        row = self.store.size
        if row == len(self._node_of_row):
            self._node_of_row = _grown(self._node_of_row, row)
            self._offset = _grown(self._offset, row)
            self._scaled = _grown(self._scaled, row)
            self._camera_bias = _grown(self._camera_bias, row)
        self._scaled[row] = scaled
        self._camera_bias[row] = camera_bias if camera_bias is not None else (np.inf, np.inf)
        self.timestamps.append(float(frame.timestamp))
        if not self.nodes or self._pending_distance >= self.node_distance:
            self.store.append(index, np.eye(4), lift)
            self._make_node(index)
        else:
            offset = invert(self._node_odometries[-1]) @ odometry
            self._node_of_row[row] = len(self.nodes) - 1
            self._offset[row] = offset
            node_pose = self.store.get(self.nodes[-1])
            assert node_pose is not None
            self.store.append(index, node_pose @ offset, lift)

    def is_node(self, frame_index: int) -> bool:
        """Whether the frame has its own node (else its pose rides on its node's by odometry)."""
        row = self.store.rows.get(frame_index)
        return row is not None and self.nodes[self._node_of_row[row]] == frame_index

    def _make_node(self, index: int) -> None:
        """Give the newest frame (already in the store) its node, odometry factor and IMU attitude."""
        import gtsam

        odometry = self._last_odometry
        assert odometry is not None and self.store.frames[-1] == index
        key = X(index)
        if not self.nodes:
            initial = odometry
            # Fixes the gauge in the odometry frame (when localizing, anchoring drops it for the map's).
            # Roll and pitch are no gauge freedom: gravity (the IMU) observes them, so they stay loose.
            n = self.noise
            model = self._diagonal(n.prior_sigma_xy, n.prior_sigma_yaw, n.prior_sigma_xy, FREE_ROLL_PITCH)
            self._prior = self._prior_factor(key, initial, model)
            self._add(self._prior)
        else:
            relative = invert(self._node_odometries[-1]) @ odometry
            node_pose = self.store.get(self.nodes[-1])
            assert node_pose is not None
            initial = node_pose @ relative
            model = self.odometry_noise(relative, self._pending_distance, self._pending_steps)
            factor = self._between_factor(X(self.nodes[-1]), key, relative, model)
            self._add(factor)
            self._odometry_factors.append(factor)
            self._node_spans.append((self._pending_distance, self._pending_steps))
        if self.pose3 and self._pending_imu is not None:
            roll, pitch = self._pending_imu
            up = rotation_rpy(float(roll), float(pitch), 0.0).T @ np.array([0.0, 0.0, 1.0])
            model = gtsam.noiseModel.Isotropic.Sigma(2, self.noise.imu_sigma_roll_pitch)
            self._add(gtsam.AttitudeFactorPose3(key, gtsam.Unit3(np.array([0.0, 0.0, 1.0])), model, gtsam.Unit3(up)))
        self._insert(key, initial)
        row = self.store.size - 1
        self.nodes.append(index)
        self._node_of_row[row] = len(self.nodes) - 1
        self._offset[row] = np.eye(4)
        self.store.set_latest(self._matrix(self._gtsam_pose(initial)))
        self._node_odometries.append(odometry)
        self._pending_distance = 0.0
        self._pending_steps = 0

    def _on_node(
        self, frame_index: int, relative: np.ndarray, side: Literal["from", "to"]
    ) -> tuple[int, np.ndarray, np.ndarray | None]:
        """A loop's end frame: its node's frame, the relative pose moved onto that node, and the covariance's adjoint.

        The adjoint is None when the covariance stays as it is; the newest frame becomes a node.
        """
        row = self.store.rows[frame_index]
        if self.nodes[self._node_of_row[row]] != frame_index and frame_index == self.store.frames[-1]:
            self._make_node(frame_index)
        node = self.nodes[self._node_of_row[row]]
        if node == frame_index:
            return node, relative, None
        offset = self._offset[row]
        if side == "from":  # T_node^-1 T_to = offset @ relative: the error (in the 'to' frame) is the same
            return node, offset @ relative, None
        # T_from^-1 T_node = relative @ offset^-1, its error is the 'to' error moved by offset's adjoint
        return node, relative @ invert(offset), np.asarray(self._gtsam_pose(offset).AdjointMap())

    def loop_noise(self, covariance: np.ndarray, adjoint: np.ndarray | None = None) -> Any:
        """The loop factor's noise: the constraint's covariance (moved by ``adjoint``) under the robust kernel."""
        import gtsam

        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            raise ValueError(f"a loop covariance must be a finite 3x3 matrix over (x, y, yaw), got {cov!r}")
        cov = 0.5 * (cov + cov.T)
        if np.linalg.eigvalsh(cov).min() <= 0.0:
            raise ValueError("a loop covariance must be positive definite")
        if self.pose3:
            full = np.zeros((6, 6))
            idx = [3, 4, 2]  # (x, y, yaw) inside Pose3's (roll, pitch, yaw, x, y, z) tangent
            full[np.ix_(idx, idx)] = cov
            full[0, 0] = full[1, 1] = self.noise.loop_sigma_roll_pitch**2
            full[5, 5] = self.noise.loop_sigma_z**2
        else:
            full = cov
        if adjoint is not None:
            full = adjoint @ full @ adjoint.T
            full = 0.5 * (full + full.T)
        gaussian = gtsam.noiseModel.Gaussian.Covariance(full)
        kernel = self.noise.loop_kernel
        if kernel == "none":
            return gaussian
        width = self.noise.loop_kernel_width
        estimator = (
            gtsam.noiseModel.mEstimator.Cauchy.Create(width)
            if kernel == "cauchy"
            else gtsam.noiseModel.mEstimator.Huber.Create(width)
        )
        return gtsam.noiseModel.Robust.Create(estimator, gaussian)

    def add_loop(self, loop: LoopConstraint) -> bool:
        """Add an SGF loop factor (eq. 11, second sum); returns whether it anchored the run in the map."""
        if loop.frame_to not in self.store.rows:
            raise ValueError(f"loop constraint to frame {loop.frame_to}, which is not a processed frame")
        relative = np.asarray(loop.relative, dtype=np.float64)
        if relative.shape != (4, 4) or not np.all(np.isfinite(relative)):
            raise ValueError("a loop constraint's relative pose must be a finite 4x4 matrix")
        if self.heading_bias is not None and not loop.from_map and not loop.position_only:  # no turn to read
            yaw, variance = xy_yaw(relative)[2], float(loop.covariance[2][2])
            self.heading_bias.observe(loop.frame_from, loop.frame_to, yaw, variance)
            key = (loop.frame_from, loop.frame_to, loop.from_map)
            self._bias_loops.append((self.store.frames[-1], key, yaw, variance))
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
        noise = self.loop_noise(loop.covariance, adjoint)
        factor = self._between_factor(key_from, X(node_to), relative, noise)
        self._add(factor)
        self._loop_factor.setdefault((loop.frame_from, loop.frame_to, loop.from_map), []).append(factor)
        return anchored

    def remove_loops(self, loops: Sequence[LoopConstraint]) -> int:
        """Take loop factors back out of the graph (an incremental solver must then start over); their number.

        With the heading bias estimated, the odometry is corrected again as if those loops had never
        come (:meth:`_replay_heading_bias`): two false loops that agree would otherwise leave the
        bias they claimed in the odometry they were in for.
        """
        gone: list[Any] = []
        keys = {(loop.frame_from, loop.frame_to, loop.from_map) for loop in loops}
        if self.heading_bias is not None and any(b[1] in keys for b in self._bias_loops):
            self._replay_heading_bias(keys)
        for loop in loops:
            factors = self._loop_factor.pop((loop.frame_from, loop.frame_to, loop.from_map), [])
            gone.extend(factors)
            if loop.from_map:
                self.map_factors -= len(factors)
            else:
                self.loop_factors -= len(factors)
        if gone:
            ids = {id(f) for f in gone}
            self.factors = [f for f in self.factors if id(f) not in ids]
            self.rebuild_new()
        return len(gone)

    def _replay_heading_bias(self, keys: set[tuple[int, int, bool]]) -> None:
        """Correct the odometry again from the first frame on, the loops ``keys`` left out of the bias.

        Every frame and every other loop is given to a new estimator in the order they came, so the
        correction of each step is the one it would have had without those loops; the nodes'
        odometry, the frames' offsets on their nodes and the odometry factors follow it.
        """
        assert self.heading_bias is not None
        bias = self.heading_bias.restarted()
        self._bias_loops = [b for b in self._bias_loops if b[1] not in keys]
        size = self.store.size
        corrected = np.empty((size, 4, 4))
        k = 0
        for row, frame in enumerate(self.store.frames):
            bias.camera(*self._camera_bias[row])
            corrected[row] = bias.correct(frame, self._scaled[row])
            while k < len(self._bias_loops) and self._bias_loops[k][0] == frame:
                _, (frame_from, frame_to, _), yaw, variance = self._bias_loops[k]
                bias.observe(frame_from, frame_to, yaw, variance)
                k += 1
        self.heading_bias = bias
        self._set_odometry(corrected)

    def hindsight_heading_bias(self) -> bool:
        """Take the heading bias now known off every odometry step from the first frame on; False if none is.

        Online, a bias corrects only the drive after the loops that measured it; at the end of a run
        the whole drive is known to share it. A loop far from the drive's start (a route whose first
        revisit comes after kilometres) otherwise has to bend all the uncorrected drive back alone.
        """
        if self.heading_bias is None or self.heading_bias.value == 0.0 or not self.store.size:
            return False
        self._set_odometry(with_heading_bias(self._scaled[: self.store.size], self.heading_bias.value))
        self.rebuild_new()
        return True

    def _set_odometry(self, corrected: np.ndarray) -> None:
        """New odometry (N, 4, 4) of the processed frames: the nodes', the frames' offsets and the odometry factors."""
        size = self.store.size
        if not self.pose3:
            corrected = np.stack([planar(pose) for pose in corrected])
        self._node_odometries = [corrected[self.store.rows[node]] for node in self.nodes]
        nodes = np.array(self._node_odometries)
        self._offset[:size] = np.matmul(np.linalg.inv(nodes[self._node_of_row[:size]]), corrected)
        self._last_odometry = corrected[-1]
        replaced: dict[int, Any] = {}
        for i, (old_factor, (distance, steps)) in enumerate(zip(self._odometry_factors, self._node_spans, strict=True)):
            relative = invert(self._node_odometries[i]) @ self._node_odometries[i + 1]
            model = self.odometry_noise(relative, distance, steps)
            factor = self._between_factor(X(self.nodes[i]), X(self.nodes[i + 1]), relative, model)
            replaced[id(old_factor)] = factor
            self._odometry_factors[i] = factor
        self.factors = [replaced.get(id(f), f) for f in self.factors]

    def dead_reckoned(self) -> Any:
        """The estimate with every node placed by the odometry from the first node's current pose.

        A start for re-solving a graph that lost loops: their pull may have left the current estimate
        far from the remaining loops' optimum. Map nodes keep their current poses.
        """
        import gtsam

        values = gtsam.Values(self.values)
        base = self._matrix(
            self.values.atPose3(X(self.nodes[0])) if self.pose3 else self.values.atPose2(X(self.nodes[0]))
        )
        start = invert(self._node_odometries[0])
        for frame, odometry in zip(self.nodes, self._node_odometries, strict=True):
            values.update(X(frame), self._gtsam_pose(base @ start @ odometry))
        return values

    def _add_map_node(self, map_frame: int) -> None:
        n = self.noise
        pose = self.map_poses[map_frame]
        if not self.pose3:
            pose = planar(pose)
        model = self._diagonal(n.map_sigma_xy, n.map_sigma_yaw, n.map_sigma_xy, n.map_sigma_yaw)
        self._add(self._prior_factor(M(map_frame), pose, model))
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
            values.insert(M(m), self._gtsam_pose(pose))
        for frame in self.nodes:
            values.insert(X(frame), self._gtsam_pose(poses[self.store.rows[frame]]))
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

    # -- estimates --------------------------------------------------------------------------

    def session_poses(self, values: Any) -> np.ndarray:
        """The (N, 4, 4) poses of the processed frames, from their nodes' poses in ``values`` (map nodes left out)."""
        import gtsam

        if self.pose3:
            rows = np.asarray(gtsam.utilities.extractPose3(values))
            out = np.tile(np.eye(4), (len(rows), 1, 1))
            out[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
            out[:, :3, 3] = rows[:, 9:12]
        else:
            out = planar_from_xyt(np.asarray(gtsam.utilities.extractPose2(values)))
        # Keys 'm...' sort before 'x...', and frame indices (so nodes) increase with insertion.
        out = out[len(out) - len(self.nodes) :]
        if len(out) != len(self.nodes):
            raise RuntimeError(f"the solver returned {len(out)} poses for {len(self.nodes)} nodes")
        size = self.store.size
        if len(self.nodes) == size:
            return out
        return np.matmul(out[self._node_of_row[:size]], self._offset[:size])

    def set_values(self, values: Any) -> None:
        """Adopt a new full estimate (after an optimisation)."""
        self.values = values
        self.store.replace_all(self.session_poses(values))

    def set_latest(self, value: Any) -> None:
        """Adopt a solver's estimate of the newest frame only."""
        self.store.set_latest(self._matrix(value))

    def error(self, values: Any | None = None) -> float:
        """The total error of eq. 11 (robust kernels applied) at ``values`` (default: the current estimate)."""
        return float(self.graph().error(self.values if values is None else values))


def planar_from_xyt(xyt: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses from (N, 3) rows of ``x, y, yaw``."""
    xyt = np.asarray(xyt, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
    out = np.tile(np.eye(4), (len(xyt), 1, 1))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 0, 3], out[:, 1, 3] = xyt[:, 0], xyt[:, 1]
    return out
