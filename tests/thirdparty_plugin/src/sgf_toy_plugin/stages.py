"""Stages of the throwaway plugin."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import Field

from sgf_pipeline import Dataset, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.types import CameraImage, Frame


class GammaParams(StageParams):
    gamma: float = Field(1.0, gt=0.0, description="exponent applied to intensities in [0, 1]")


class GammaEnhancement(Stage):
    """Gamma correction of the camera image."""

    kind = "enhance"
    name = "gamma"
    output = "image"
    Params = GammaParams

    def process(self, frame: Frame) -> CameraImage:
        img = frame.image.astype(np.float64) / 255.0
        out = np.clip(255.0 * img**self.params.gamma + 0.5, 0, 255).astype(np.uint8)
        if out.ndim == 2:
            out = np.repeat(out[:, :, None], 3, axis=2)
        return CameraImage(out, frame.index)


class CircleParams(StageParams):
    frames: int = Field(40, ge=3)
    radius: float = Field(5.0, gt=0.0)
    seed: int = 0
    mark_file: str = Field("", description="a file created once frame 20 is read: a test's sign that frames flow")


class ToyCircle(Dataset):
    """A robot driving a circle at 10 Hz; odometry has a yaw bias, ground truth is exact."""

    name = "toy_circle"
    Params = CircleParams

    def __init__(self, params: CircleParams) -> None:
        super().__init__(params)
        self.calibration = Calibration.from_mounting(
            Intrinsics(fx=120.0, fy=120.0, cx=80.0, cy=60.0, width=160, height=120), height=0.6, tilt=0.4
        )

    def __len__(self) -> int:
        return self.params.frames

    def frames(self):  # type: ignore[no-untyped-def]
        p = self.params
        for i in range(p.frames):
            angle = 2.0 * math.pi * i / p.frames
            x, y = p.radius * math.sin(angle), p.radius * (1.0 - math.cos(angle))
            gt = pose_from_xy_yaw(x, y, angle)
            odo = pose_from_xy_yaw(x * 1.02, y * 1.02, angle * 1.01)
            if p.mark_file and i == 20:
                Path(p.mark_file).touch()
            rng = np.random.default_rng(p.seed * 100003 + i)
            yield Frame(
                i,
                0.1 * i,
                lambda rng=rng: rng.integers(0, 128, (120, 160), dtype=np.uint8),
                odo,
                self.calibration,
                imu_roll_pitch=(0.0, 0.0),
                ground_truth=gt,
            )


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    registry.add(GammaEnhancement)
    registry.add(ToyCircle)
