"""Image enhancement before IPM (paper Sec. IV-C): none, or CLAHE for night sequences."""

from __future__ import annotations

import cv2
import numpy as np
from pydantic import Field

from sgf_pipeline import DataError, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.types import CameraImage, Frame


def as_rgb(image: np.ndarray) -> np.ndarray:
    """An (H, W, 3) uint8 view of a grey or RGB image."""
    if image.dtype != np.uint8:
        raise DataError(f"camera images must be uint8 (grey or RGB), got dtype {image.dtype}")
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return np.repeat(image, 3, axis=2)
    raise DataError(f"expected an (H, W) or (H, W, 3) image, got shape {image.shape}")


class NoEnhancement(Stage):
    """Pass the camera image through unchanged (grey images become 3-channel)."""

    kind = "enhance"
    name = "none"
    output = "image"
    cache_outputs = False  # the camera image: cheaper to read again than to keep

    def process(self, frame: Frame) -> CameraImage:
        """The frame's image as RGB."""
        return CameraImage(as_rgb(frame.image), frame.index)


class ClaheParams(StageParams):
    """Contrast Limited Adaptive Histogram Equalization on the lightness channel."""

    clip_limit: float = Field(2.0, gt=0.0, description="CLAHE contrast limit")
    tiles: int = Field(8, ge=1, le=64, description="tiles per image side")
    max_brightness: float | None = Field(
        None,
        gt=0.0,
        le=1.0,
        description="enhance only images whose mean brightness (0-1) is below this (night); null = every image",
    )


class ClaheEnhancement(Stage):
    """CLAHE on the L channel of Lab, for dark (night) images lit by the robot's LED.

    With ``max_brightness`` set, only images darker than it are enhanced, so one configuration
    serves day and night sequences.
    """

    kind = "enhance"
    name = "clahe"
    output = "image"
    Params = ClaheParams
    cache_outputs = False  # an image: cheaper to equalise again than to keep

    def __init__(self, params: ClaheParams) -> None:
        super().__init__(params)
        self.params: ClaheParams = params
        self._clahe = cv2.createCLAHE(clipLimit=params.clip_limit, tileGridSize=(params.tiles, params.tiles))

    def process(self, frame: Frame) -> CameraImage:
        """The frame's image with equalised local contrast."""
        image = frame.image
        limit = self.params.max_brightness
        if limit is not None and image.dtype == np.uint8 and float(image[::4, ::4].mean()) / 255.0 >= limit:
            return CameraImage(as_rgb(image), frame.index)
        if image.ndim == 2 and image.dtype == np.uint8:
            return CameraImage(as_rgb(self._clahe.apply(image)), frame.index)
        lab = cv2.cvtColor(as_rgb(image), cv2.COLOR_RGB2LAB)
        lab[:, :, 0] = self._clahe.apply(np.ascontiguousarray(lab[:, :, 0]))
        return CameraImage(cv2.cvtColor(lab, cv2.COLOR_LAB2RGB), frame.index)


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the enhancement variants."""
    registry.add(NoEnhancement)
    registry.add(ClaheEnhancement)
