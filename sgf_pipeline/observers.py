"""Built-in observers (timing, progress, logging): plugins on the lifecycle hooks, not code in stages."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import Any

from sgf_pipeline.hookspecs import hookimpl
from sgf_pipeline.run_info import RunInfo, StageNode
from sgf_pipeline.types import Frame

log = logging.getLogger("sgf_pipeline")


class _StageTime:
    """Calls, total and longest wall time of one stage (constant memory over a run of any length)."""

    __slots__ = ("calls", "longest", "total")

    def __init__(self) -> None:
        self.calls = 0
        self.total = 0.0
        self.longest = 0.0

    def add(self, seconds: float) -> None:
        """Count one call that took ``seconds``."""
        self.calls += 1
        self.total += seconds
        self.longest = max(self.longest, seconds)


class TimingObserver:
    """Per-stage wall time, frames per second and the real-time factor, for metrics.json."""

    def __init__(self) -> None:
        self._stages: dict[int, dict[str, _StageTime]] = {}

    @hookimpl
    def sgf_run_start(self, run: RunInfo) -> None:
        self._stages[id(run)] = {node.kind: _StageTime() for node in run.stages[1:]}

    @hookimpl
    def sgf_after_stage(self, run: RunInfo, stage: StageNode, frame: Frame, output: Any, seconds: float) -> None:
        if output is not None or seconds > 0.0:
            self._stages.setdefault(id(run), {}).setdefault(stage.kind, _StageTime()).add(seconds)

    @hookimpl
    def sgf_report_metrics(self, run: RunInfo) -> dict[str, Any]:
        stages = self._stages.pop(id(run), {})
        duration = None
        if run.first_timestamp is not None and run.last_timestamp is not None:
            duration = run.last_timestamp - run.first_timestamp
        work = run.work_seconds
        timing: dict[str, Any] = {
            "frames": run.frames_processed,
            "dataset_frames": run.frames_seen,
            "seconds": round(work, 4),
            "fps": round(run.frames_processed / work, 3) if work > 0 else None,
            "dataset_seconds": round(run.dataset_seconds, 4),
            "sequence_seconds": duration,
            "realtime_factor": round(duration / work, 3) if duration and work > 0 else None,
            "stages": {},
        }
        for node in run.stages[1:]:
            times = stages.get(node.kind, _StageTime())
            timing["stages"][node.kind] = {
                "variant": node.name,
                "calls": times.calls,
                "total_s": round(times.total, 4),
                "mean_ms": round(1000.0 * times.total / times.calls, 3) if times.calls else None,
                "max_ms": round(1000.0 * times.longest, 3) if times.calls else None,
            }
        return {"timing": timing}


class ProgressObserver:
    """A progress bar over the dataset's frames (when ``run.progress`` is true)."""

    def __init__(self) -> None:
        self._bars: dict[int, Any] = {}

    @hookimpl
    def sgf_run_start(self, run: RunInfo) -> None:
        if run.options is not None and not getattr(run.options, "progress", True):
            return
        from tqdm import tqdm

        self._bars[id(run)] = tqdm(
            total=run.total_frames or None,
            desc=run.sequence,
            unit="frame",
            dynamic_ncols=True,
            file=sys.stderr,
            mininterval=0.5,
        )

    @hookimpl
    def sgf_frame_end(self, run: RunInfo, frame: Frame, seconds: float) -> None:
        bar = self._bars.get(id(run))
        if bar is None:
            return
        bar.update(run.frames_seen - bar.n)
        if run.work_seconds > 0:
            bar.set_postfix(
                key=run.frames_processed, fps=f"{run.frames_processed / run.work_seconds:.1f}", refresh=False
            )

    @hookimpl
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        bar = self._bars.pop(id(run), None)
        if bar is not None:
            bar.update(run.frames_seen - bar.n)
            bar.close()

    @hookimpl
    def sgf_on_error(self, run: RunInfo, stage: StageNode, frame: Frame | None, error: BaseException) -> None:
        bar = self._bars.pop(id(run), None)
        if bar is not None:
            bar.close()


class LoggingObserver:
    """Log lines at the start and end of a run and on errors."""

    @hookimpl
    def sgf_run_start(self, run: RunInfo) -> None:
        log.info("pipeline: %s", " -> ".join(n.label for n in run.stages))
        if run.run_dir is not None:
            log.info("output directory: %s", run.run_dir)

    @hookimpl
    def sgf_on_error(self, run: RunInfo, stage: StageNode, frame: Frame | None, error: BaseException) -> None:
        where = f"frame {frame.index}" if frame is not None else "finalize"
        log.error("stage %s failed on %s: %s: %s", stage.label, where, type(error).__name__, error)

    @hookimpl
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        log.info("processed %d of %d frames", run.frames_processed, run.frames_seen)


BUILTIN_OBSERVERS: list[tuple[str, Callable[[], object]]] = [
    ("sgf.timing", TimingObserver),
    ("sgf.progress", ProgressObserver),
    ("sgf.logging", LoggingObserver),
]
