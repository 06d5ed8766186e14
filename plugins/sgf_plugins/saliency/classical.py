"""A learning-free detector of painted markings on a metric BEV: morphological top-hat and an adaptive threshold.

Paint is brighter than the ground around it in at least one colour channel (white, yellow, red and
blue paints all are), and markings are narrower than a few decimetres in at least one direction.
The white top-hat of the per-pixel channel maximum (image minus its opening by a disc a little wider
than the markings) keeps exactly such narrow bright structures and removes the slowly varying
ground. Its threshold adapts to each BEV: a number of robust standard deviations (1.4826 x MAD) of
the top-hat over the seen ground, and never below a minimum contrast. Small components are removed,
and nothing outside ``Bev.valid`` (nor on its border) is salient.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

from sgf_plugins.saliency.preprocess import as_rgb


def _odd(n: float) -> int:
    k = max(3, round(n))
    return k if k % 2 else k + 1


def marking_saliency(
    rgb: np.ndarray,
    valid: np.ndarray | None,
    resolution: float,
    kernel_m: float = 0.8,
    polarity: Literal["bright", "dark", "both"] = "bright",
    min_contrast: float = 12.0,
    k_sigma: float = 4.0,
    min_area_m2: float = 0.01,
    smooth_px: float = 1.0,
) -> np.ndarray:
    """Saliency ``(H, W)`` float32 in [0, 1] of painted markings in an RGB (or grey) BEV of ``resolution`` m/px."""
    rgb = as_rgb(rgb)
    h, w = rgb.shape[:2]
    seen = np.ones((h, w), bool) if valid is None else np.asarray(valid, dtype=bool)
    if not seen.any():
        return np.zeros((h, w), np.float32)
    # 1. channel extremes; unseen pixels take the median of the seen ground so no edge appears there
    image = np.asarray(rgb, dtype=np.uint8)
    planes = []
    if polarity in ("bright", "both"):
        planes.append(image.max(axis=2))
    if polarity in ("dark", "both"):
        planes.append(255 - image.min(axis=2))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (_odd(kernel_m / resolution),) * 2)
    response = np.zeros((h, w), np.float32)
    for plane in planes:
        plane = plane.copy()
        plane[~seen] = np.uint8(np.median(plane[seen]))
        if smooth_px > 0:
            plane = cv2.GaussianBlur(plane, (0, 0), smooth_px)
        # 2. white top-hat: structures narrower than the kernel and brighter than their surroundings
        tophat = cv2.morphologyEx(plane, cv2.MORPH_TOPHAT, kernel).astype(np.float32)
        response = np.maximum(response, tophat)
    # 3. adaptive threshold: k robust sigmas of the top-hat over the seen ground, at least min_contrast
    inner = cv2.erode(seen.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    values = response[inner] if inner.any() else response[seen]
    median = float(np.median(values))
    sigma = 1.4826 * float(np.median(np.abs(values - median)))
    threshold = max(min_contrast, median + k_sigma * sigma)
    binary = (response > threshold) & inner
    # 4. clean: drop specks and components smaller than min_area_m2
    binary = cv2.morphologyEx(binary.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    min_area = min_area_m2 / (resolution * resolution)
    keep = np.zeros(count, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    kept = keep[labels]
    support = cv2.dilate(kept.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & inner
    # 5. soft probability: 0 at half the threshold, 1 at 1.5 times it, only on kept components
    soft = np.clip((response - 0.5 * threshold) / threshold, 0.0, 1.0)
    return np.where(support, soft, 0.0).astype(np.float32)
