"""Hook specifications: the one registration hook and the run's lifecycle hooks.

A plugin module implements any of these with ``@hookimpl`` and is announced through the
``sgf_pipeline`` entry-point group, exactly like the first-party plugins.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:
    from pydantic import BaseModel

    from sgf_pipeline.run_info import RunInfo, StageNode
    from sgf_pipeline.types import Frame
    from sgf_pipeline.variants import StageRegistry

PROJECT = "sgf_pipeline"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


class PipelineHooks:
    """The hooks a plugin may implement."""

    @hookspec
    def sgf_register_stages(self, registry: StageRegistry) -> None:
        """Register the stage classes (variants) that this plugin offers.

        :param registry: call ``registry.add(StageClass)`` once per variant.
        """

    @hookspec
    def sgf_observer_options(self) -> dict[str, type[BaseModel]] | None:
        """The top-level config nodes an observer plugin reads, each with its pydantic model (``extra="forbid"``).

        Such a node sits beside the stage nodes; a model with a default ``name`` is selectable by it
        (``sgf-run viz=rerun``, at its defaults). The runner validates the node while the pipeline is
        built and hands it to every hook as ``run.observer_options[name]``, which has no entry when
        the config has no such node.
        """

    @hookspec
    def sgf_run_start(self, run: RunInfo) -> None:
        """Called once after the pipeline is built and validated, before the first frame.

        :param run: the run's description: stages in execution order, output directory, frame count.
        """

    @hookspec
    def sgf_before_stage(self, run: RunInfo, stage: StageNode, frame: Frame) -> None:
        """Called before a stage processes a frame.

        :param run: the running pipeline's description.
        :param stage: the stage about to run.
        :param frame: the frame being processed.
        """

    @hookspec
    def sgf_after_stage(self, run: RunInfo, stage: StageNode, frame: Frame, output: Any, seconds: float) -> None:
        """Called after a stage has processed a frame.

        :param run: the running pipeline's description.
        :param stage: the stage that ran.
        :param frame: the frame it processed.
        :param output: the value the stage produced (``None`` when it was skipped).
        :param seconds: wall time the stage took on this frame.
        """

    @hookspec
    def sgf_frame_end(self, run: RunInfo, frame: Frame, seconds: float) -> None:
        """Called when every stage has processed a frame.

        :param run: the running pipeline's description.
        :param frame: the frame that was processed.
        :param seconds: wall time of the stages after ``dataset`` on this frame.
        """

    @hookspec
    def sgf_on_error(self, run: RunInfo, stage: StageNode, frame: Frame | None, error: BaseException) -> None:
        """Called when a stage raises; the run stops after the hooks have been called.

        :param run: the running pipeline's description.
        :param stage: the stage that failed.
        :param frame: the frame it was processing, or ``None`` during finalize.
        :param error: the exception it raised.
        """

    @hookspec
    def sgf_report_metrics(self, run: RunInfo) -> dict[str, Any] | None:
        """Return entries to merge into the run's ``metrics.json`` (or ``None``).

        :param run: the finished pipeline's description.
        """

    @hookspec
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        """Called once after finalize and after ``metrics.json`` was written.

        :param run: the finished pipeline's description.
        :param metrics: the metrics that were written.
        """
