"""Back-ends of eq. 11: GTSAM batch Levenberg-Marquardt, iSAM2, and odometry only (the baseline).

Every variant adds each processed frame's odometry, publishes a :class:`PoseEstimate` of every
processed frame on every frame (online), writes the final trajectory as ``trajectory_sgf.tum``
and, with ``save_map``, the run's SGF map (``sgf_map.safetensors``: the groups seen by the loop
stage, from the optimized poses). With ``graph=g2o`` the graph back-ends also write the final
pose graph (``pose_graph.g2o``). With ``prior_map`` the run is localized on an earlier run's
map: SGFs matched to it give inter-session factors to the map's frames, held by priors at their
map poses, and the run's trajectory ends in the map's frame.

The graph holds a pose node every ``node_distance`` metres (1 m by default, and on every frame a
loop ends on); the frames between ride on their node by odometry. A node per 0.25 m keyframe made
iSAM2's update and the full estimate of a loop frame four times as large for the same route.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from sgf_pipeline import RunContext, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.io import atomic_write_text
from sgf_pipeline.sgf_map import SgfMap, build_map, load_map, save_map
from sgf_pipeline.stage import Settlement
from sgf_pipeline.trajectory import Trajectory
from sgf_pipeline.types import (
    Frame,
    LoopConstraints,
    OdometryDrift,
    OdometryScale,
    PoseEstimate,
    YawBiasCorrection,
)
from sgf_plugins.backend.factors import FRAME_SYMBOL, MAP_SYMBOL, NoiseSettings, X
from sgf_plugins.backend.pose_graph import PoseGraph
from sgf_plugins.backend.poses import PoseStore

log = logging.getLogger("sgf_pipeline")
#: The file of the final pose graph (``graph=g2o``).
GRAPH_FILE = "pose_graph.g2o"


class BackendParams(StageParams):
    """What every back-end writes at the end of a run."""

    save_map: bool = Field(True, description="write the run's SGF map into the run directory")
    map_file: str = Field("sgf_map.safetensors", description="file name of the saved SGF map")


class GraphParams(BackendParams):
    """The pose graph of eq. 11: pose type, noise models, robust kernel, prior map."""

    pose: Literal["pose2", "pose3"] = Field("pose2", description="planar poses, or 3-D with IMU roll/pitch factors")
    odometry_sigma_xy: float = Field(0.05, gt=0.0, description="odometry translation sigma over one metre (m/sqrt(m))")
    odometry_sigma_yaw_deg: float = Field(
        0.5, gt=0.0, description="odometry heading sigma over one metre (deg/sqrt(m))"
    )
    odometry_sigma_z: float = Field(0.02, gt=0.0, description="pose3: height sigma over one metre (m/sqrt(m))")
    odometry_sigma_roll_pitch_deg: float = Field(
        2.0, gt=0.0, description="pose3: roll/pitch sigma over one metre (deg/sqrt(m)); loose, the IMU observes them"
    )
    odometry_floor_xy: float = Field(0.005, gt=0.0, description="odometry translation sigma of a standstill (m)")
    odometry_floor_yaw_deg: float = Field(0.05, gt=0.0, description="odometry heading sigma of a standstill (deg)")
    imu_sigma_roll_pitch_deg: float = Field(0.5, gt=0.0, description="pose3: sigma of the IMU attitude factor (deg)")
    loop_sigma_z: float = Field(0.05, gt=0.0, description="pose3: loop factor height sigma (m)")
    loop_sigma_roll_pitch_deg: float = Field(1.0, gt=0.0, description="pose3: loop factor roll/pitch sigma (deg)")
    loop_kernel: Literal["cauchy", "huber", "none"] = Field(
        "cauchy", description="robust kernel on loop factors (cauchy ignores gross outliers, huber bounds them)"
    )
    loop_kernel_width: float = Field(
        3.0,
        gt=0.0,
        description="kernel width in sigmas of the whitened loop error (a loop is closed from dead "
        "reckoning while its error is below about twice this many sigmas of the odometry chain)",
    )
    prior_sigma_xy: float = Field(1e-3, gt=0.0, description="prior on the first pose (m), fixes the map frame")
    prior_sigma_yaw_deg: float = Field(0.01, gt=0.0, description="prior on the first pose (deg)")
    node_distance: float = Field(
        1.0,
        ge=0.0,
        description="travel (m) between pose nodes; frames between ride on the last node by odometry "
        "(0 = a node per processed frame; the newest frame of a loop gets one)",
    )
    prior_map: str | None = Field(None, description="SGF map of an earlier run to localize on (inter-session factors)")
    map_sigma_xy: float = Field(0.05, gt=0.0, description="prior sigma of a prior map's frame poses (m)")
    map_sigma_yaw_deg: float = Field(0.5, gt=0.0, description="prior sigma of a prior map's frame poses (deg)")
    odometry_yaw_bias: bool = Field(
        True,
        description="estimate the odometry's heading bias per metre travelled from the loops, and take it off the "
        "odometry that follows (the drive after the last loop drifts less); false = eq. 11 as printed",
    )
    odometry_yaw_bias_sigma_deg_per_m: float = Field(
        0.5, gt=0.0, description="prior sigma of that bias (deg per metre; the prior's mean is 0)"
    )
    odometry_yaw_bias_reading_sigma_deg_per_m: float = Field(
        0.1,
        gt=0.0,
        description="the bias wheel odometry is expected to have (deg per metre): it chooses between readings of "
        "the loops' turns that the loops cannot tell apart (loops one lap long: b and b + 360 deg / lap)",
    )
    odometry_yaw_bias_hindsight: bool = Field(
        True,
        description="at the end of the run, take the final heading bias off the whole drive from its first frame "
        "(online it corrects only the drive after the loops that measured it) and solve the graph again in batch",
    )
    graph: Literal["none", "g2o"] = Field(
        "none",
        description="write the final pose graph the back-end optimised: g2o (pose_graph.g2o, VERTEX_SE2 and EDGE_SE2 "
        "lines that GTSAM and g2o read; pose2 without a prior map), or none",
    )

    @model_validator(mode="after")
    def _graph_fits_g2o(self) -> GraphParams:
        if self.graph == "g2o" and (self.pose == "pose3" or self.prior_map):
            raise ValueError(
                "graph=g2o writes the Pose2 graph of one session; the pose3 graph's IMU attitude factors and a prior "
                "map's poses have no g2o edge: use pose=pose2 without a prior map, or graph=none"
            )
        return self

    def noise(self) -> NoiseSettings:
        """The noise models in the graph's units (radians)."""
        r = math.radians
        return NoiseSettings(
            odometry_sigma_xy=self.odometry_sigma_xy,
            odometry_sigma_yaw=r(self.odometry_sigma_yaw_deg),
            odometry_sigma_z=self.odometry_sigma_z,
            odometry_sigma_roll_pitch=r(self.odometry_sigma_roll_pitch_deg),
            odometry_floor_xy=self.odometry_floor_xy,
            odometry_floor_yaw=r(self.odometry_floor_yaw_deg),
            imu_sigma_roll_pitch=r(self.imu_sigma_roll_pitch_deg),
            loop_sigma_z=self.loop_sigma_z,
            loop_sigma_roll_pitch=r(self.loop_sigma_roll_pitch_deg),
            loop_kernel=self.loop_kernel,
            loop_kernel_width=self.loop_kernel_width,
            prior_sigma_xy=self.prior_sigma_xy,
            prior_sigma_yaw=r(self.prior_sigma_yaw_deg),
            map_sigma_xy=self.map_sigma_xy,
            map_sigma_yaw=r(self.map_sigma_yaw_deg),
            yaw_bias_sigma=r(self.odometry_yaw_bias_sigma_deg_per_m) if self.odometry_yaw_bias else None,
            yaw_bias_reading_sigma=r(self.odometry_yaw_bias_reading_sigma_deg_per_m),
        )


class LmParams(GraphParams):
    """Batch Levenberg-Marquardt over the whole graph."""

    optimize_every_loop: bool = Field(True, description="re-optimize the whole graph on every frame that adds loops")
    max_iterations: int = Field(100, ge=1, description="LM iterations per optimisation")
    relative_error_tol: float = Field(1e-6, gt=0.0, description="LM stops when the error improves by less (relative)")


class Isam2Params(GraphParams):
    """Incremental smoothing and mapping (iSAM2), for online use."""

    factorization: Literal["qr", "cholesky"] = Field(
        "qr", description="QR: robust on long loop-free drives, where Cholesky finds the system indeterminate"
    )
    relinearize_threshold: float = Field(
        0.1, gt=0.0, description="relinearize a pose whose delta exceeds this (rad; also m unless set below)"
    )
    relinearize_threshold_translation: float | None = Field(
        None,
        gt=0.0,
        description="relinearize a pose whose translation delta exceeds this (m); null = relinearize_threshold",
    )
    relinearize_skip: int = Field(
        1, ge=1, description="check relinearization every this many updates (with the partial check keep 1)"
    )
    partial_relinearization_check: bool = Field(
        True, description="check only the variables an update touched for relinearization, not all of them"
    )
    loop_updates: int = Field(
        0, ge=0, description="extra iSAM2 updates on a frame that adds loops (each re-linearizes widely: costly)"
    )
    final_batch: bool = Field(False, description="finish with a batch LM over the whole graph from iSAM2's estimate")


class _Backend(Stage):
    """What the back-ends share: per-frame bookkeeping, the trajectory, metrics and the saved map."""

    kind = "backend"
    output = "estimate"

    def __init__(self, params: BackendParams) -> None:
        super().__init__(params)
        self.begin(RunContext(run_dir=None))

    def begin(self, context: RunContext) -> None:
        """Forget the previous sequence."""
        self.ground_truth: dict[int, np.ndarray] = {}
        self.calibration: Calibration | None = context.calibration
        self.loops_received = 0
        self.update_seconds: list[float] = []
        self.settlement = Settlement()  # what the other stages concluded, for the SGF map

    def _note(self, frame: Frame) -> None:
        if frame.ground_truth is not None:
            self.ground_truth[frame.index] = np.asarray(frame.ground_truth, dtype=np.float64)
        if self.calibration is None:
            self.calibration = frame.calibration

    def poses(self) -> tuple[list[float], np.ndarray, PoseEstimate | None]:
        """Timestamps, poses and the latest estimate of the processed frames."""
        raise NotImplementedError

    def conclude(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Keep the settlement for :meth:`finalize`: the loops closed or taken back at the end, the SGF map's groups."""
        self.settlement = settlement
        return settlement

    def finalize(self, context: RunContext) -> None:
        """The optimized trajectory, back-end metrics and the run's SGF map."""
        timestamps, poses, estimate = self.poses()
        if len(timestamps) == 0 or estimate is None:
            return
        context.trajectories["sgf"] = Trajectory(np.asarray(timestamps), poses)
        updates = np.asarray(self.update_seconds) * 1e3
        metrics: dict[str, Any] = {
            "variant": self.name,
            "nodes": len(timestamps),
            "loops_received": self.loops_received,
            "update_ms_median": float(np.median(updates)) if updates.size else None,
            "update_ms_max": float(updates.max()) if updates.size else None,
        }
        metrics.update(self.extra_metrics())
        params = self.params
        assert isinstance(params, BackendParams)
        saved = self._save_map(context, estimate, params.map_file, self.settlement)
        if saved is not None:
            metrics["map"] = {"file": params.map_file, "groups": len(saved.groups), "views": len(saved.views)}
        context.metrics.setdefault("backend", {}).update(metrics)

    def partial(self, context: RunContext, settlement: Settlement) -> Settlement:
        """The estimate so far (``trajectory_sgf.partial.tum``) and the SGF map so far (``<map_file>.partial``)."""
        timestamps, poses, estimate = self.poses()
        if len(timestamps) == 0 or estimate is None:
            return settlement
        context.trajectories["sgf"] = Trajectory(np.asarray(timestamps), poses)
        params = self.params
        assert isinstance(params, BackendParams)
        name = Path(params.map_file)
        self._save_map(context, estimate, f"{name.stem}.partial{name.suffix}", settlement)
        return settlement

    def _save_map(
        self, context: RunContext, estimate: PoseEstimate, file_name: str, settlement: Settlement
    ) -> SgfMap | None:
        """Write the SGF map of the loop stage's group assignments (``save_map``); the map, or None if none."""
        params = self.params
        assert isinstance(params, BackendParams)
        if not (params.save_map and context.run_dir is not None and settlement.assignments):
            return None
        # a run stopped between the loop stage and this one has assignments of a frame without a pose yet
        assignments = [
            a
            for a in settlement.assignments
            if getattr(a.descriptor, "sgf", None) is None or a.descriptor.sgf.frame_index in estimate.poses
        ]
        sgf_map = build_map(
            assignments,
            estimate.poses,
            calibration=context.calibration or self.calibration,
            sequence=context.sequence,
            ground_truth=self.ground_truth,
            group_of=settlement.group_of,
        )
        path = Path(context.run_dir) / file_name
        map_id = save_map(path, sgf_map)
        context.artifacts["sgf_map"] = {"path": str(path), "map_id": map_id}
        return sgf_map

    def extra_metrics(self) -> dict[str, Any]:
        """Variant-specific metrics."""
        return {}


class OdometryBackend(_Backend):
    """Odometry only, the baseline of Table 2: the estimate is the wheel odometry, loops are ignored."""

    name = "none"
    Params = BackendParams

    def begin(self, context: RunContext) -> None:
        """Forget the previous sequence."""
        super().begin(context)
        self.store = PoseStore()
        self.timestamps: list[float] = []

    def process(self, frame: Frame, loops: LoopConstraints | None) -> PoseEstimate:
        """The odometry of every processed frame so far (the odometry's scale left as it is: the baseline)."""
        t0 = time.perf_counter()
        self._note(frame)
        self.store.append(frame.index, np.asarray(frame.odometry, dtype=np.float64))
        self.timestamps.append(float(frame.timestamp))
        if loops is not None:
            self.loops_received += len(loops.items)
        self.update_seconds.append(time.perf_counter() - t0)
        return PoseEstimate(frame.index, self.store.snapshot())

    def poses(self) -> tuple[list[float], np.ndarray, PoseEstimate | None]:
        """Timestamps, poses and the latest estimate of the processed frames."""
        if not self.timestamps:
            return [], np.zeros((0, 4, 4)), None
        table = self.store.snapshot()
        return self.timestamps, table.array(), PoseEstimate(self.store.frames[-1], table)


class _GraphBackend(_Backend):
    """A GTSAM pose graph (eq. 11), optionally on a prior SGF map."""

    def __init__(self, params: GraphParams) -> None:
        # A missing or broken prior map stops the pipeline while it is built, before any frame.
        self.prior: SgfMap | None = load_map(params.prior_map) if params.prior_map else None
        super().__init__(params)

    def begin(self, context: RunContext) -> None:
        """Start an empty graph on the prior map, checked against the run's calibration."""
        super().begin(context)
        params = self.params
        assert isinstance(params, GraphParams)
        self.map_poses: dict[int, np.ndarray] | None = None
        self._map_checked = False
        if self.prior is not None:
            self.prior.check_calibration(context.calibration)
            self.map_poses = self.prior.frame_poses
            self._map_checked = context.calibration is not None
        self.graph = PoseGraph(params.pose, params.noise(), self.map_poses, params.node_distance)
        self.optimizations = 0
        self.optimize_seconds = 0.0
        self.hindsight = False  # the final heading bias was taken off the whole drive
        self.camera: OdometryScale | None = None  # the camera's newest measurement of the odometry's errors

    def finalize(self, context: RunContext) -> None:
        """The trajectory, metrics and map (:meth:`_Backend.finalize`), then the final pose graph if asked."""
        super().finalize(context)
        params = self.params
        assert isinstance(params, GraphParams)
        path = context.path(GRAPH_FILE)
        if params.graph == "g2o" and path is not None and self.graph.nodes:
            text, vertices, edges = self.graph.g2o()
            atomic_write_text(path, text)
            written = {"file": GRAPH_FILE, "format": "g2o", "vertices": vertices, "edges": edges}
            context.metrics.setdefault("backend", {})["graph"] = written

    def _add(
        self, frame: Frame, loops: LoopConstraints | None, odometry_scale: OdometryScale | None
    ) -> tuple[int, bool]:
        """Add the frame (its odometry scaled) and its loops; the number of loops and whether the run was anchored."""
        self._note(frame)
        if self.prior is not None and not self._map_checked:
            self.prior.check_calibration(frame.calibration)
            self._map_checked = True
        if odometry_scale is None:
            self.graph.add_frame(frame)
        else:
            self.camera = odometry_scale
            camera = (odometry_scale.yaw_bias, odometry_scale.yaw_bias_sigma)
            self.graph.add_frame(frame, odometry_scale.factor, camera)
        return self._add_loops(loops)

    def _add_loops(self, loops: LoopConstraints | None) -> tuple[int, bool]:
        """Add loop factors; their number and whether one anchored the run in the map."""
        anchored = False
        items = loops.items if loops is not None else ()
        for loop in items:
            anchored |= self.graph.add_loop(loop)
        self.loops_received += len(items)
        return len(items), anchored

    def _add_final_loops(self, settlement: Settlement) -> int:
        """Add the loops a loop stage closed at the end of the run (``settlement.final_loops``); their number."""
        return self._add_loops(settlement.final_loops)[0]

    def _hindsight(self) -> bool:
        """The final heading bias taken off the whole drive (``odometry_yaw_bias_hindsight``); False if none moved."""
        params = self.params
        assert isinstance(params, GraphParams)
        if not params.odometry_yaw_bias_hindsight:
            return False
        self.hindsight = self.graph.hindsight_heading_bias()
        return self.hindsight

    def resolve(self) -> None:
        """Batch LM over the whole graph from the current estimate and from dead reckoning; the lower error wins.

        After the odometry changed (the hindsight heading bias), the old estimate may lie far from the optimum.
        """
        self.batch_optimize()
        optimum, error = self.graph.values, self.graph.error()
        self.graph.values = self.graph.dead_reckoned()
        self.batch_optimize()
        if self.graph.error() > error:
            self.graph.set_values(optimum)

    def estimate(self) -> PoseEstimate:
        """The current estimate of every processed frame."""
        return PoseEstimate(self.graph.store.frames[-1], self.graph.store.snapshot(), self._yaw_bias(), self._drift())

    def _yaw_bias(self) -> YawBiasCorrection | None:
        """The heading bias model: where it is taken off the odometry, and its uncertainty; None when not estimated."""
        bias = self.graph.heading_bias
        if bias is None:
            return None
        return YawBiasCorrection(bias.since, bias.residual_sigma, bias.uncorrected_sigma)

    def _drift(self) -> OdometryDrift | None:
        """The odometry's errors left in the estimate: the camera's, once it has measured them (else None).

        The graph scales each odometry step by the camera's factor, so the scale error left is that
        factor's uncertainty.
        """
        camera = self.camera
        if camera is None or not math.isfinite(camera.sigma):
            return None
        walks = math.isfinite(camera.sigma_xy) and math.isfinite(camera.sigma_yaw)
        return OdometryDrift(camera.sigma, camera.sigma_xy if walks else None, camera.sigma_yaw if walks else None)

    def poses(self) -> tuple[list[float], np.ndarray, PoseEstimate | None]:
        """Timestamps, poses and the latest estimate of the processed frames."""
        if not self.graph.timestamps:
            return [], np.zeros((0, 4, 4)), None
        table = self.graph.store.snapshot()
        estimate = PoseEstimate(self.graph.store.frames[-1], table, self._yaw_bias(), self._drift())
        return self.graph.timestamps, table.array(), estimate

    def batch_optimize(self) -> None:
        """Levenberg-Marquardt over the whole graph from the current estimate."""
        import gtsam

        params = self.params
        t0 = time.perf_counter()
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(params.max_iterations if isinstance(params, LmParams) else 100)
        lm.setRelativeErrorTol(params.relative_error_tol if isinstance(params, LmParams) else 1e-6)
        result = gtsam.LevenbergMarquardtOptimizer(self.graph.graph(), self.graph.values, lm).optimize()
        self.graph.set_values(result)
        self.optimizations += 1
        self.optimize_seconds += time.perf_counter() - t0

    def extra_metrics(self) -> dict[str, Any]:
        """Graph size, optimisations and the map anchoring."""
        out: dict[str, Any] = {
            "pose": "pose3" if self.graph.pose3 else "pose2",
            "pose_nodes": len(self.graph.nodes),
            "loop_factors": self.graph.loop_factors,
            "map_factors": self.graph.map_factors,
            "optimizations": self.optimizations,
            "optimize_seconds": round(self.optimize_seconds, 4),
            "final_error": self.graph.error(),
        }
        bias = self.graph.heading_bias
        if bias is not None:
            out["odometry_yaw_bias"] = {
                "deg_per_m": math.degrees(bias.value),
                "estimate_deg_per_m": math.degrees(bias.estimate),
                "sigma_deg_per_m": math.degrees(bias.sigma),
                "loops": bias.loops,
                "agreeing": bias.agreeing,
                "hindsight": self.hindsight,
            }
        if self.prior is not None:
            out["prior_map"] = {"map_id": self.prior.map_id, "anchored": self.graph.anchored}
        return out


class GtsamLmBackend(_GraphBackend):
    """Batch Levenberg-Marquardt (GTSAM) at the end of the run, and on frames that add loops when asked."""

    name = "gtsam_lm"
    Params = LmParams

    def process(
        self, frame: Frame, loops: LoopConstraints | None, odometry_scale: OdometryScale | None = None
    ) -> PoseEstimate:
        """Add the frame's odometry and loop factors; re-optimize on new loops if configured."""
        t0 = time.perf_counter()
        count, _ = self._add(frame, loops, odometry_scale)
        self.graph.take_new()  # batch optimisation uses the whole graph
        params = self.params
        assert isinstance(params, LmParams)
        if count and params.optimize_every_loop:
            self.batch_optimize()
        self.update_seconds.append(time.perf_counter() - t0)
        return self.estimate()

    def finalize(self, context: RunContext) -> None:
        """The loops closed at the end, a final batch optimisation, then the rest."""
        if self.graph.timestamps:
            self._add_final_loops(self.settlement)
            hindsight = self._hindsight()
            self.graph.take_new()
            if hindsight:
                self.resolve()
            else:
                self.batch_optimize()
        super().finalize(context)


class Isam2Backend(_GraphBackend):
    """Incremental smoothing and mapping (GTSAM iSAM2): one update per processed frame."""

    name = "isam2"
    Params = Isam2Params

    def begin(self, context: RunContext) -> None:
        """Start an empty graph and solver."""
        super().begin(context)
        self.isam = self._solver()
        self.reeliminated: list[int] = []  # per iSAM2 update: variables re-eliminated, and re-linearized
        self.relinearized: list[int] = []

    def _solver(self) -> Any:
        import gtsam

        params = self.params
        assert isinstance(params, Isam2Params)
        settings = gtsam.ISAM2Params()
        rotation = params.relinearize_threshold
        translation = params.relinearize_threshold_translation
        if translation is None:
            settings.setRelinearizeThreshold(rotation)
        else:
            # per pose type, in GTSAM's tangent order: Pose2 (x, y, yaw), Pose3 (rotation, translation)
            if self.graph.pose3:
                threshold = np.array([rotation] * 3 + [translation] * 3)
            else:
                threshold = np.array([translation, translation, rotation])
            per_key = gtsam.ISAM2ThresholdMap()
            for symbol in (FRAME_SYMBOL, MAP_SYMBOL):
                per_key.insert((symbol, threshold))
            settings.setRelinearizeThreshold(per_key)
        settings.relinearizeSkip = params.relinearize_skip
        settings.enablePartialRelinearizationCheck = params.partial_relinearization_check
        settings.setFactorization(params.factorization.upper())
        return gtsam.ISAM2(settings)

    def process(
        self, frame: Frame, loops: LoopConstraints | None, odometry_scale: OdometryScale | None = None
    ) -> PoseEstimate:
        """One iSAM2 update with the frame's factors; the full estimate is refreshed when loops arrive."""
        t0 = time.perf_counter()
        count, anchored = self._add(frame, loops, odometry_scale)
        if anchored:
            self.isam = self._solver()  # the run moved into the map frame: start the solver over
        factors, values = self.graph.take_new()
        if factors.size() == 0 and values.size() == 0:
            # A frame between nodes: its pose rides on the last node's estimate (set when it was added).
            self.update_seconds.append(time.perf_counter() - t0)
            return self.estimate()
        result = self.isam.update(factors, values)
        self.reeliminated.append(int(result.getVariablesReeliminated()))
        self.relinearized.append(int(result.getVariablesRelinearized()))
        if count:
            params = self.params
            assert isinstance(params, Isam2Params)
            for _ in range(params.loop_updates):
                self.isam.update()
            self.graph.set_values(self.isam.calculateEstimate())
        else:
            key = X(frame.index)
            value = self.isam.calculateEstimatePose3(key) if self.graph.pose3 else self.isam.calculateEstimatePose2(key)
            self.graph.set_latest(value)
        self.update_seconds.append(time.perf_counter() - t0)
        return self.estimate()

    def extra_metrics(self) -> dict[str, Any]:
        """The graph's figures and how much of it each iSAM2 update re-eliminated and re-linearized.

        An update that re-eliminates a large part of the graph is what makes iSAM2 slow; a pose
        graph whose loops contradict its odometry keeps re-linearizing (``bench/RESULTS.md`` ## soak).
        """
        out = super().extra_metrics()
        if self.reeliminated:
            reeliminated, relinearized = np.asarray(self.reeliminated), np.asarray(self.relinearized)
            out["isam2"] = {
                "updates": int(reeliminated.size),
                "reeliminated_median": float(np.median(reeliminated)),
                "reeliminated_p90": float(np.percentile(reeliminated, 90)),
                "reeliminated_max": int(reeliminated.max()),
                "relinearized_median": float(np.median(relinearized)),
                "relinearized_max": int(relinearized.max()),
            }
        return out

    def finalize(self, context: RunContext) -> None:
        """The loops closed at the end, the final iSAM2 estimate (optionally refined by batch LM), then the rest.

        When the hindsight heading bias changed the odometry, the graph is solved by batch LM instead.
        """
        if self.graph.timestamps:
            final = self._add_final_loops(self.settlement)
            if self._hindsight():  # iSAM2 holds the odometry before the hindsight: solved in batch
                self.graph.take_new()
                self.resolve()
            else:
                self._finish_isam2(final)
        super().finalize(context)

    def _finish_isam2(self, final_loops: int) -> None:
        """The final iSAM2 update (with the loops closed at the end), optionally refined by batch LM."""
        t0 = time.perf_counter()
        if final_loops:
            factors, values = self.graph.take_new()
            self.isam.update(factors, values)
        self.isam.update()
        self.graph.set_values(self.isam.calculateEstimate())
        self.optimize_seconds += time.perf_counter() - t0
        params = self.params
        assert isinstance(params, Isam2Params)
        if params.final_batch:
            self.batch_optimize()


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the back-end variants."""
    registry.add(OdometryBackend)
    registry.add(GtsamLmBackend)
    registry.add(Isam2Backend)
