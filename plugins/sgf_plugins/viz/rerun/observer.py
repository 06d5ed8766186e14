"""The pipeline observer that records a run with Rerun: its lifecycle hooks hand the stages' outputs over."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from sgf_pipeline import hookimpl
from sgf_pipeline.run_info import RunInfo, StageNode
from sgf_pipeline.types import Frame
from sgf_plugins.viz.rerun.options import NODE, RECORDING, RerunOptions
from sgf_plugins.viz.rerun.worker import RecordingWorker


class RerunObserver:
    """Records a run with Rerun when its config has a ``viz`` node (``sgf-run viz=rerun``)."""

    def __init__(self) -> None:
        self._runs: dict[int, RecordingWorker] = {}

    @hookimpl
    def sgf_observer_options(self) -> dict[str, type[BaseModel]]:
        """The ``viz`` node."""
        return {NODE: RerunOptions}

    @hookimpl
    def sgf_run_start(self, run: RunInfo) -> None:
        """Open the recording and lay out the viewer."""
        options = run.observer_options.get(NODE)
        if run.run_dir is not None and run.options is not None and getattr(run.options, "overwrite", False):
            (run.run_dir / RECORDING).unlink(missing_ok=True)  # the replaced run's recording
        if isinstance(options, RerunOptions):
            self._runs[id(run)] = RecordingWorker(run, options)

    @hookimpl
    def sgf_after_stage(self, run: RunInfo, stage: StageNode, frame: Frame, output: Any, seconds: float) -> None:
        """Keep the stage's output for the end of the frame."""
        worker = self._runs.get(id(run))
        if worker is not None:
            worker.stage_done(stage.kind, output, seconds)

    @hookimpl
    def sgf_frame_end(self, run: RunInfo, frame: Frame, seconds: float) -> None:
        """Hand the keyframe to the recording."""
        worker = self._runs.get(id(run))
        if worker is not None:
            worker.frame_done(frame, run.context.artifacts if run.context is not None else None)

    @hookimpl
    def sgf_on_error(self, run: RunInfo, stage: StageNode, frame: Frame | None, error: BaseException) -> None:
        """Close the recording as it is (``run.partial.rrd``)."""
        worker = self._runs.pop(id(run), None)
        if worker is not None:
            worker.finish(None)

    @hookimpl
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        """Log the end of the run and close the recording as ``run.rrd``."""
        worker = self._runs.pop(id(run), None)
        if worker is not None:
            worker.finish(run)
