"""A Rerun recording of a run (``sgf-run viz=rerun``): an observer on the lifecycle hooks, unknown to every stage.

Each keyframe is logged on two timelines, ``frame`` (its index) and ``time`` (its timestamp: a
duration, or a date when the dataset's clock is Unix time):

- ``camera/image``: the (enhanced) camera image, JPEG;
- ``bev/image``: the BEV at its own resolution, JPEG; ``bev/saliency``: the saliency map over it
  (a heat map at half opacity); ``bev/sgfs``: the outlines of the SGFs selected from that BEV,
  labelled with their track and group (logged at the frame of the view once the detector selects it);
- ``sgf/descriptor``: the polar descriptor of the newest SGF (rings x sectors), with the SGF's
  frame, track and group;
- ``map/*`` (2-D, x right and y up: y is logged negated) and ``world/*`` (3-D): ``odometry``,
  ``ground_truth`` (a segment per keyframe, shown from the start to the cursor), ``estimate``
  (the back-end's current estimate; ``map/robot`` its newest pose, heading as an arrow), ``correction``
  (arrows from poses to where the back-end moved them, shown on a frame that re-solves, at most 60)
  and ``loops/<n>``: row ``n`` of ``loop_candidates.csv``, a line
  between the estimated poses of its two frames in its outcome's colour, labelled with the outcome
  and its detail; ``log/loops`` and ``log/sgfs`` say the same as text;
- ``timing/<kind>``: each stage's milliseconds.

One frame after the last, the end of the run is logged: the final trajectory and its correction,
and the loops the end of the run decided or changed, so the recording ends as the run directory
does. The recording is written to ``<run dir>/run.partial.rrd`` and renamed ``run.rrd`` once the run
has finished (a failed run keeps the partial one); ``spawn``, ``connect`` and ``serve`` stream it to
a viewer as well. The logging runs on a thread of its own, ten keyframes at a time
(``bench/RESULTS.md`` has its cost); the pipeline's thread only hands the outputs over.
"""

from __future__ import annotations

import logging
import os
import queue
import sys
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from sgf_pipeline import ConfigError, hookimpl
from sgf_pipeline.errors import ImageNotCachedError
from sgf_pipeline.runner import RunInfo, StageNode
from sgf_pipeline.types import (
    Bev,
    CameraImage,
    Frame,
    GroupAssignments,
    LoopConstraints,
    PoseEstimate,
    SaliencyMap,
    SgfDescriptors,
    SgfDetections,
)
from sgf_plugins.viz.figures import group_colour

if TYPE_CHECKING:
    from sgf_pipeline.types import SalientGroundFeature

log = logging.getLogger("sgf_pipeline")

#: The config node of the observer's options.
NODE = "viz"
#: The recording of a finished run, and of one still running or failed.
RECORDING = "run.rrd"
PARTIAL_RECORDING = "run.partial.rrd"
#: The rerun-sdk minor version this recording is written for (its API changes between minor versions).
RERUN_VERSION = (0, 41)
APPLICATION_ID = "sgf-pipeline"
JPEG_QUALITY = 75
#: Timestamps from this value on are Unix time, shown as dates (after September 2001).
UNIX_TIME_FROM = 1e9
#: Keyframes whose rows are held back and sent together (a live viewer lags by as many).
SEND_FRAMES = 10
#: Keyframes queued for the recording thread at most (the pipeline waits beyond).
QUEUED_FRAMES = 32
#: Correction arrows drawn at most, and the smallest correction drawn (m).
MAX_ARROWS = 60
MIN_CORRECTION = 0.01

_OUTCOME_COLOURS = {
    "accepted": (60, 200, 80),
    "inconsistent": (230, 40, 230),
    "gate": (255, 150, 30),
    "icp": (240, 220, 50),
    "consensus": (160, 110, 255),
    "ambiguous": (60, 200, 230),
    "symmetric": (150, 150, 150),
    "separation": (170, 110, 60),
    "too_few_points": (250, 120, 160),
    "not_unique": (140, 160, 40),
    "map_unconfirmed": (40, 160, 150),
}
_TRAJECTORY_COLOURS = {"odometry": (230, 60, 50), "ground_truth": (220, 220, 220), "estimate": (60, 140, 255)}


def outcome_colour(outcome: str) -> tuple[int, int, int]:
    """The colour of a loop candidate's outcome (an outcome without its own colour gets its name's)."""
    known = _OUTCOME_COLOURS.get(outcome)
    if known is not None:
        return known
    return group_colour(sum(outcome.encode()))


def rerun_missing() -> str | None:
    """Why the installed rerun-sdk cannot write the recording, saying how to install it; None when it can."""
    wanted = ".".join(map(str, RERUN_VERSION))
    install = "install it with pip install 'sgf-pipeline[viz]' (in a checkout: scripts/setup.sh --dev)"
    try:
        version = metadata.version("rerun-sdk")
    except metadata.PackageNotFoundError:
        return (
            f"viz=rerun needs the rerun-sdk package ({wanted}, on Python 3.11 or later), which is not installed: "
            f"{install}, or run without viz=rerun"
        )
    if tuple(int(p) for p in version.split(".")[:2] if p.isdigit()) != RERUN_VERSION:
        return f"viz=rerun is written for rerun-sdk {wanted}, and {version} is installed: {install}"
    return None


class RerunOptions(BaseModel):
    """Where the recording goes (config node ``viz``: ``conf/viz/rerun.yaml``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Literal["rerun"] = Field("rerun", description="the viewer")
    save: bool = Field(True, description="write <run dir>/run.rrd")
    spawn: bool = Field(False, description="open a local Rerun viewer and stream to it")
    connect: str | None = Field(
        None, description="stream to a running viewer at this address: host:port, or a rerun+http://.../proxy URL"
    )
    serve: bool = Field(False, description="serve the recording and the web viewer while the run lasts")
    grpc_port: int = Field(9876, ge=1, le=65535, description="port of the spawned viewer, or of the served recording")
    web_port: int = Field(9090, ge=1, le=65535, description="port of the served web viewer")

    @field_validator("connect")
    @classmethod
    def _viewer_url(cls, value: str | None) -> str | None:
        """``host:port`` becomes the viewer's URL; a URL must be one the Rerun SDK connects to."""
        if value is None:
            return None
        if "://" not in value:
            return f"rerun+http://{value}/proxy"
        if not value.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ValueError("a viewer's address is host:port or a rerun://, rerun+http:// or rerun+https:// URL")
        return value

    @model_validator(mode="after")
    def _usable(self) -> RerunOptions:
        """rerun-sdk is installed, and the viewer's ports are taken once."""
        problem = rerun_missing()
        if problem is not None:
            raise ValueError(problem)
        if self.spawn and self.serve:
            raise ValueError("viz.spawn and viz.serve would both listen on viz.grpc_port: choose one of them")
        return self


def _jpeg(image: np.ndarray, bgr: bool = False) -> bytes:
    """JPEG bytes of a uint8 grey or RGB image (``bgr``: already in OpenCV's channel order)."""
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 3 and not bgr:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise ValueError(f"could not encode an image of shape {image.shape} as JPEG")
    return buffer.tobytes()


def outline(sgf: SalientGroundFeature) -> list[np.ndarray]:
    """The closed outlines of an SGF's BEV pixels, in the BEV image's coordinates (pixel centres at +0.5)."""
    pixels = np.asarray(sgf.pixels)
    if pixels.size == 0:
        return []
    h, w = sgf.grid.height, sgf.grid.width
    mask = np.zeros((h, w), np.uint8)
    mask[pixels[:, 1].clip(0, h - 1), pixels[:, 0].clip(0, w - 1)] = 1
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    strips = []
    for contour in contours:
        points = contour.reshape(-1, 2).astype(np.float32) + 0.5
        strips.append(np.vstack([points, points[:1]]))
    return strips


def nanoseconds(seconds: float) -> int:
    """A time in whole nanoseconds, as the recording's ``time`` timeline holds it."""
    return round(seconds * 1e9)


def _map_xy(positions: np.ndarray) -> np.ndarray:
    """Map-view coordinates of 3-D positions: x right, y up (a 2-D view's y points down)."""
    return np.column_stack([positions[:, 0], -positions[:, 1]]).astype(np.float32)


@dataclass(frozen=True)
class _Keyframe:
    """What the recording logs of one keyframe: the stages' outputs (by type; no stage changes them later)."""

    index: int
    timestamp: float
    image: np.ndarray | None  # None: the frame came from the stage cache without its image
    odometry: np.ndarray
    ground_truth: np.ndarray | None
    outputs: dict[type, Any]
    times: dict[str, float]
    first_candidate: int  # the index of the first loop candidate decided on this frame
    candidates: list[dict[str, Any]]  # copies of those candidates


class _Rows:
    """Rows of one entity held back and sent together as columns.

    A log call costs about 0.2 ms of Python in the Rerun SDK; a row of a batch of ten a third of that.
    """

    __slots__ = ("archetype", "fields", "frames", "times")

    def __init__(self, archetype: Any) -> None:
        self.archetype = archetype
        self.frames: list[int] = []
        self.times: list[int] = []
        self.fields: dict[str, list[Any]] = {}

    def add(self, index: int, timestamp: int, **fields: Any) -> None:
        """One row at ``frame=index``, ``time=timestamp`` (ns; one value of each field)."""
        self.frames.append(index)
        self.times.append(timestamp)
        for name, value in fields.items():
            self.fields.setdefault(name, []).append(value)

    def send(self, rr: Any, stream: Any, path: str, time_kind: str) -> None:
        """Send the rows held back."""
        if not self.frames:
            return
        nanos = np.asarray(self.times, dtype=np.int64).astype(
            "timedelta64[ns]" if time_kind == "duration" else "M8[ns]"
        )
        indexes = [rr.TimeColumn("frame", sequence=self.frames), rr.TimeColumn("time", **{time_kind: nanos})]
        stream.send_columns(path, indexes=indexes, columns=self.archetype.columns(**self.fields))
        self.frames, self.times, self.fields = [], [], {}


class _Recording:
    """One run's recording stream, and what it remembers between frames."""

    def __init__(self, run: RunInfo, options: RerunOptions) -> None:
        import rerun as rr

        self.rr = rr
        self.run_dir = run.run_dir
        self.saving = options.save and run.run_dir is not None
        self.stream = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        self.stream.set_log_time_enabled(False)  # the frame and time timelines only
        sinks: list[Any] = []
        if self.saving:
            assert run.run_dir is not None
            sinks.append(rr.FileSink(run.run_dir / PARTIAL_RECORDING))
        if options.spawn:
            executable = Path(sys.executable).parent / "rerun"  # the venv's viewer, also when it is not on PATH
            rr.spawn(
                port=options.grpc_port,
                connect=False,
                recording=self.stream,
                executable_path=str(executable) if executable.is_file() else None,
            )
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{options.grpc_port}/proxy"))
        if options.connect is not None:
            sinks.append(rr.GrpcSink(options.connect))
        server = rr.GrpcServerSink(port=options.grpc_port) if options.serve else None
        if server is not None:
            sinks.append(server)
        if not sinks:
            raise ConfigError(
                "viz=rerun has nowhere to send the recording: this pipeline writes no run directory; "
                "set viz.spawn=true, viz.connect=<address> or viz.serve=true"
            )
        self.stream.set_sinks(*sinks)
        if server is not None:
            rr.serve_web_viewer(web_port=options.web_port, open_browser=False, connect_to=server.uri)
            log.info(
                "Rerun web viewer: http://localhost:%d/?url=%s (while the run lasts)", options.web_port, server.uri
            )
        self.stream.send_blueprint(blueprint())
        self.stream.send_recording_name(run.sequence)
        self._static()
        self.time_kind: str | None = None  # "duration", or "timestamp" for Unix time
        self.now = (0, 0)  # the frame and time (ns) logged at
        self.rows: dict[str, _Rows] = {}
        self.held = 0  # frames whose rows are held back
        self.frames = np.zeros(1024, dtype=np.int64)  # processed frames, in order (the estimate's rows)
        self.count = 0
        self.last: dict[str, np.ndarray] = {}  # newest position of each trajectory drawn segment by segment
        self.estimate: PoseEstimate | None = None
        self.estimate_drawn = 0  # frames the whole estimate path covered when it was last drawn
        self.logged: list[tuple[str, str]] = []  # (outcome, detail) of each loop candidate as logged
        self.labelled: list[int] = []  # loop candidates labelled on the current frame
        self.last_frame: tuple[int, float] | None = None

    def _static(self) -> None:
        """What never changes: the 3-D axes, the trajectories' colours and the images' layering."""
        rr = self.rr
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for name, colour in _TRAJECTORY_COLOURS.items():
            paths = [f"{name}"] if name != "estimate" else ["estimate/path", "estimate/recent"]
            for path in paths:
                self.stream.log(f"world/{path}", rr.LineStrips3D.from_fields(colors=[colour]), static=True)
                self.stream.log(
                    f"map/{path}",
                    rr.LineStrips2D.from_fields(colors=[colour], radii=rr.Radius.ui_points(1.0)),
                    static=True,
                )
        self.stream.log(
            "map/robot",
            rr.Arrows2D.from_fields(colors=[_TRAJECTORY_COLOURS["estimate"]], radii=rr.Radius.ui_points(2.5)),
            static=True,
        )
        self.stream.log(
            "bev/saliency",
            rr.EncodedImage.from_fields(media_type="image/jpeg", opacity=0.5, draw_order=1.0),
            static=True,
        )

    # -- time ---------------------------------------------------------------------------------

    def at(self, index: int, timestamp: float) -> None:
        """Log what follows at ``frame=index`` and ``time=timestamp`` (s)."""
        if self.time_kind is None:
            self.time_kind = "timestamp" if timestamp >= UNIX_TIME_FROM else "duration"
        self.now = (index, nanoseconds(timestamp))
        self.stream.set_time("frame", sequence=index)
        if self.time_kind == "duration":
            self.stream.set_time("time", duration=np.timedelta64(self.now[1], "ns"))
        else:
            self.stream.set_time("time", timestamp=np.datetime64(self.now[1], "ns"))

    def hold(self, path: str, archetype: Any, **fields: Any) -> None:
        """A row of ``path`` at the current frame, sent with the next batch."""
        rows = self.rows.get(path)
        if rows is None:
            rows = self.rows[path] = _Rows(archetype)
        rows.add(*self.now, **fields)

    def send(self) -> None:
        """Send every row held back."""
        assert self.time_kind is not None
        for path, rows in self.rows.items():
            rows.send(self.rr, self.stream, path, self.time_kind)
        self.held = 0

    # -- per frame ----------------------------------------------------------------------------

    def log_frame(self, key: _Keyframe) -> None:
        """Everything the stages made of one keyframe."""
        rr = self.rr
        outputs = key.outputs
        self.last_frame = (key.index, key.timestamp)
        self.at(*self.last_frame)
        if self.count == len(self.frames):
            self.frames = np.concatenate([self.frames, np.zeros_like(self.frames)])
        self.frames[self.count] = key.index
        self.count += 1
        camera = outputs.get(CameraImage)
        image = camera.pixels if camera is not None else key.image
        if image is not None:
            self.hold("camera/image", rr.EncodedImage, blob=_jpeg(np.asarray(image)), media_type="image/jpeg")
        bev = outputs.get(Bev)
        if bev is not None:
            self.hold("bev/image", rr.EncodedImage, blob=_jpeg(bev.image), media_type="image/jpeg")
        saliency = outputs.get(SaliencyMap)
        if saliency is not None:
            heat = cv2.applyColorMap(cv2.convertScaleAbs(saliency.probability, alpha=255.0), cv2.COLORMAP_INFERNO)
            self.hold("bev/saliency", rr.EncodedImage, blob=_jpeg(heat, bgr=True))
        for kind, seconds in key.times.items():
            self.hold(f"timing/{kind}", rr.Scalars, scalars=1000.0 * seconds)
        self._log_trajectory("odometry", np.asarray(key.odometry, dtype=np.float64)[:3, 3])
        if key.ground_truth is not None:
            self._log_trajectory("ground_truth", key.ground_truth[:3, 3])
        self._log_sgfs(outputs)
        estimate = outputs.get(PoseEstimate)
        if estimate is not None:
            loops = outputs.get(LoopConstraints)
            resolved = (loops is not None and len(loops.items) > 0) or (
                self.estimate is not None and estimate.yaw_bias != self.estimate.yaw_bias
            )
            self._log_estimate(estimate, resolved)
        self._log_loops(key.first_candidate, key.candidates, final=False)
        self.held += 1
        if self.held >= SEND_FRAMES:
            self.send()

    def _log_sgfs(self, outputs: dict[type, Any]) -> None:
        """The SGFs selected on this frame (outlined on the BEV of their view's frame), and the newest descriptor."""
        rr = self.rr
        assignments = outputs.get(GroupAssignments)
        detections = outputs.get(SgfDetections)
        if assignments is not None:
            selected = [(a.descriptor.sgf, a.group_id, a.new_group) for a in assignments.items]
        elif detections is not None:
            selected = [(sgf, None, False) for sgf in detections.items]
        else:
            selected = []
        groups = {(sgf.frame_index, sgf.track_id): g for sgf, g, _ in selected}
        for sgf, group_id, new_group in selected:
            group = "" if group_id is None else f" -> {'new ' if new_group else ''}group {group_id}"
            label = f"SGF {sgf.track_id}{group}"
            self.stream.log("log/sgfs", rr.TextLog(f"{label} (view of frame {sgf.frame_index})", level="SGF"))
            strips = outline(sgf)
            if strips:  # shown on the BEV it was selected from, at that frame only
                self.at(sgf.frame_index, float(sgf.timestamp))
                self.stream.log(
                    "bev/sgfs",
                    rr.LineStrips2D(
                        strips,
                        colors=[group_colour(group_id if group_id is not None else sgf.track_id)],
                        labels=[label],  # one label for the SGF's parts
                        radii=rr.Radius.ui_points(1.5),
                        draw_order=2.0,
                    ),
                )
                assert self.last_frame is not None
                self.at(*self.last_frame)
        descriptors = outputs.get(SgfDescriptors)
        if descriptors is not None and descriptors.items:
            newest = descriptors.items[-1]
            self.stream.log(
                "sgf/descriptor",
                rr.Tensor(np.asarray(newest.matrix, dtype=np.float32), dim_names=["ring", "sector"]),
                rr.AnyValues(
                    sgf_frame=newest.sgf.frame_index,
                    sgf_track=newest.sgf.track_id,
                    sgf_group=groups.get((newest.sgf.frame_index, newest.sgf.track_id), -1),
                ),
            )

    def _log_trajectory(self, name: str, position: np.ndarray) -> None:
        """One more segment of a trajectory that never changes (odometry, ground truth), shown from the start."""
        rr = self.rr
        segment = np.vstack([self.last.get(name, position), position])
        self.last[name] = position
        self.hold(f"world/{name}", rr.LineStrips3D, strips=segment.astype(np.float32))
        self.hold(f"map/{name}", rr.LineStrips2D, strips=_map_xy(segment))

    def _log_estimate(self, estimate: PoseEstimate, resolved: bool) -> None:
        """The back-end's current estimate: the whole path now and then, the part since on every frame.

        The whole path is drawn again when the back-end re-solves (with arrows from the poses as they
        were), and after max(10, n / 50) frames; the frames since are drawn on every frame, so a frame
        costs a bounded share of the path.
        """
        rr = self.rr
        frames = self.frames[: self.count]
        if resolved or self.estimate_drawn == 0 or self.count - self.estimate_drawn >= max(10, self.count // 50):
            poses, found = estimate.stack(frames)
            if resolved and self.estimate is not None:  # it holds every frame before this one
                before, had = self.estimate.stack(frames[:-1])
                self._log_correction(before[:, :3, 3], poses[:-1, :3, 3], had & found[:-1])
            self._log_path(poses[found][:, :3, 3])
            self.estimate_drawn = self.count
            recent = poses[found][-1:, :3, 3]
        else:
            poses, found = estimate.stack(frames[self.estimate_drawn - 1 :])
            recent = poses[found][:, :3, 3]
        self.hold("world/estimate/recent", rr.LineStrips3D, strips=recent.astype(np.float32))
        self.hold("map/estimate/recent", rr.LineStrips2D, strips=_map_xy(recent))
        latest = estimate.latest
        self.hold(
            "map/robot", rr.Arrows2D, origins=_map_xy(latest[None, :3, 3])[0], vectors=_map_xy(latest[None, :3, 0])[0]
        )
        self.estimate = estimate

    def _log_path(self, positions: np.ndarray) -> None:
        """The estimate's whole path."""
        rr = self.rr
        self.stream.log("world/estimate/path", rr.LineStrips3D([positions.astype(np.float32)]))
        self.stream.log("map/estimate/path", rr.LineStrips2D([_map_xy(positions)]))

    def _log_correction(self, before: np.ndarray, after: np.ndarray, known: np.ndarray) -> None:
        """Arrows from where the poses were to where the back-end moved them (those over 1 cm, thinned out)."""
        rr = self.rr
        moved = np.linalg.norm(after - before, axis=1)
        keep = np.flatnonzero(known & (moved >= MIN_CORRECTION))
        if len(keep) > MAX_ARROWS:
            keep = keep[np.linspace(0, len(keep) - 1, MAX_ARROWS).round().astype(int)]
        origins, vectors = before[keep], after[keep] - before[keep]
        colour, radius = [(255, 255, 255, 160)], rr.Radius.ui_points(0.75)
        self.stream.log("world/correction", rr.Arrows3D(origins=origins, vectors=vectors, colors=colour, radii=radius))
        self.stream.log(
            "map/correction",
            rr.Arrows2D(origins=_map_xy(origins), vectors=_map_xy(vectors), colors=colour, radii=radius),
        )

    def _log_loops(self, first: int, candidates: list[dict[str, Any]], final: bool) -> None:
        """Loop candidates ``first``, ``first + 1``, ... decided (or, at the end, changed), each on its own entity."""
        rr = self.rr
        for k in self.labelled:  # labelled on the frame they were decided on, then on hover
            self.stream.log(f"world/loops/{k}", rr.LineStrips3D.from_fields(show_labels=False))
            self.stream.log(f"map/loops/{k}", rr.LineStrips2D.from_fields(show_labels=False))
        self.labelled = []
        for k, row in enumerate(candidates, start=first):
            seen = (str(row.get("outcome")), str(row.get("detail") or ""))
            if k < len(self.logged) and self.logged[k] == seen:
                continue
            if k < len(self.logged):
                self.logged[k] = seen
            else:
                self.logged.append(seen)
            outcome, detail = seen
            label = f"{outcome}: {detail}" if detail else outcome
            colour = outcome_colour(outcome)
            text = f"frame {row.get('frame_from')} -> {row.get('frame_to')}, group {row.get('group_id')}"
            if row.get("from_map"):
                text += " (prior map)"
            self.stream.log("log/loops", rr.TextLog(f"{text}: {label}", level=outcome, color=colour))
            if self.estimate is None or row.get("from_map"):
                continue
            poses, found = self.estimate.stack([int(row["frame_from"]), int(row["frame_to"])])
            if not found.all():
                continue
            ends = poses[:, :3, 3]
            show = not final
            self.stream.log(
                f"world/loops/{k}",
                rr.LineStrips3D([ends.astype(np.float32)], colors=[colour], labels=[label], show_labels=show),
            )
            self.stream.log(
                f"map/loops/{k}",
                rr.LineStrips2D(
                    [_map_xy(ends)],
                    colors=[colour],
                    labels=[label],
                    show_labels=show,
                    radii=rr.Radius.ui_points(1.5),
                    draw_order=3.0,
                ),
            )
            self.labelled.append(k)

    # -- end ------------------------------------------------------------------------------------

    def log_end(self, final: np.ndarray | None, candidates: list[dict[str, Any]]) -> None:
        """One frame after the last: the final trajectory's poses and correction, and the loops decided at the end."""
        if self.last_frame is None:
            return
        self.send()
        index, timestamp = self.last_frame
        self.at(index + 1, timestamp)
        if final is not None and len(final) == self.count:
            if self.estimate is not None:
                before, had = self.estimate.stack(self.frames[: self.count])
                self._log_correction(before[:, :3, 3], final[:, :3, 3], had)
            self._log_path(final[:, :3, 3])
            self.stream.log("world/estimate/recent", self.rr.LineStrips3D([]))
            self.stream.log("map/estimate/recent", self.rr.LineStrips2D([]))
            self.estimate = PoseEstimate(
                int(self.frames[self.count - 1]),
                {int(f): p for f, p in zip(self.frames[: self.count], final, strict=True)},
            )
        self._log_loops(0, candidates, final=True)

    def close(self, finished: bool) -> None:
        """Send what is held back, close every sink; a finished run's file becomes ``run.rrd``."""
        if self.time_kind is not None:
            self.send()
        self.stream.flush()
        self.stream.disconnect()  # writes the file's footer
        if finished and self.saving:
            assert self.run_dir is not None
            os.replace(self.run_dir / PARTIAL_RECORDING, self.run_dir / RECORDING)


def blueprint() -> Any:
    """The layout a newcomer sees: camera and BEV, the map (2-D and 3-D), stage times and the events' log."""
    import rerun.blueprint as rrb

    def shown(start: Any) -> Any:
        return rrb.VisibleTimeRanges(
            [
                rrb.VisibleTimeRange(timeline, start=start, end=rrb.TimeRangeBoundary.cursor_relative())
                for timeline in ("frame", "time")
            ]
        )

    ever, now = shown(rrb.TimeRangeBoundary.infinite()), shown(rrb.TimeRangeBoundary.cursor_relative())
    drawn: dict[str, Any] = {}  # odometry and truth from the start to the cursor; corrections at their frame
    for root in ("map", "world"):
        drawn.update({f"{root}/odometry": ever, f"{root}/ground_truth": ever, f"{root}/correction": now})
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="camera", name="camera"),
                rrb.Spatial2DView(origin="bev", name="BEV, saliency and SGFs", overrides={"bev/sgfs": now}),
                rrb.TensorView(origin="sgf/descriptor", name="SGF descriptor (rings x sectors)"),
                row_shares=[3, 3, 2],
            ),
            rrb.Tabs(
                rrb.Spatial2DView(
                    origin="map", name="map (x right, y up)", overrides={k: v for k, v in drawn.items() if "map" in k}
                ),
                rrb.Spatial3DView(
                    origin="world", name="3-D", overrides={k: v for k, v in drawn.items() if "world" in k}
                ),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="timing", name="stage times (ms)"),
                rrb.TextLogView(origin="log", name="SGFs and loop candidates"),
            ),
            column_shares=[2, 3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline="frame", play_state="following"),  # a saved run opens at its end
    )


class _Recorder:
    """A run's recording, logged on a thread of its own so that the pipeline does not wait for it.

    The pipeline's thread only gathers each keyframe's outputs and queues them; the recording thread
    encodes the images and makes every Rerun call. A full queue (the recording falls behind) makes
    the pipeline wait.
    """

    def __init__(self, run: RunInfo, options: RerunOptions) -> None:
        self.recording = _Recording(run, options)
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
        key = _Keyframe(
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


class RerunObserver:
    """Records a run with Rerun when its config has a ``viz`` node (``sgf-run viz=rerun``)."""

    def __init__(self) -> None:
        self._runs: dict[int, _Recorder] = {}

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
            self._runs[id(run)] = _Recorder(run, options)

    @hookimpl
    def sgf_after_stage(self, run: RunInfo, stage: StageNode, frame: Frame, output: Any, seconds: float) -> None:
        """Keep the stage's output for the end of the frame."""
        recorder = self._runs.get(id(run))
        if recorder is not None:
            recorder.stage_done(stage.kind, output, seconds)

    @hookimpl
    def sgf_frame_end(self, run: RunInfo, frame: Frame, seconds: float) -> None:
        """Hand the keyframe to the recording."""
        recorder = self._runs.get(id(run))
        if recorder is not None:
            recorder.frame_done(frame, run.context.artifacts if run.context is not None else None)

    @hookimpl
    def sgf_on_error(self, run: RunInfo, stage: StageNode, frame: Frame | None, error: BaseException) -> None:
        """Close the recording as it is (``run.partial.rrd``)."""
        recorder = self._runs.pop(id(run), None)
        if recorder is not None:
            recorder.finish(None)

    @hookimpl
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        """Log the end of the run and close the recording as ``run.rrd``."""
        recorder = self._runs.pop(id(run), None)
        if recorder is not None:
            recorder.finish(run)


_OBSERVER = RerunObserver()

# pluggy registers this module; the observer's hook implementations are its module-level names.
sgf_observer_options = _OBSERVER.sgf_observer_options
sgf_run_start = _OBSERVER.sgf_run_start
sgf_after_stage = _OBSERVER.sgf_after_stage
sgf_frame_end = _OBSERVER.sgf_frame_end
sgf_on_error = _OBSERVER.sgf_on_error
sgf_run_end = _OBSERVER.sgf_run_end
