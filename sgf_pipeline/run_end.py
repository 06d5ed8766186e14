"""The end of a run: the stages' end-of-run passes, the stage cache's new entries, a stopped run's partial results."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from sgf_pipeline.cache import CachePlan
from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import StageError
from sgf_pipeline.run_info import RunInfo, StageNode
from sgf_pipeline.stage import Settlement, Stage

if TYPE_CHECKING:
    import pluggy

log = logging.getLogger("sgf_pipeline")


def end_stages(
    order: list[StageNode],
    context: RunContext,
    info: RunInfo,
    hooks: pluggy.HookRelay,
    cache: CachePlan | None,
) -> None:
    """Every stage's end-of-run calls, in DAG order: each settles, then stage by stage concludes and finalizes.

    A failing call is reported to the observers (``sgf_on_error``) and the others still run; the first
    failure is raised at the end, its message naming the others.
    """
    failures: list[tuple[StageError, str]] = []
    settlement = Settlement()

    def end(node: StageNode, phase: str, *args: Any) -> Any:
        """One stage's end-of-run call, its result; a failure is recorded (result ``None``)."""
        try:
            if phase == "finalize" and cache is not None:
                return cache.finalize(node, context)
            return getattr(node.stage, phase)(context, *args)
        except Exception as exc:
            hooks.sgf_on_error(run=info, stage=node, frame=None, error=exc)
            error = StageError(
                f"stage {node.label} failed in {phase}: {type(exc).__name__}: {exc}", node.kind, node.name, None
            )
            error.__cause__ = exc
            failures.append((error, phase))
            return None

    # Every stage settles, then stage by stage concludes and finalizes, even after another failed: the
    # settlement goes on along the DAG (as it was when a stage failed).
    for node in order:
        if isinstance(node.stage, Stage):  # a dataset has nothing to settle
            settlement = end(node, "settle", settlement) or settlement
    for node in order:
        if isinstance(node.stage, Stage):
            settlement = end(node, "conclude", settlement) or settlement
        end(node, "finalize")
    if failures:
        first = failures[0][0]
        if len(failures) > 1:
            others = ", ".join(f"{e.kind}={e.name} in {phase}" for e, phase in failures[1:])
            first.args = (f"{first.args[0]} (also failed: {others})",)
        raise first


def commit_cache(cache: CachePlan, context: RunContext, reading: dict[str, Any], processed_all: bool) -> None:
    """Keep a finished run's new stage cache entries; report the run's use of the cache in metrics.json.

    ``reading`` is what the run's reading of its dataset counted, kept with the entries. A run that did
    not process every frame of its dataset (``processed_all`` false) keeps none.
    """
    if not processed_all:
        log.info("stage cache: the run did not process every frame of its dataset; no entry is kept")
        cache.abort()
        context.metrics["cache"] = cache.report()
        return
    try:
        cache.commit(reading)
    except OSError as exc:  # a full disk costs the cache, never the run
        log.warning("stage cache: the new entries were not kept: %s", exc)
        cache.abort()
    context.metrics["cache"] = cache.report()


def keep_partial(order: list[StageNode], context: RunContext) -> None:
    """Have every stage keep what it has so far (the pose estimate, the SGF map) for a stopped run's files."""
    settlement = Settlement()
    for node in order:
        if isinstance(node.stage, Stage):
            try:
                settlement = node.stage.partial(context, settlement)
            except KeyboardInterrupt:  # a second Ctrl-C: record the run with what is kept so far
                break
            except Exception as error:  # a stage broken by the stop itself: the others still keep theirs
                log.warning("%s could not keep its results so far: %s: %s", node.label, type(error).__name__, error)
