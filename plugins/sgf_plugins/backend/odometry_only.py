"""The odometry-only back-end (``backend=none``), the baseline of Table 2."""

from __future__ import annotations

import time

import numpy as np

from sgf_pipeline import RunContext
from sgf_pipeline.types import Frame, LoopConstraints, PoseEstimate
from sgf_plugins.backend.base import Backend
from sgf_plugins.backend.params import BackendParams
from sgf_plugins.backend.poses import PoseStore


class OdometryBackend(Backend):
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
