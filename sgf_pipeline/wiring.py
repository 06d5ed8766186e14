"""The stage graph: configured stages instantiated, their inputs wired to outputs and put in DAG order.

Every config or wiring error is raised here, before the first frame: a variant of the wrong kind,
invalid parameters, a missing or ambiguous producer, a type mismatch on an edge, or a cycle.
"""

from __future__ import annotations

import graphlib
import logging

from sgf_pipeline.config import StageConfig, format_validation_error
from sgf_pipeline.errors import ConfigError, PipelineGraphError
from sgf_pipeline.registry import LoadedPlugins
from sgf_pipeline.run_info import StageNode
from sgf_pipeline.stage import Dataset

log = logging.getLogger("sgf_pipeline")


def build_node(sc: StageConfig, plugins: LoadedPlugins) -> StageNode:
    """The stage node of one configured stage: its variant, validated parameters and renamed inputs."""
    variant = plugins.registry.get(sc.kind, sc.name)
    if variant.kind != sc.kind:  # pragma: no cover - registry keys guarantee this
        raise ConfigError(f"{sc.kind}: variant {sc.name!r} is a {variant.kind} stage")
    try:
        params = variant.params_model.model_validate(sc.params)
    except Exception as exc:
        from pydantic import ValidationError

        if isinstance(exc, ValidationError):
            detail = format_validation_error(sc.kind, variant.params_model, exc)
            raise ConfigError(f"invalid parameters for {sc.kind}={sc.name}:\n  {detail}") from None
        raise
    try:
        stage = variant.cls(params)
    except (ValueError, FileNotFoundError) as exc:
        raise ConfigError(f"{sc.kind}={sc.name} cannot start: {exc}") from exc
    node = StageNode(sc.kind, sc.name, variant, stage, variant.cls.output)
    unknown = set(sc.rename) - {i.parameter for i in variant.signature.inputs}
    if unknown:
        known = ", ".join(i.parameter for i in variant.signature.inputs) or "none"
        raise PipelineGraphError(
            f"{sc.kind}.rename names input(s) {sorted(unknown)} that {sc.kind}={sc.name} does not have "
            f"(its inputs: {known})"
        )
    node.inputs = [(spec, sc.rename.get(spec.parameter, spec.parameter)) for spec in variant.signature.inputs]
    return node


def wire(nodes: list[StageNode]) -> list[StageNode]:
    """The nodes in the order frames flow through them (the dataset first), every edge checked."""
    datasets = [n for n in nodes if isinstance(n.stage, Dataset)]
    if len(datasets) != 1:
        raise PipelineGraphError(
            f"a pipeline needs exactly one dataset stage, got {len(datasets)} "
            f"({', '.join(n.label for n in datasets) or 'none'}); put `dataset` first in `pipeline`"
        )
    producers: dict[str, StageNode] = {}
    for node in nodes:
        other = producers.get(node.output)
        if other is not None:
            raise PipelineGraphError(
                f"output {node.output!r} is produced by two stages, {other.label} and {node.label}; "
                "remove one of them from `pipeline`"
            )
        producers[node.output] = node
    graph: dict[str, set[str]] = {n.kind: set() for n in nodes}
    for node in nodes:
        for spec, source in node.inputs:
            producer = producers.get(source)
            if producer is None and spec.optional:
                # An optional input (``X | None``, ``Previous[X]``) that no stage produces receives None,
                # e.g. the association's back-end estimate in a pipeline without a back-end.
                log.info("%s: optional input %r has no producer; it receives None", node.label, source)
                continue
            if producer is None:
                available = ", ".join(f"{o} ({p.label})" for o, p in sorted(producers.items()))
                raise PipelineGraphError(
                    f"{node.label} needs input {source!r} ({spec.describe()}) but no stage produces it. "
                    f"Outputs available: {available}. Add a stage that produces {source!r} to `pipeline`, "
                    f"or map the input to another output with {node.kind}.rename.{spec.parameter}=<output>"
                )
            produced = producer.variant.signature.output_types
            if not _types_compatible(produced, spec.types):
                got = " | ".join(t.__name__ for t in produced)
                raise PipelineGraphError(
                    f"type mismatch on edge {producer.label} -> {node.label}: {producer.label} produces "
                    f"{source!r} as {got}, but {node.label} expects {spec.parameter!r} as {spec.describe()}. "
                    f"Wire another output with {node.kind}.rename.{spec.parameter}=<output>"
                )
            if not spec.previous:
                graph[node.kind].add(producer.kind)
    try:
        order = list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        cycle = exc.args[1]
        raise PipelineGraphError(
            f"the stages form a cycle: {' -> '.join(cycle)}. Break it by removing a stage or by "
            "declaring one input as Previous[...] (the value of the previous frame)"
        ) from None
    by_kind = {n.kind: n for n in nodes}
    ordered = [by_kind[k] for k in order]
    ordered.remove(datasets[0])
    return [datasets[0], *ordered]


def _types_compatible(produced: tuple[type, ...], expected: tuple[type, ...]) -> bool:
    return all(any(issubclass(p, e) for e in expected) for p in produced)
