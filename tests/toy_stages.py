"""Small in-process stages for testing the runner (test helpers, never registered by the project)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
from pydantic import Field

from sgf_pipeline import Dataset, Previous, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.context import RunContext
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.trajectory import Trajectory
from sgf_pipeline.types import Bev, CameraImage, Frame, PathAhead, PoseEstimate

CALIBRATION = Calibration.from_mounting(
    Intrinsics(fx=100.0, fy=100.0, cx=40.0, cy=30.0, width=80, height=60), height=0.6, tilt=0.4
)


class FigureEightParams(StageParams):
    frames: int = Field(30, ge=1, description="number of frames")
    step: float = Field(0.2, gt=0.0, description="metres between frames")


class FigureEight(Dataset):
    """A robot driving a figure eight; odometry scaled by 1.05; images encode the frame index."""

    name = "figure_eight"
    Params = FigureEightParams

    def __len__(self) -> int:
        return self.params.frames

    def frames(self) -> Iterator[Frame]:
        n = self.params.frames
        for i in range(n):
            t = 2.0 * math.pi * i / max(n, 2)
            x, y = 10.0 * math.sin(t), 5.0 * math.sin(2.0 * t)
            yaw = math.atan2(10.0 * math.cos(2.0 * t), 10.0 * math.cos(t) + 1e-9)
            gt = pose_from_xy_yaw(x, y, yaw)
            odo = pose_from_xy_yaw(1.05 * x, 1.05 * y, yaw)
            yield Frame(i, 0.1 * i, lambda i=i: np.full((60, 80), i % 256, np.uint8), odo, CALIBRATION, ground_truth=gt)


class Brightness(Stage):
    """Mean intensity of the image (a real computation on the image)."""

    kind = "measure"
    name = "brightness"
    output = "brightness"

    def process(self, image: CameraImage) -> float:
        return float(image.pixels.mean())


class CountParams(StageParams):
    start: int = Field(0, description="first value")


class Counter(Stage):
    """Counts frames through a feedback edge: output = previous output + 1."""

    kind = "counter"
    name = "feedback"
    output = "count"
    Params = CountParams

    def process(self, frame: Frame, count: Previous[int]) -> int:
        return self.params.start if count is None else count + 1


class EveryOther(Stage):
    """Produces a value on even frames only (an optional output)."""

    kind = "gate"
    name = "even"
    output = "gated"

    def process(self, frame: Frame) -> int | None:
        return frame.index if frame.index % 2 == 0 else None


class NeedsGated(Stage):
    """Runs only when `gated` exists (its input is not optional)."""

    kind = "consumer"
    name = "strict"
    output = "consumed"

    def process(self, gated: int) -> int:
        return gated * 10


class NeedsBev(Stage):
    """Expects a Bev: wiring it to `image` is a type error."""

    kind = "bevuser"
    name = "needs_bev"
    output = "bev_mean"

    def process(self, bev: Bev) -> float:
        return float(bev.image.mean())


class OdometryBackend(Stage):
    """A back-end that trusts odometry: publishes the estimate and the `sgf` trajectory."""

    kind = "backend"
    name = "trust_odometry"
    output = "estimate"

    def begin(self, context: RunContext) -> None:
        self.poses: dict[int, np.ndarray] = {}
        self.stamps: dict[int, float] = {}

    def process(self, frame: Frame) -> PoseEstimate:
        self.poses[frame.index] = frame.odometry
        self.stamps[frame.index] = frame.timestamp
        return PoseEstimate(frame.index, self.poses)

    def finalize(self, context: RunContext) -> None:
        keys = sorted(self.poses)
        context.trajectories["sgf"] = Trajectory(
            np.array([self.stamps[k] for k in keys]), np.stack([self.poses[k] for k in keys])
        )
        context.metrics["backend"] = {"nodes": len(keys)}


class Exploding(Stage):
    """Raises on frame 3."""

    kind = "explode"
    name = "on_three"
    output = "boom"

    def process(self, frame: Frame) -> int:
        if frame.index == 3:
            raise RuntimeError("kaboom")
        return 0


class DuplicateImage(Stage):
    """A second producer of `image` (for the two-producers error)."""

    kind = "other"
    name = "dup"
    output = "image"

    def process(self, frame: Frame) -> CameraImage:
        return CameraImage(frame.image, frame.index)


class GateFromConsumer(Stage):
    """A gate that consumes the consumer's output: with consumer=strict it closes a cycle."""

    kind = "gate"
    name = "loops"
    output = "gated"

    def process(self, frame: Frame, consumed: int) -> int:
        return consumed


class ReadAheadParams(StageParams):
    distance: float = Field(2.0, gt=0.0, description="metres of path the stage needs after a frame")


class ReadAhead(Stage):
    """Returns the path the runner read ahead of each frame."""

    kind = "ahead"
    name = "path"
    output = "path"
    Params = ReadAheadParams

    @property
    def read_ahead(self) -> float:
        assert isinstance(self.params, ReadAheadParams)
        return self.params.distance

    def process(self, frame: Frame) -> PathAhead | None:
        return frame.path_ahead


class ToyPlugin:
    """Registers the toy stages."""

    @hookimpl
    def sgf_register_stages(self, registry: StageRegistry) -> None:
        for cls in (
            FigureEight,
            Brightness,
            Counter,
            EveryOther,
            NeedsGated,
            NeedsBev,
            OdometryBackend,
            Exploding,
            DuplicateImage,
            GateFromConsumer,
            ReadAhead,
        ):
            registry.add(cls)
