"""The pipeline: a DAG of configured stages that frames stream through in time order.

Usable as a library: ``Pipeline.from_config(cfg)`` builds and validates the graph (every config
or wiring error is raised here, before the first frame), ``process(frame)`` runs one frame and
``finish()`` finalizes and writes the run directory. ``run()`` does all three over the dataset.
"""

from __future__ import annotations

import graphlib
import logging
import math
import os
import time
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from sgf_pipeline import outputs
from sgf_pipeline.config import (
    PipelineConfig,
    StageConfig,
    check_keys,
    format_validation_error,
    parse_config,
    validate_options,
)
from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import ConfigError, PipelineGraphError, SgfError, StageError
from sgf_pipeline.registry import LoadedPlugins, load_plugins
from sgf_pipeline.run_info import RunInfo, RunView, StageNode
from sgf_pipeline.stage import Dataset, Settlement, Stage
from sgf_pipeline.trajectory import Trajectory
from sgf_pipeline.types import Frame, PathAhead, PoseEstimate

log = logging.getLogger("sgf_pipeline")

#: Files of a finished run that the runner writes (plus ``trajectory_*.tum``); cleared before an overwrite.
RUN_FILES = ("metrics.json", "report.md", "trajectory.png", "loops.csv", "config.yaml", "failure.json")
#: The lock a running pipeline holds on its run directory (a second run into it is refused).
LOCK_FILE = ".sgf-run.lock"
#: Largest deviation of an odometry rotation from orthonormal that the runner accepts.
_RIGID_TOLERANCE = 1e-3
_LOGGED_PER_REASON = 5


@dataclass
class StepResult:
    """What ``process(frame)`` returns: every stage output and the current pose estimate.

    ``dropped`` names why the runner refused the frame (non-finite odometry, time going back, ...);
    a dropped frame reaches no stage and is counted in metrics.json under ``runner``.
    """

    frame_index: int
    timestamp: float
    outputs: dict[str, Any]
    pose: np.ndarray | None
    dropped: str | None = None


def frame_problem(frame: Frame, last_timestamp: float | None) -> str | None:
    """Why a frame cannot enter the pipeline (a short reason), or None when it can."""
    if not isinstance(frame.timestamp, (int, float)) or not math.isfinite(frame.timestamp):
        return "non-finite timestamp"
    if last_timestamp is not None and frame.timestamp <= last_timestamp:
        return "timestamp not increasing"
    odometry = np.asarray(frame.odometry)
    if odometry.shape != (4, 4) or not np.issubdtype(odometry.dtype, np.number):
        return "malformed odometry"
    if not np.all(np.isfinite(odometry)):
        return "non-finite odometry"
    rotation = odometry[:3, :3].astype(np.float64)
    rigid = np.abs(rotation @ rotation.T - np.eye(3)).max() <= _RIGID_TOLERANCE and np.allclose(
        odometry[3], (0.0, 0.0, 0.0, 1.0)
    )
    return None if rigid else "non-rigid odometry"


def _types_compatible(produced: tuple[type, ...], expected: tuple[type, ...]) -> bool:
    return all(any(issubclass(p, e) for e in expected) for p in produced)


class Pipeline:
    """A validated stage graph bound to one dataset sequence."""

    def __init__(
        self,
        config: PipelineConfig,
        plugins: LoadedPlugins,
        run_dir: Path | None = None,
        effective_config: Mapping[str, Any] | None = None,
    ) -> None:
        self.config = config
        self.plugins = plugins
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.effective_config = effective_config
        nodes = [self._instantiate(config.stages[kind]) for kind in config.pipeline]
        self.order = self._wire(nodes)
        self.dataset_node = self.order[0]
        self.context = RunContext(run_dir=self.run_dir)
        self.info = RunInfo(
            run_dir=self.run_dir,
            stages=self.order,
            sequence=self.dataset_node.name,
            total_frames=0,
            options=config.run,
            context=self.context,
            observer_options={
                name: validate_options(name, model, (effective_config or {})[name])
                for name, model in plugins.observer_options.items()
                if (effective_config or {}).get(name) is not None
            },
        )
        self._previous: dict[str, Any] = {}
        self._odometry = PoseLog()
        self._ground_truth = PoseLog()
        self._last_key: np.ndarray | None = None
        self._last_processed: float | None = None
        self._dropped: Counter[str] = Counter()
        self._ground_truth_dropped = 0
        self._lock: IO[str] | None = None
        self._begun = False
        self._finished = False
        self._written = False
        self._check_finished_run()

    def _check_finished_run(self) -> None:
        if self.run_dir is not None and (self.run_dir / "metrics.json").exists() and not self.config.run.overwrite:
            raise ConfigError(
                f"{self.run_dir} already holds a finished run (metrics.json); choose another output "
                "directory (hydra.run.dir=...) or pass run.overwrite=true to replace it"
            )

    # -- building ---------------------------------------------------------------------------

    @classmethod
    def from_config(
        cls,
        cfg: Mapping[str, Any],
        run_dir: str | Path | None = None,
        plugins: LoadedPlugins | None = None,
    ) -> Pipeline:
        """Build a pipeline from a composed config (a DictConfig or a plain mapping)."""
        raw = _to_plain(cfg)
        config = parse_config(raw)
        if plugins is None:
            plugins = load_plugins(allow=config.plugins.allow, block=config.plugins.block)
        check_keys(raw, [*plugins.registry.kinds(), *config.pipeline], plugins.observer_options)
        return cls(config, plugins, Path(run_dir) if run_dir is not None else None, effective_config=raw)

    def _instantiate(self, sc: StageConfig) -> StageNode:
        variant = self.plugins.registry.get(sc.kind, sc.name)
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

    def _wire(self, nodes: list[StageNode]) -> list[StageNode]:
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

    # -- running ----------------------------------------------------------------------------

    @property
    def dataset(self) -> Dataset:
        """The dataset stage."""
        stage = self.dataset_node.stage
        assert isinstance(stage, Dataset)
        return stage

    def begin(self) -> None:
        """Prepare every stage for the sequence and announce the run to observers."""
        if self._begun:
            return
        if self.config.run.torch_threads is not None:
            try:
                import torch

                torch.set_num_threads(self.config.run.torch_threads)
            except ImportError:  # pragma: no cover - torch is a dependency
                pass
        self.info.total_frames = len(self.dataset)
        for node in self.order:
            node.stage.begin(self.context)
        if self.context.sequence:  # the dataset's own name for the recording (else the variant's)
            self.info.sequence = self.context.sequence
        if self.run_dir is not None:
            self._claim_run_dir(self.run_dir)
        self.plugins.manager.hook.sgf_run_start(run=self.info)
        self._begun = True

    def _claim_run_dir(self, run_dir: Path) -> None:
        """Lock the run directory for this run, and clear what an earlier run left there when allowed."""
        run_dir.mkdir(parents=True, exist_ok=True)
        self._lock = _lock_directory(run_dir)
        try:
            self._check_finished_run()  # again, under the lock: another run may have finished meanwhile
        except ConfigError:
            self.release()
            raise
        if (run_dir / "metrics.json").exists():  # run.overwrite=true: the old run's files go first
            log.warning("run.overwrite=true: replacing the finished run in %s", run_dir)
            stale = [run_dir / n for n in RUN_FILES] + sorted(run_dir.glob("trajectory_*.tum"))
        elif (run_dir / "failure.json").exists():
            log.warning("%s holds the record of a failed run (failure.json); a new run replaces it", run_dir)
            stale = [run_dir / "failure.json", *sorted(run_dir.glob("trajectory_*.partial.tum"))]
            stale += sorted(run_dir.glob("*.partial.safetensors"))
        else:
            stale = []
        for path in stale:  # metrics.json first: the directory stops claiming a finished run at once
            path.unlink(missing_ok=True)

    def release(self) -> None:
        """Unlock the run directory (``run`` and ``finish`` do it; for code that stops feeding frames early)."""
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def is_keyframe(self, frame: Frame) -> bool:
        """Whether the frame moved far enough from the last processed one to be processed."""
        opts = self.config.run
        if opts.keyframe_distance <= 0.0 or self._last_key is None:
            return True
        delta = np.linalg.inv(self._last_key) @ frame.odometry
        moved = float(np.linalg.norm(delta[:3, 3]))
        turned = math.acos(max(-1.0, min(1.0, (np.trace(delta[:3, :3]) - 1.0) / 2.0)))
        return moved >= opts.keyframe_distance or turned >= opts.keyframe_angle

    def _drop(self, frame: Frame, reason: str) -> None:
        """Count (and log the first few of) a frame the runner refuses."""
        self._dropped[reason] += 1
        if self._dropped[reason] <= _LOGGED_PER_REASON:
            log.warning("frame %s (t=%s) dropped: %s", frame.index, frame.timestamp, reason)
        elif self._dropped[reason] == _LOGGED_PER_REASON + 1:
            log.warning("more frames dropped for %r; logging no more of them (counted in metrics.json)", reason)

    def drop_report(self) -> dict[str, Any]:
        """Frames the runner refused, by reason, and ground-truth poses left out (for metrics.json)."""
        return {
            "dropped_frames": sum(self._dropped.values()),
            "dropped_by_reason": dict(sorted(self._dropped.items())),
            "ground_truth_dropped": self._ground_truth_dropped,
        }

    def view(self) -> RunView:
        """The run so far as its output files are written from: a read-only view."""
        logs = (("odometry", self._odometry), ("gt", self._ground_truth))
        return RunView(
            info=self.info,
            options=self.config.run,
            run_dir=self.run_dir,
            effective_config=self.effective_config,
            context=self.context,
            hooks=self.plugins.manager.hook,
            dropped=self.drop_report(),
            recorded={name: log_.trajectory() for name, log_ in logs if len(log_)},
        )

    def process(self, frame: Frame) -> StepResult:
        """Run every stage after ``dataset`` on one frame.

        A frame with a non-finite or non-rigid odometry pose, or a timestamp not after the last
        processed one, reaches no stage: it is counted, logged and returned with ``dropped`` set,
        so that a robot feeding imperfect data keeps running.
        """
        self.begin()
        problem = frame_problem(frame, self._last_processed)
        if problem is not None:
            self._drop(frame, problem)
            return StepResult(frame.index, frame.timestamp, {}, None, dropped=problem)
        hook = self.plugins.manager.hook
        values: dict[str, Any] = {"frame": frame}
        start = time.perf_counter()
        for node in self.order[1:]:
            kwargs: dict[str, Any] = {}
            skip = False
            for spec, source in node.inputs:
                value = self._previous.get(source) if spec.previous else values.get(source)
                if value is None and not spec.optional:
                    skip = True
                    break
                kwargs[spec.parameter] = value
            if skip:
                values[node.output] = None
                hook.sgf_after_stage(run=self.info, stage=node, frame=frame, output=None, seconds=0.0)
                continue
            hook.sgf_before_stage(run=self.info, stage=node, frame=frame)
            t0 = time.perf_counter()
            try:
                out = node.stage.process(**kwargs)  # type: ignore[union-attr]  # only Stage nodes follow dataset
            except Exception as exc:
                hook.sgf_on_error(run=self.info, stage=node, frame=frame, error=exc)
                raise StageError(
                    f"stage {node.label} failed on frame {frame.index} (t={frame.timestamp:.3f} s): "
                    f"{type(exc).__name__}: {exc}",
                    node.kind,
                    node.name,
                    frame.index,
                ) from exc
            seconds = time.perf_counter() - t0
            values[node.output] = out
            hook.sgf_after_stage(run=self.info, stage=node, frame=frame, output=out, seconds=seconds)
        elapsed = time.perf_counter() - start
        self.info.work_seconds += elapsed
        self.info.frames_processed += 1
        self._previous = values
        self._last_processed = float(frame.timestamp)
        self._odometry.append(frame.timestamp, frame.odometry)
        if frame.ground_truth is not None:
            truth = np.asarray(frame.ground_truth, dtype=np.float64)
            if truth.shape == (4, 4) and np.all(np.isfinite(truth)):
                self._ground_truth.append(frame.timestamp, truth)
            else:
                self._ground_truth_dropped += 1
        hook.sgf_frame_end(run=self.info, frame=frame, seconds=elapsed)
        pose = next((v.latest for v in values.values() if isinstance(v, PoseEstimate)), None)
        return StepResult(frame.index, frame.timestamp, values, pose)

    @property
    def read_ahead(self) -> float:
        """Metres of path read ahead of the frame being processed: the most any stage asks for."""
        return max((n.stage.read_ahead for n in self.order[1:] if isinstance(n.stage, Stage)), default=0.0)

    def frames(self) -> Iterator[Frame]:
        """The dataset's keyframes, timed and counted, in time order.

        With a :attr:`read_ahead`, a keyframe comes once the odometry has moved that far past it (or
        the sequence has ended), its ``path_ahead`` filled with every frame read after it.
        """
        distance = self.read_ahead
        if distance > 0.0:
            yield from read_ahead(self._read(), distance, self.config.run.read_ahead_seconds)
            return
        for frame, key in self._read():
            if key:
                yield frame

    def _read(self) -> Iterator[tuple[Frame, bool]]:
        """Every valid frame of the dataset, and whether it is a keyframe (whose image is then loaded)."""
        self.begin()
        iterator = iter(self.dataset.frames())
        limit = self.config.run.max_frames
        label = self.dataset_node.label
        while limit is None or self.info.frames_seen < limit:
            t0 = time.perf_counter()
            try:
                frame = next(iterator)
            except StopIteration:
                self.info.dataset_seconds += time.perf_counter() - t0
                return
            except SgfError:
                raise
            except Exception as exc:
                raise StageError(
                    f"dataset {label} failed after {self.info.frames_seen} frame(s): {type(exc).__name__}: {exc}",
                    "dataset",
                    self.dataset_node.name,
                    None,
                ) from exc
            self.info.frames_seen += 1
            problem = frame_problem(frame, None)  # order is checked below: going back is the dataset's bug
            if problem is not None:
                self._drop(frame, problem)
                self.info.dataset_seconds += time.perf_counter() - t0
                continue
            if self.info.first_timestamp is None:
                self.info.first_timestamp = frame.timestamp
            elif self.info.last_timestamp is not None and frame.timestamp <= self.info.last_timestamp:
                raise StageError(
                    f"dataset {self.dataset_node.label} yielded frame {frame.index} at t={frame.timestamp} "
                    f"after t={self.info.last_timestamp}: frames must come in increasing time order",
                    "dataset",
                    self.dataset_node.name,
                    frame.index,
                )
            self.info.last_timestamp = frame.timestamp
            key = self.is_keyframe(frame)
            if key:
                self._last_key = frame.odometry
                try:
                    _ = frame.image  # load (decode or render) now, so it counts as dataset time
                    frame.truth_ids()
                except SgfError:
                    raise
                except Exception as exc:
                    raise StageError(
                        f"dataset {label} failed to load frame {frame.index} (t={frame.timestamp:.3f} s): "
                        f"{type(exc).__name__}: {exc}",
                        "dataset",
                        self.dataset_node.name,
                        frame.index,
                    ) from exc
            self.info.dataset_seconds += time.perf_counter() - t0
            yield frame, key

    def run(self) -> dict[str, Any]:
        """Stream the whole dataset through the pipeline, finalize, and return the metrics."""
        try:
            for frame in self.frames():
                self.process(frame)
            return self.finish()
        except BaseException as exc:
            self._write_failure(exc)
            raise
        finally:
            self.release()

    # -- finishing --------------------------------------------------------------------------

    def finish(self) -> dict[str, Any]:
        """Finalize every stage, compute metrics and write the run directory."""
        if self._finished:
            raise RuntimeError("finish() was called twice")
        self.begin()
        self._finished = True
        failures: list[tuple[StageError, str]] = []
        settlement = Settlement()

        def end(node: StageNode, phase: str, *args: Any) -> Any:
            """One stage's end-of-run call, its result; a failure is recorded (result ``None``)."""
            try:
                return getattr(node.stage, phase)(self.context, *args)
            except Exception as exc:
                self.plugins.manager.hook.sgf_on_error(run=self.info, stage=node, frame=None, error=exc)
                error = StageError(
                    f"stage {node.label} failed in {phase}: {type(exc).__name__}: {exc}", node.kind, node.name, None
                )
                error.__cause__ = exc
                failures.append((error, phase))
                return None

        # Every stage settles, then stage by stage concludes and finalizes, even after another failed: the
        # settlement goes on along the DAG (as it was when a stage failed).
        for node in self.order:
            if isinstance(node.stage, Stage):  # a dataset has nothing to settle
                settlement = end(node, "settle", settlement) or settlement
        for node in self.order:
            if isinstance(node.stage, Stage):
                settlement = end(node, "conclude", settlement) or settlement
            end(node, "finalize")
        if failures:
            first = failures[0][0]
            if len(failures) > 1:
                others = ", ".join(f"{e.kind}={e.name} in {phase}" for e, phase in failures[1:])
                first.args = (f"{first.args[0]} (also failed: {others})",)
            raise first
        view = self.view()
        trajectories = dict(self.context.trajectories)
        for name, trajectory in view.recorded.items():
            trajectories.setdefault(name, trajectory)
        metrics = outputs.collect_metrics(view, trajectories)
        if self.run_dir is not None:
            outputs.write_run(view, trajectories, metrics)
            self._written = True
        self.release()
        self.plugins.manager.hook.sgf_run_end(run=self.info, metrics=metrics)
        if self._written and self.config.run.plots:
            assert self.run_dir is not None
            outputs.link_figures(self.run_dir)  # what the observers drew at the end
        return metrics

    def _write_failure(self, exc: BaseException) -> None:
        if self.run_dir is None or not self._begun:
            return
        if self._written:  # every file of the run is complete; the error came after (an observer)
            log.error("the run in %s finished writing before it failed: %s: %s", self.run_dir, type(exc).__name__, exc)
            return
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        settlement = Settlement()
        for node in self.order:  # what each stage has so far (the pose estimate, the SGF map)
            if isinstance(node.stage, Stage):
                try:
                    settlement = node.stage.partial(self.context, settlement)
                except KeyboardInterrupt:  # a second Ctrl-C: record the run with what is kept so far
                    break
                except Exception as error:  # a stage broken by the stop itself: the others still keep theirs
                    log.warning("%s could not keep its results so far: %s: %s", node.label, type(error).__name__, error)
        outputs.write_failure(self.view(), status, exc)


def read_ahead(frames: Iterable[tuple[Frame, bool]], distance: float, max_seconds: float = math.inf) -> Iterator[Frame]:
    """The keyframes of ``(frame, is_keyframe)`` pairs, each once the odometry has moved ``distance`` metres past it.

    Each keyframe gets ``path_ahead``: the odometry and IMU of every frame read after it until then.
    A keyframe that has waited ``max_seconds`` (the robot stands still), and the last keyframes of
    a sequence that ends sooner, go on with the path read so far (``complete`` False).
    """
    buffer: deque[tuple[Frame, float, bool]] = deque()  # frames from the oldest waiting keyframe on
    travelled = 0.0
    last: np.ndarray | None = None
    for frame, key in frames:
        position = np.asarray(frame.odometry, dtype=np.float64)[:3, 3]
        if last is not None:
            travelled += float(np.linalg.norm(position - last))
        last = position
        if key or buffer:
            buffer.append((frame, travelled, key))
        while buffer:
            oldest, start, _ = buffer[0]
            complete = travelled - start >= distance
            if not complete and frame.timestamp - oldest.timestamp < max_seconds:
                break
            yield _with_path(buffer, distance, complete)
    while buffer:
        yield _with_path(buffer, distance, complete=False)


def _with_path(buffer: deque[tuple[Frame, float, bool]], distance: float, complete: bool) -> Frame:
    """Pop the oldest keyframe with the frames after it as its path ahead; drop the non-keyframes before the next."""
    frame, _, _ = buffer.popleft()
    after = [f for f, _, _ in buffer]
    odometry = np.array([np.asarray(f.odometry, dtype=np.float64) for f in after]).reshape(-1, 4, 4)
    imu = np.array([f.imu_roll_pitch if f.imu_roll_pitch is not None else (math.nan, math.nan) for f in after])
    frame.path_ahead = PathAhead(odometry, imu.reshape(-1, 2).astype(np.float64), distance, complete)
    while buffer and not buffer[0][2]:
        buffer.popleft()
    return frame


class PoseLog:
    """Timed poses appended frame by frame, kept as rows of 13 floats (t and the 3x4 pose) in a growing array.

    About 100 bytes a pose: an hours-long run's odometry fits where a list of 4x4 arrays would not.
    """

    def __init__(self) -> None:
        self._rows = np.empty((1024, 13), dtype=np.float64)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(self, timestamp: float, pose: np.ndarray) -> None:
        """Add one pose (4x4; the last row is taken to be 0 0 0 1)."""
        if self._count == len(self._rows):
            self._rows = np.concatenate([self._rows, np.empty_like(self._rows)])
        self._rows[self._count, 0] = timestamp
        self._rows[self._count, 1:] = np.asarray(pose, dtype=np.float64)[:3, :4].reshape(12)
        self._count += 1

    def trajectory(self) -> Trajectory:
        """The poses so far as a :class:`Trajectory`."""
        rows = self._rows[: self._count]
        poses = np.tile(np.eye(4), (self._count, 1, 1))
        poses[:, :3, :4] = rows[:, 1:].reshape(-1, 3, 4)
        return Trajectory(rows[:, 0].copy(), poses)


def _to_plain(cfg: Mapping[str, Any]) -> dict[str, Any]:
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(cfg, DictConfig):
        try:
            container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
        except OmegaConfBaseException as exc:
            raise ConfigError(describe_omegaconf_error(exc)) from None
        assert isinstance(container, dict)
        return {str(k): v for k, v in container.items() if k != "hydra"}
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"a configuration is a mapping (pipeline, run, plugins, stage nodes), got {cfg!r:.80}")
    return {str(k): v for k, v in dict(cfg).items() if k != "hydra"}


def describe_omegaconf_error(exc: Exception) -> str:
    """One paragraph about a config value OmegaConf cannot resolve, with the resolvers on offer."""
    from omegaconf.basecontainer import BaseContainer

    key = getattr(exc, "full_key", None) or "?"
    detail = [
        line.strip()
        for line in str(exc).splitlines()
        if line.strip() and not line.strip().startswith(("full_key:", "object_type=", "reference_type="))
    ]
    message = " ".join(" ".join(detail).split())
    resolvers = ", ".join(sorted(BaseContainer._resolvers))
    return (
        f"{key}: the value cannot be resolved: {message}. Interpolations may name other keys (${{run.max_frames}}) "
        f"or the registered resolvers ({resolvers}); none of them imports or runs code"
    )


def _lock_directory(run_dir: Path) -> IO[str] | None:
    """An exclusive lock on ``run_dir`` held while this process runs (released when it exits, even killed)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not a POSIX system: no lock
        return None
    handle = open(run_dir / LOCK_FILE, "a+")  # noqa: SIM115  (held open for the run's duration)
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        holder = handle.read().strip() or "?"
        handle.close()
        raise ConfigError(
            f"another run (process {holder}) is writing into {run_dir}; wait for it to end or choose another "
            "output directory (hydra.run.dir=...)"
        ) from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle
