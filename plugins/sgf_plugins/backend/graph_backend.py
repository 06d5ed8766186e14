"""The shared stage of the graph back-ends: a GTSAM pose graph (eq. 11), optionally on a prior SGF map.

The graph holds a pose node every ``node_distance`` metres (1 m by default, and on every frame a
loop ends on); the frames between ride on their node by odometry. A node per 0.25 m keyframe made
iSAM2's update and the full estimate of a loop frame four times as large for the same route.

With ``graph=g2o`` the final pose graph is written as ``pose_graph.g2o``. With ``prior_map`` the
run is localized on an earlier run's map: SGFs matched to it give inter-session factors to the
map's frames, held by priors at their map poses, and the run's trajectory ends in the map's frame.
The solvers' stages are :mod:`~sgf_plugins.backend.lm` and :mod:`~sgf_plugins.backend.isam2`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from sgf_pipeline import RunContext
from sgf_pipeline.io import atomic_write_text
from sgf_pipeline.sgf_map import SgfMap, load_map
from sgf_pipeline.stage import Settlement
from sgf_pipeline.types import (
    Frame,
    LoopConstraints,
    OdometryDrift,
    OdometryScale,
    PoseEstimate,
    YawBiasCorrection,
)
from sgf_plugins.backend.base import Backend
from sgf_plugins.backend.params import GraphParams, LmParams, LmSolver
from sgf_plugins.backend.pose_graph import PoseGraph

#: The file of the final pose graph (``graph=g2o``).
GRAPH_FILE = "pose_graph.g2o"


class GraphBackend(Backend):
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
        """The trajectory, metrics and map (:meth:`Backend.finalize`), then the final pose graph if asked."""
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
        """The final heading bias taken off the whole drive (``heading_bias.hindsight``); False if none moved."""
        params = self.params
        assert isinstance(params, GraphParams)
        if not params.heading_bias.hindsight:
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
        solver = params.solver if isinstance(params, LmParams) else LmSolver()
        lm.setMaxIterations(solver.max_iterations)
        lm.setRelativeErrorTol(solver.relative_error_tol)
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
