"""The Rerun recording of one run: its stream and sinks, and what it logs of each keyframe and of the end."""

from __future__ import annotations

import logging
import os
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline import ConfigError
from sgf_pipeline.runner import RunInfo
from sgf_pipeline.types import (
    Bev,
    CameraImage,
    GroupAssignments,
    LoopConstraints,
    PoseEstimate,
    SaliencyMap,
    SgfDescriptors,
    SgfDetections,
)
from sgf_plugins.viz.figures import group_colour
from sgf_plugins.viz.rerun.blueprint import blueprint
from sgf_plugins.viz.rerun.drawing import TRAJECTORY_COLOURS, jpeg, map_xy, nanoseconds, outcome_colour, outline
from sgf_plugins.viz.rerun.options import PARTIAL_RECORDING, RECORDING, RerunOptions

log = logging.getLogger("sgf_pipeline")

APPLICATION_ID = "sgf-pipeline"
#: Timestamps from this value on are Unix time, shown as dates (after September 2001).
UNIX_TIME_FROM = 1e9
#: Keyframes whose rows are held back and sent together (a live viewer lags by as many).
SEND_FRAMES = 10
#: Correction arrows drawn at most, and the smallest correction drawn (m).
MAX_ARROWS = 60
MIN_CORRECTION = 0.01


@dataclass(frozen=True)
class Keyframe:
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


class Rows:
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


class Recording:
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
        self.rows: dict[str, Rows] = {}
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
        for name, colour in TRAJECTORY_COLOURS.items():
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
            rr.Arrows2D.from_fields(colors=[TRAJECTORY_COLOURS["estimate"]], radii=rr.Radius.ui_points(2.5)),
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
            rows = self.rows[path] = Rows(archetype)
        rows.add(*self.now, **fields)

    def send(self) -> None:
        """Send every row held back."""
        assert self.time_kind is not None
        for path, rows in self.rows.items():
            rows.send(self.rr, self.stream, path, self.time_kind)
        self.held = 0

    # -- per frame ----------------------------------------------------------------------------

    def log_frame(self, key: Keyframe) -> None:
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
            self.hold("camera/image", rr.EncodedImage, blob=jpeg(np.asarray(image)), media_type="image/jpeg")
        bev = outputs.get(Bev)
        if bev is not None:
            self.hold("bev/image", rr.EncodedImage, blob=jpeg(bev.image), media_type="image/jpeg")
        saliency = outputs.get(SaliencyMap)
        if saliency is not None:
            heat = cv2.applyColorMap(cv2.convertScaleAbs(saliency.probability, alpha=255.0), cv2.COLORMAP_INFERNO)
            self.hold("bev/saliency", rr.EncodedImage, blob=jpeg(heat, bgr=True))
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
        self.hold(f"map/{name}", rr.LineStrips2D, strips=map_xy(segment))

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
        self.hold("map/estimate/recent", rr.LineStrips2D, strips=map_xy(recent))
        latest = estimate.latest
        self.hold(
            "map/robot", rr.Arrows2D, origins=map_xy(latest[None, :3, 3])[0], vectors=map_xy(latest[None, :3, 0])[0]
        )
        self.estimate = estimate

    def _log_path(self, positions: np.ndarray) -> None:
        """The estimate's whole path."""
        rr = self.rr
        self.stream.log("world/estimate/path", rr.LineStrips3D([positions.astype(np.float32)]))
        self.stream.log("map/estimate/path", rr.LineStrips2D([map_xy(positions)]))

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
            rr.Arrows2D(origins=map_xy(origins), vectors=map_xy(vectors), colors=colour, radii=radius),
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
                    [map_xy(ends)],
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
