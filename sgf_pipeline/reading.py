"""Reading the dataset: frames checked and counted, keyframes chosen, the path ahead of each buffered."""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from sgf_pipeline.config import RunOptions
from sgf_pipeline.errors import SgfError, StageError
from sgf_pipeline.run_info import RunInfo, StageNode
from sgf_pipeline.stage import Dataset
from sgf_pipeline.types import Frame, PathAhead

log = logging.getLogger("sgf_pipeline")

#: Largest deviation of an odometry rotation from orthonormal that the runner accepts.
_RIGID_TOLERANCE = 1e-3
_LOGGED_PER_REASON = 5


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


class FrameDrops:
    """The frames the runner refused, counted by reason, and the ground-truth poses left out."""

    def __init__(self) -> None:
        self.by_reason: Counter[str] = Counter()
        self.ground_truth = 0

    def drop(self, frame: Frame, reason: str) -> None:
        """Count (and log the first few of) a frame the runner refuses."""
        self.by_reason[reason] += 1
        if self.by_reason[reason] <= _LOGGED_PER_REASON:
            log.warning("frame %s (t=%s) dropped: %s", frame.index, frame.timestamp, reason)
        elif self.by_reason[reason] == _LOGGED_PER_REASON + 1:
            log.warning("more frames dropped for %r; logging no more of them (counted in metrics.json)", reason)

    def report(self) -> dict[str, Any]:
        """Frames the runner refused, by reason, and ground-truth poses left out (for metrics.json)."""
        return {
            "dropped_frames": sum(self.by_reason.values()),
            "dropped_by_reason": dict(sorted(self.by_reason.items())),
            "ground_truth_dropped": self.ground_truth,
        }


class DatasetReader:
    """The dataset stage's frames, checked, timed and counted in the run's info, keyframes chosen."""

    def __init__(self, node: StageNode, info: RunInfo, options: RunOptions, drops: FrameDrops) -> None:
        self.dataset_node = node
        self.info = info
        self.options = options
        self.drops = drops
        self.last_key: np.ndarray | None = None
        #: Whether keyframes' images are loaded as they are read (counted as dataset time); when stages
        #: take their outputs from the stage cache, an image is loaded only if a stage reads it.
        self.load_images = True

    @property
    def dataset(self) -> Dataset:
        """The dataset stage."""
        stage = self.dataset_node.stage
        assert isinstance(stage, Dataset)
        return stage

    def frames(self, distance: float) -> Iterator[Frame]:
        """The keyframes; with a ``distance`` read ahead, each with its ``path_ahead`` (see :func:`read_ahead`)."""
        if distance > 0.0:
            yield from read_ahead(self.read(), distance, self.options.read_ahead_seconds)
            return
        for frame, key in self.read():
            if key:
                yield frame

    def is_keyframe(self, frame: Frame) -> bool:
        """Whether the frame moved far enough from the last processed one to be processed."""
        opts = self.options
        if opts.keyframe_distance <= 0.0 or self.last_key is None:
            return True
        delta = np.linalg.inv(self.last_key) @ frame.odometry
        moved = float(np.linalg.norm(delta[:3, 3]))
        turned = math.acos(max(-1.0, min(1.0, (np.trace(delta[:3, :3]) - 1.0) / 2.0)))
        return moved >= opts.keyframe_distance or turned >= opts.keyframe_angle

    def read(self) -> Iterator[tuple[Frame, bool]]:
        """Every valid frame of the dataset, and whether it is a keyframe (whose image is then loaded)."""
        iterator = iter(self.dataset.frames())
        limit = self.options.max_frames
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
                self.drops.drop(frame, problem)
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
                self.last_key = frame.odometry
            if key and self.load_images:
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


#: Keyframes the reading thread may hold ready ahead of the one being processed.
READ_DEPTH = 4
_COUNTS = ("frames_seen", "dataset_seconds", "first_timestamp", "last_timestamp")


def read_in_background(reader: DatasetReader, distance: float, depth: int = READ_DEPTH) -> Iterator[Frame]:
    """The reader's keyframes, read (decoded or rendered) by a thread up to ``depth`` keyframes ahead.

    Reading and processing overlap on two cores; the keyframes, their order and their contents are
    those of :meth:`DatasetReader.frames`. The thread counts into its own copy of the run's
    counters, and each keyframe brings the counts as they stood when it was read, so the run sees
    the counts of a reading in its own thread. The dataset is only touched by the thread.
    """
    own_info = dataclasses.replace(reader.info)
    own_drops = FrameDrops()
    own_drops.by_reason.update(reader.drops.by_reason)
    own = DatasetReader(reader.dataset_node, own_info, reader.options, own_drops)
    own.last_key, own.load_images = reader.last_key, reader.load_images
    ready: queue.Queue[tuple[Any, dict[str, Any], Counter[str]]] = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def put(item: Any) -> bool:
        counts = {name: getattr(own_info, name) for name in _COUNTS}
        while not stop.is_set():
            try:
                ready.put((item, counts, Counter(own_drops.by_reason)), timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def read() -> None:
        try:
            for frame in own.frames(distance):
                if not put(frame):
                    return
            put(end)
        except BaseException as exc:  # handed to the caller, raised there
            put(exc)

    thread = threading.Thread(target=read, name="sgf-reading", daemon=True)
    thread.start()
    try:
        while True:
            item, counts, drops = ready.get()
            for name, value in counts.items():
                setattr(reader.info, name, value)
            reader.drops.by_reason = drops
            if item is end:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=10.0)


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
