"""Network inputs and targets of the saliency networks: RGB images, normalised input tensors, resized masks."""

from __future__ import annotations

import cv2
import numpy as np

#: Channel statistics used to normalise network inputs (ImageNet's, as in the reference implementations).
MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def as_rgb(image: np.ndarray) -> np.ndarray:
    """An RGB image ``(H, W, 3)``; a grey one (``(H, W)`` or ``(H, W, 1)``: KITTI's image_0, EuRoC) in all three."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB or (H, W) grey image, got shape {image.shape}")
    return image


def normalize_image(rgb: np.ndarray, size: int) -> np.ndarray:
    """Network input ``(3, size, size)`` float32: area-resized, scaled to [0, 1], normalised by channel."""
    if rgb.shape[0] != size or rgb.shape[1] != size:
        rgb = cv2.resize(rgb, (size, size), interpolation=cv2.INTER_AREA)
    x = (rgb.astype(np.float32) / 255.0 - MEAN) / STD
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def resize_mask(mask: np.ndarray, size: int) -> np.ndarray:
    """A mask (uint8 or float) as float32 in [0, 1] at ``size x size`` (area-averaged)."""
    m = mask.astype(np.float32) / 255.0 if mask.dtype == np.uint8 else mask.astype(np.float32)
    if m.shape[0] != size or m.shape[1] != size:
        m = np.asarray(cv2.resize(m, (size, size), interpolation=cv2.INTER_AREA), np.float32)
    return np.clip(m, 0.0, 1.0)
