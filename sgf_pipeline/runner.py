"""The pipeline: a DAG of configured stages that frames stream through in time order.

Usable as a library: ``Pipeline.from_config(cfg)`` builds and validates the graph (every config
or wiring error is raised here, before the first frame), ``process(frame)`` runs one frame and
``finish()`` finalizes and writes the run directory. ``run()`` does all three over the dataset.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sgf_pipeline import outputs
from sgf_pipeline.cache import CachePlan, StageCache, cache_dir
from sgf_pipeline.config import (
    PipelineConfig,
    check_keys,
    parse_config,
    plain_config,
    validate_options,
)
from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import CacheError, StageError
from sgf_pipeline.reading import DatasetReader, FrameDrops, frame_problem, read_in_background
from sgf_pipeline.reading import read_ahead as read_ahead
from sgf_pipeline.registry import LoadedPlugins, load_plugins
from sgf_pipeline.run_directory import LOCK_FILE as LOCK_FILE
from sgf_pipeline.run_directory import RUN_FILES as RUN_FILES
from sgf_pipeline.run_directory import RunDirectory
from sgf_pipeline.run_end import commit_cache, end_stages, keep_partial
from sgf_pipeline.run_info import RunInfo, RunView
from sgf_pipeline.stage import Dataset, Stage
from sgf_pipeline.trajectory import Trajectory
from sgf_pipeline.types import Frame, PoseEstimate
from sgf_pipeline.wiring import build_node, wire

log = logging.getLogger("sgf_pipeline")


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


class Pipeline:
    """A validated stage graph bound to one dataset sequence.

    The graph is built by :mod:`sgf_pipeline.wiring`, frames are read by a
    :class:`~sgf_pipeline.reading.DatasetReader` and the run's files go to a
    :class:`~sgf_pipeline.run_directory.RunDirectory`.
    """

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
        self.order = wire([build_node(config.stages[kind], plugins) for kind in config.pipeline])
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
        self._last_processed: float | None = None
        self.drops = FrameDrops()
        self.reader = DatasetReader(self.dataset_node, self.info, config.run, self.drops)
        self._begun = False
        self._finished = False
        self._written = False
        self.cache: CachePlan | None = None
        self._yielded: Frame | None = None  # the last frame frames() gave
        self._given = self._taken = 0  # frames frames() gave, and of them the ones process() took
        self._read_to_end = False
        self.directory = RunDirectory(self.run_dir, config.run.overwrite) if self.run_dir is not None else None

    # -- building ---------------------------------------------------------------------------

    @classmethod
    def from_config(
        cls,
        cfg: Mapping[str, Any],
        run_dir: str | Path | None = None,
        plugins: LoadedPlugins | None = None,
    ) -> Pipeline:
        """Build a pipeline from a composed config (a DictConfig or a plain mapping)."""
        raw = plain_config(cfg)
        config = parse_config(raw)
        if plugins is None:
            plugins = load_plugins(allow=config.plugins.allow, block=config.plugins.block)
        check_keys(raw, [*plugins.registry.kinds(), *config.pipeline], plugins.observer_options)
        return cls(config, plugins, Path(run_dir) if run_dir is not None else None, effective_config=raw)

    # -- running ----------------------------------------------------------------------------

    @property
    def dataset(self) -> Dataset:
        """The dataset stage."""
        stage = self.dataset_node.stage
        assert isinstance(stage, Dataset)
        return stage

    def begin(self, cache: bool = False) -> None:
        """Prepare every stage for the sequence and announce the run to observers.

        With ``cache`` (as :meth:`frames` begins a run) the stages take their outputs from the stage
        cache where it has them: a run fed frames from elsewhere (a robot's driver) computes everything.
        """
        if self._begun:
            return
        if self.config.run.torch_threads is not None:
            try:
                import torch

                torch.set_num_threads(self.config.run.torch_threads)
            except ImportError:  # pragma: no cover - torch is a dependency
                pass
        root = cache_dir(self.config.run) if cache else None
        if root is not None:
            store = StageCache(root, int(self.config.run.cache_max_gb * 1e9))
            self.cache = CachePlan.build(store, self.order, self.config.run, self.read_ahead)
            self.reader.load_images = not self.cache.hits
        if self.cache is not None and self.cache.dataset_from_cache:
            self.info.total_frames = self.cache.reading["total_frames"]
        else:
            self.info.total_frames = len(self.dataset)
        for node in self.order:
            if self.cache is not None:
                self.cache.begin(node, self.context)
            else:
                node.stage.begin(self.context)
        if self.context.sequence:  # the dataset's own name for the recording (else the variant's)
            self.info.sequence = self.context.sequence
        if self.directory is not None:
            self.directory.claim()
        self.plugins.manager.hook.sgf_run_start(run=self.info)
        self._begun = True

    def release(self) -> None:
        """Unlock the run directory (``run`` and ``finish`` do it; for code that stops feeding frames early).

        Stage cache entries still being filled are dropped: only a finished run fills the cache.
        """
        if self.cache is not None:
            self.cache.abort()
        if self.directory is not None:
            self.directory.release()

    def drop_report(self) -> dict[str, Any]:
        """Frames the runner refused, by reason, and ground-truth poses left out (for metrics.json)."""
        return self.drops.report()

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
        if self.cache is not None and frame is not self._yielded:
            raise CacheError(
                f"frame {frame.index} did not come from Pipeline.frames(), whose run takes stage outputs from the "
                "stage cache; feed one source of frames, or set run.cache=false"
            )
        self._taken += 1
        problem = frame_problem(frame, self._last_processed)
        if problem is not None:
            self.drops.drop(frame, problem)
            return StepResult(frame.index, frame.timestamp, {}, None, dropped=problem)
        hook = self.plugins.manager.hook
        values: dict[str, Any] = {"frame": frame}
        start = time.perf_counter()
        cache = self.cache
        for node in self.order[1:]:
            if cache is not None:
                hit, out = cache.cached_output(node, frame, values)
                if hit:
                    values[node.output] = out
                    hook.sgf_after_stage(run=self.info, stage=node, frame=frame, output=out, seconds=0.0)
                    continue
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
                if cache is not None:
                    cache.keep(node, frame, None, {})
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
            if cache is not None:
                cache.keep(node, frame, out, kwargs)
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
                self.drops.ground_truth += 1
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
        self.begin(cache=True)
        cache = self.cache
        filling = cache if cache is not None and not cache.dataset_from_cache else None
        if cache is not None and cache.dataset_from_cache:
            source = self._cached_frames(cache)
        elif self.reader.load_images:  # the images read by a thread while the stages work
            source = read_in_background(self.reader, distance)
        else:  # images loaded when a stage reads them, in this thread
            source = self.reader.frames(distance)
        for frame in source:
            if filling is not None:
                filling.keep_frame(frame, self.context, self.info.frames_seen)
            self._yielded = frame
            self._given += 1
            yield frame
        self._read_to_end = True

    def _cached_frames(self, cache: CachePlan) -> Iterator[Frame]:
        """The keyframes kept in the stage cache, counted as the dataset's reading counted them."""
        reading = cache.reading
        start = time.perf_counter()
        for frame, seen in cache.frames(self.context):
            self.info.frames_seen = seen
            if self.info.first_timestamp is None:
                self.info.first_timestamp = frame.timestamp
            self.info.dataset_seconds += time.perf_counter() - start
            yield frame
            start = time.perf_counter()
        self.info.frames_seen = reading["frames_seen"]
        self.info.last_timestamp = reading["last_timestamp"]
        self.drops.by_reason.update(reading["dropped_by_reason"])

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
        cache = self.cache
        end_stages(self.order, self.context, self.info, self.plugins.manager.hook, cache)
        if cache is not None:
            self._commit_cache(cache)
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

    def _commit_cache(self, cache: CachePlan) -> None:
        """Keep the finished run's new stage cache entries (:func:`~sgf_pipeline.run_end.commit_cache`)."""
        reading = {
            "total_frames": self.info.total_frames,
            "frames_seen": self.info.frames_seen,
            "last_timestamp": self.info.last_timestamp,
            "dropped_by_reason": dict(self.drops.by_reason),
        }
        commit_cache(cache, self.context, reading, self._read_to_end and self._taken == self._given)

    def _write_failure(self, exc: BaseException) -> None:
        if self.run_dir is None or not self._begun:
            return
        if self._written:  # every file of the run is complete; the error came after (an observer)
            log.error("the run in %s finished writing before it failed: %s: %s", self.run_dir, type(exc).__name__, exc)
            return
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        keep_partial(self.order, self.context)  # what each stage has so far (the pose estimate, the SGF map)
        outputs.write_failure(self.view(), status, exc)


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
