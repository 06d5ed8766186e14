"""What every back-end shares: per-frame bookkeeping, the final trajectory, the metrics and the SGF map."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sgf_pipeline import RunContext, Stage
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.sgf_map import SgfMap
from sgf_pipeline.stage import Settlement
from sgf_pipeline.trajectory import Trajectory
from sgf_pipeline.types import Frame, PoseEstimate
from sgf_plugins.backend.map_writer import write_sgf_map
from sgf_plugins.backend.params import BackendParams


class Backend(Stage):
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
        """The run's SGF map written by :func:`write_sgf_map` (``save_map``); the map, or None if none."""
        params = self.params
        assert isinstance(params, BackendParams)
        if not params.save_map:
            return None
        calibration = context.calibration or self.calibration
        return write_sgf_map(context, settlement, estimate, file_name, calibration, self.ground_truth)

    def extra_metrics(self) -> dict[str, Any]:
        """Variant-specific metrics."""
        return {}
