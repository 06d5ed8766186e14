"""Lens undistortion with precomputed remap tables: the adapters hand undistorted pinhole images on.

Every dataset adapter undistorts its images when the calibration has a distortion model
(``dataset.undistort=true``, the default), so that IPM and everything after it can assume an
ideal pinhole camera. The undistorted image keeps the size and the camera matrix K of the
original (OpenCV's ``newCameraMatrix = K``): the centre of the image keeps its scale, the
corners of a strongly distorted lens are cropped or left black. The frames then carry a
calibration with ``distortion.model == "none"``.
"""

from __future__ import annotations

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration, Distortion
from sgf_pipeline.errors import DataError


class Undistorter:
    """Undo a calibration's lens distortion: one ``cv2.remap`` per image with maps built once."""

    def __init__(self, calibration: Calibration, interpolation: int = cv2.INTER_LINEAR) -> None:
        self.source = calibration
        intr = calibration.intrinsics
        self.size = (intr.width, intr.height)
        self.interpolation = interpolation
        self.calibration = calibration.model_copy(update={"distortion": Distortion()})
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        dist = calibration.distortion
        if dist.is_identity:
            return
        k = intr.matrix
        coeffs = np.asarray(dist.coefficients, dtype=np.float64)
        if dist.model == "radtan":
            self._maps = cv2.initUndistortRectifyMap(k, coeffs, None, k, self.size, cv2.CV_16SC2)
        elif dist.model == "equidistant":
            self._maps = cv2.fisheye.initUndistortRectifyMap(
                k, coeffs.reshape(4, 1), np.eye(3), k, self.size, cv2.CV_16SC2
            )
        else:  # pragma: no cover - Distortion validates the model
            raise DataError(f"unknown distortion model {dist.model!r}")

    @property
    def active(self) -> bool:
        """Whether there is any distortion to undo."""
        return self._maps is not None

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The undistorted image (the same array when the lens has no distortion)."""
        if self._maps is None:
            return image
        height, width = image.shape[:2]
        if (width, height) != self.size:
            raise DataError(
                f"image of {width}x{height} px but the calibration is for {self.size[0]}x{self.size[1]} px; "
                "use the calibration of this camera and resolution"
            )
        return cv2.remap(image, self._maps[0], self._maps[1], self.interpolation, borderMode=cv2.BORDER_CONSTANT)
