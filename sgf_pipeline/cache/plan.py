"""A run's use of the stage cache: which stages take their outputs from it, which fill it."""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from sgf_pipeline.cache.keys import cacheable_nodes, dataset_components, digest, stage_components
from sgf_pipeline.cache.store import Entry, EntryWriter, StageCache
from sgf_pipeline.config import RunOptions
from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import ImageNotCachedError
from sgf_pipeline.run_info import StageNode
from sgf_pipeline.stage import Dataset
from sgf_pipeline.types import Frame

_CONTEXT_FIELDS = ("sequence", "rate_hz", "calibration", "truth")


@dataclass
class ContextSnapshot:
    """The run context before a stage's ``begin`` or ``finalize``, to tell what the stage changed."""

    metrics: dict[str, Any]
    artifacts: dict[str, int]
    fields: dict[str, int]
    trajectories: dict[str, int]

    @classmethod
    def of(cls, context: RunContext) -> ContextSnapshot:
        """The context as it is now."""
        return cls(
            copy.deepcopy(context.metrics),
            {k: id(v) for k, v in context.artifacts.items()},
            {f: id(getattr(context, f)) for f in _CONTEXT_FIELDS},
            {k: id(v) for k, v in context.trajectories.items()},
        )

    def changes(self, context: RunContext) -> dict[str, Any]:
        """What the context holds now that it did not (metric leaves, artifacts, fields, trajectories)."""
        return {
            "metrics": _metric_changes(self.metrics, context.metrics, []),
            "artifacts": {k: v for k, v in context.artifacts.items() if self.artifacts.get(k) != id(v)},
            "fields": {f: getattr(context, f) for f in _CONTEXT_FIELDS if self.fields[f] != id(getattr(context, f))},
            "trajectories": {k: v for k, v in context.trajectories.items() if self.trajectories.get(k) != id(v)},
        }


def _metric_changes(before: Any, after: Mapping[str, Any], path: list[str]) -> list[tuple[list[str], Any]]:
    changes: list[tuple[list[str], Any]] = []
    for key, value in after.items():
        old = before.get(key, _MISSING) if isinstance(before, Mapping) else _MISSING
        if isinstance(value, Mapping) and isinstance(old, Mapping):
            changes += _metric_changes(old, value, [*path, key])
        elif old is _MISSING or not _equal(old, value):
            changes.append(([*path, key], copy.deepcopy(value)))
    return changes


_MISSING = object()


def _equal(a: Any, b: Any) -> bool:
    try:
        return bool(a == b) and type(a) is type(b)
    except Exception:
        return False


def apply_changes(changes: Mapping[str, Any], context: RunContext) -> None:
    """Put recorded changes into the run context."""
    for path, value in changes["metrics"]:
        node = context.metrics
        for key in path[:-1]:
            child = node.get(key)
            if not isinstance(child, dict):
                child = node[key] = {}
            node = child
        node[path[-1]] = value
    context.artifacts.update(changes["artifacts"])
    for name, value in changes["fields"].items():
        setattr(context, name, value)
    context.trajectories.update(changes["trajectories"])


@dataclass
class CachePlan:
    """Which of a run's stages take their outputs from the cache, and which fill it.

    Built at the start of a run (:meth:`build`); the runner asks it for each cacheable stage's begin,
    output and finalize, and commits the filled entries when the run has finished.
    """

    cache: StageCache
    hits: dict[str, Entry] = field(default_factory=dict)
    writers: dict[str, EntryWriter] = field(default_factory=dict)
    frames_entry: Entry | None = None
    frames_writer: EntryWriter | None = None
    missed: list[str] = field(default_factory=list)  # cacheable stages that run (their entries filled, or not kept)
    seconds: float = 0.0

    @classmethod
    def build(cls, cache: StageCache, order: list[StageNode], options: RunOptions, read_ahead: float) -> CachePlan:
        """Look up every cacheable stage's entry; open writers for the missing ones."""
        start = time.perf_counter()
        dataset = order[0]
        data_components = dataset_components(dataset, options, read_ahead)
        keys = {dataset.kind: digest(data_components)}
        components: dict[str, dict[str, Any]] = {}
        producers = {n.output: n.kind for n in order}
        nodes = cacheable_nodes(order)
        for node in nodes:
            inputs = {spec.parameter: keys.get(producers.get(source, "")) for spec, source in node.inputs}
            components[node.kind] = stage_components(node, inputs)
            keys[node.kind] = digest(components[node.kind])
        plan = cls(cache)
        found = {node.kind: cache.lookup(node.kind, keys[node.kind]) for node in nodes}
        for node in reversed(nodes):  # a stage's readers before the stage
            entry = found[node.kind]
            if entry is None:
                continue
            readers = [n.kind for n in order if any(source == node.output for _, source in n.inputs)]
            if _keeps_outputs(node) or all(kind in plan.hits for kind in readers):
                plan.hits[node.kind] = entry
            else:  # its outputs are not kept and a stage after it needs them: it runs
                entry.close()
        if len(plan.hits) == len(components):
            plan.frames_entry = cache.lookup(dataset.kind, keys[dataset.kind])
        for kind, parts in components.items():
            if found[kind] is None:
                plan.writers[kind] = cache.writer(kind, keys[kind], parts)
            if kind not in plan.hits:
                plan.missed.append(kind)
        if plan.frames_entry is None and not cache.contains(dataset.kind, keys[dataset.kind]):
            plan.frames_writer = cache.writer(dataset.kind, keys[dataset.kind], data_components)
        plan.seconds += time.perf_counter() - start
        return plan

    @property
    def dataset_from_cache(self) -> bool:
        """Whether the keyframes come from the cache (the dataset is not read)."""
        return self.frames_entry is not None

    def begin(self, node: StageNode, context: RunContext) -> None:
        """The stage's ``begin``, or its recorded changes to the context on a hit."""
        self._run_or_replay(node, context, "begin")

    def finalize(self, node: StageNode, context: RunContext) -> None:
        """The stage's ``finalize``, or its recorded changes to the context on a hit."""
        self._run_or_replay(node, context, "finalize")

    def _run_or_replay(self, node: StageNode, context: RunContext, phase: str) -> None:
        dataset = isinstance(node.stage, Dataset)
        entry = self.frames_entry if dataset else self.hits.get(node.kind)
        if entry is not None:
            changes = entry.changes(phase)
            if changes:
                apply_changes(changes, context)
            return
        writer = self.frames_writer if dataset else self.writers.get(node.kind)
        before = ContextSnapshot.of(context) if writer is not None else None
        getattr(node.stage, phase)(context)
        if writer is not None and before is not None:
            writer.record_effects(phase, before.changes(context))

    def cached_output(self, node: StageNode, frame: Frame, values: Mapping[str, Any]) -> tuple[bool, Any]:
        """``(True, output)`` of a stage that hits, read for this frame; ``(False, None)`` otherwise."""
        entry = self.hits.get(node.kind)
        if entry is None:
            return False, None
        if not _keeps_outputs(node):  # every stage reading its outputs hits too
            return True, None
        start = time.perf_counter()
        inputs = {spec.parameter: values.get(source) for spec, source in node.inputs}
        out = entry.next(frame.index, inputs)
        self.seconds += time.perf_counter() - start
        return True, out

    def keep(self, node: StageNode, frame: Frame, output: Any, inputs: Mapping[str, Any]) -> None:
        """Write a missing stage's output of this frame into its entry."""
        writer = self.writers.get(node.kind)
        if writer is not None and _keeps_outputs(node):
            start = time.perf_counter()
            writer.add(frame.index, output, {id(v): k for k, v in inputs.items() if v is not None})
            self.seconds += time.perf_counter() - start

    def keep_frame(self, frame: Frame, context: RunContext, frames_seen: int) -> None:
        """Write a keyframe, all but its image, into the dataset's entry."""
        if self.frames_writer is None:
            return
        record = {
            "index": frame.index,
            "timestamp": frame.timestamp,
            "odometry": frame.odometry,
            "calibration": frame.calibration,
            "imu_roll_pitch": frame.imu_roll_pitch,
            "ground_truth": frame.ground_truth,
            "path_ahead": frame.path_ahead,
            "seen": frames_seen,
        }
        refs = {} if context.calibration is None else {id(context.calibration): "calibration"}
        self.frames_writer.add(frame.index, record, refs)

    def frames(self, context: RunContext) -> Iterator[tuple[Frame, int]]:
        """The cached keyframes (no image) and the dataset frames seen up to each."""
        entry = self.frames_entry
        assert entry is not None
        for data in entry.records():
            record = entry.decode(data, {"calibration": context.calibration})
            frame = Frame(
                record["index"],
                record["timestamp"],
                _image_not_cached(record["index"]),
                record["odometry"],
                record["calibration"],
                record["imu_roll_pitch"],
                record["ground_truth"],
                _image_not_cached(record["index"]),
            )
            frame.path_ahead = record["path_ahead"]
            yield frame, int(record["seen"])

    @property
    def reading(self) -> dict[str, Any]:
        """What the dataset's reading counted (frames seen, drops, timestamps), kept in the dataset's entry."""
        assert self.frames_entry is not None
        return dict(self.frames_entry.manifest.get("reading", {}))

    def commit(self, reading: Mapping[str, Any]) -> None:
        """Move every filled entry into place (the run finished), then bound the cache's size."""
        start = time.perf_counter()
        for writer in self.writers.values():
            writer.commit()
        if self.frames_writer is not None:
            self.frames_writer.commit({"reading": dict(reading)})
        self.writers, self.frames_writer = {}, None
        self.close()
        self.cache.evict()
        self.seconds += time.perf_counter() - start

    def abort(self) -> None:
        """Forget the entries being filled (the run stopped early)."""
        for writer in self.writers.values():
            writer.abort()
        if self.frames_writer is not None:
            self.frames_writer.abort()
        self.writers, self.frames_writer = {}, None
        self.close()

    def close(self) -> None:
        """Close the entries read."""
        for entry in self.hits.values():
            entry.close()
        if self.frames_entry is not None:
            self.frames_entry.close()

    def report(self) -> dict[str, Any]:
        """The run's use of the cache, for metrics.json (``cache``)."""
        return {
            "dir": str(self.cache.root),
            "hits": sorted(self.hits),
            "misses": sorted(self.missed),
            "dataset_from_cache": self.dataset_from_cache,
            "seconds": round(self.seconds, 3),
        }


def _image_not_cached(index: int) -> Any:
    def load() -> Any:
        raise ImageNotCachedError(
            f"frame {index} came from the stage cache without its image (every stage that reads images took its "
            "outputs from the cache); a stage or observer that reads frame images needs run.cache=false"
        )

    return load


def _keeps_outputs(node: StageNode) -> bool:
    """Whether the cache keeps the stage's outputs (``Stage.cache_outputs``)."""
    return bool(getattr(node.stage, "cache_outputs", True))
