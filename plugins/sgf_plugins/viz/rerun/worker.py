"""The thread that logs a run's Rerun recording, fed keyframe by keyframe from the pipeline's thread."""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from sgf_pipeline.errors import ImageNotCachedError
from sgf_pipeline.runner import RunInfo
from sgf_pipeline.types import Frame
from sgf_plugins.viz.rerun.options import RerunOptions
from sgf_plugins.viz.rerun.recording import Keyframe, Recording

log = logging.getLogger("sgf_pipeline")

#: Keyframes queued for the recording thread at most (the pipeline waits beyond).
QUEUED_FRAMES = 32


class RecordingWorker:
    """A run's recording, logged on a thread of its own so that the pipeline does not wait for it.

    The pipeline's thread only gathers each keyframe's outputs and queues them; the recording thread
    encodes the images and makes every Rerun call. A full queue (the recording falls behind) makes
    the pipeline wait.
    """

    def __init__(self, run: RunInfo, options: RerunOptions) -> None:
        self.recording = Recording(run, options)
        self.outputs: dict[type, Any] = {}
        self.times: dict[str, float] = {}
        self.candidates = 0  # loop candidates handed over so far
        self.error: BaseException | None = None
        self.jobs: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize=QUEUED_FRAMES)
        self.thread = threading.Thread(target=self._work, name="sgf-rerun", daemon=True)
        self.thread.start()

    def _work(self) -> None:
        while True:
            job = self.jobs.get()
            if job is None:
                return
            if self.error is None:
                try:
                    job()
                except BaseException as exc:  # raised on the pipeline's thread at the end
                    self.error = exc
                    log.error("the Rerun recording stopped: %s: %s", type(exc).__name__, exc)

    def stage_done(self, kind: str, output: Any, seconds: float) -> None:
        """Keep a stage's output (by its type) and time until the frame ends."""
        if output is not None:
            self.outputs[type(output)] = output
        if output is not None or seconds > 0.0:
            self.times[kind] = seconds

    def frame_done(self, frame: Frame, artifacts: dict[str, Any] | None) -> None:
        """Queue the keyframe for the recording thread."""
        candidates = (artifacts or {}).get("loop_candidates")
        rows = candidates[self.candidates :] if isinstance(candidates, list) else []
        truth = frame.ground_truth
        if truth is not None:
            truth = np.asarray(truth, dtype=np.float64)
            truth = truth if truth.shape == (4, 4) and bool(np.all(np.isfinite(truth))) else None
        try:
            image: np.ndarray | None = frame.image
        except ImageNotCachedError:  # the run took every image stage's outputs from the stage cache
            image = None
        key = Keyframe(
            frame.index,
            float(frame.timestamp),
            image,
            np.array(frame.odometry, dtype=np.float64),
            truth,
            self.outputs,
            self.times,
            self.candidates,
            [dict(row) for row in rows],
        )
        self.candidates += len(rows)
        self.outputs, self.times = {}, {}
        self.jobs.put(lambda: self.recording.log_frame(key))

    def finish(self, run: RunInfo | None) -> None:
        """Log the end of the run (``run``; None: it failed), close the recording and wait for the thread."""
        if run is not None:
            context = run.context
            final = context.trajectories.get("sgf") if context is not None else None
            poses = None if final is None else np.array(final.poses, dtype=np.float64)
            candidates = context.artifacts.get("loop_candidates") if context is not None else None
            rows = [dict(row) for row in candidates] if isinstance(candidates, list) else []
            self.jobs.put(lambda: self.recording.log_end(poses, rows))
        self.jobs.put(lambda: self.recording.close(finished=run is not None))
        self.jobs.put(None)
        self.thread.join()
        if self.error is not None and run is not None:
            raise RuntimeError(f"the Rerun recording failed: {type(self.error).__name__}: {self.error}") from self.error
