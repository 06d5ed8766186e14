"""The incremental back-end (``backend=isam2``): one GTSAM iSAM2 update per processed frame, for online use."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from sgf_pipeline import RunContext
from sgf_pipeline.types import Frame, LoopConstraints, OdometryScale, PoseEstimate
from sgf_plugins.backend.factors import FRAME_SYMBOL, MAP_SYMBOL, X
from sgf_plugins.backend.graph_backend import GraphBackend
from sgf_plugins.backend.params import Isam2Params


class Isam2Backend(GraphBackend):
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
        rotation = params.solver.relinearize_threshold
        translation = params.solver.relinearize_threshold_translation
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
        settings.relinearizeSkip = params.solver.relinearize_skip
        settings.enablePartialRelinearizationCheck = params.solver.partial_relinearization_check
        settings.setFactorization(params.solver.factorization.upper())
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
            for _ in range(params.solver.loop_updates):
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
        if params.solver.final_batch:
            self.batch_optimize()
