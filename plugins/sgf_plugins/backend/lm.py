"""The batch back-end (``backend=gtsam_lm``): GTSAM's Levenberg-Marquardt over the whole pose graph."""

from __future__ import annotations

import time

from sgf_pipeline import RunContext
from sgf_pipeline.types import Frame, LoopConstraints, OdometryScale, PoseEstimate
from sgf_plugins.backend.graph_backend import GraphBackend
from sgf_plugins.backend.params import LmParams


class GtsamLmBackend(GraphBackend):
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
        if count and params.solver.every_loop:
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
