"""Candidate SGF regions of one frame (paper Sec. III-B, step 1): blobs of the binarised saliency."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from sgf_pipeline.types import Bev, SaliencyMap
from sgf_plugins.sgf.hu import hu_moments


@dataclass(frozen=True)
class Region:
    """A candidate SGF region of one frame: a connected component of the binarised saliency."""

    pixels: np.ndarray
    saliency: float
    hu: np.ndarray
    touches_border: bool
    instance_id: int | None


def border_band(valid: np.ndarray, margin: int) -> np.ndarray:
    """Pixels within ``margin`` px of the image border or of the BEV's invalid area (outside the camera's view)."""
    h, w = valid.shape
    outside = ~valid.astype(bool)
    band = np.zeros((h, w), dtype=bool)
    band[:margin, :] = band[-margin:, :] = True
    band[:, :margin] = band[:, -margin:] = True
    if outside.any():
        size = 2 * margin + 1
        near = cv2.dilate(outside.astype(np.uint8), np.ones((size, size), np.uint8)) > 0
        band |= near
    return band


def majority_instance(ids: np.ndarray, min_fraction: float) -> int | None:
    """The most frequent non-zero instance id of a region when markings cover ``min_fraction`` of it, else None."""
    if ids.size == 0:
        return None
    marked = ids[ids > 0]
    if marked.size == 0 or marked.size < min_fraction * ids.size:
        return None
    values, counts = np.unique(marked, return_counts=True)
    return int(values[int(np.argmax(counts))])


def find_regions(
    bev: Bev,
    saliency: SaliencyMap,
    *,
    threshold: float,
    min_area: int,
    closing: int,
    merge_distance: float,
    border_margin: int,
    border_reach: Literal["region", "merge"],
    truth_min_fraction: float,
) -> tuple[np.ndarray, list[Region], int]:
    """Label image, candidate regions (label k is ``regions[k - 1]``) and how many components were below ``min_area``.

    The saliency is binarised at ``threshold`` inside the camera's view, optionally closed with a
    disk of radius ``closing`` px; components closer than ``merge_distance`` (m) share a label.
    """
    raw = np.asarray(saliency.probability)
    if raw.dtype != bool and not np.issubdtype(raw.dtype, np.floating):
        raise ValueError(f"saliency must be a float map in [0, 1] (or a boolean mask), got dtype {raw.dtype}")
    prob = np.nan_to_num(raw.astype(np.float32), nan=0.0)
    valid = np.asarray(bev.valid, dtype=bool)
    if prob.shape != valid.shape:
        raise ValueError(f"saliency map {prob.shape} and BEV valid mask {valid.shape} differ in size")
    if prob.ndim != 2:
        raise ValueError(f"saliency must be an (H, W) map, got shape {prob.shape}")
    mask = (prob >= threshold) & valid
    if closing > 0:
        size = 2 * closing + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        mask = (cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel) > 0) & valid
    merge: np.ndarray | None = None  # the disk of half merge_distance that joins regions into one SGF
    if merge_distance > 0.0:
        # Label the mask dilated by half the merge distance: regions with a smaller gap share a label.
        radius = max(1, round(0.5 * merge_distance / bev.grid.resolution))
        merge = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        grown = cv2.dilate(mask.astype(np.uint8), merge)
        count, grown_labels = cv2.connectedComponents(grown, connectivity=8)
        grown_labels = np.where(mask, grown_labels, 0).astype(np.int32)
        areas = np.bincount(grown_labels.ravel(), minlength=count)
        stats = np.zeros((count, 5), dtype=np.int64)
        stats[:, cv2.CC_STAT_AREA] = areas
        stats[0, cv2.CC_STAT_AREA] = 0
        labels = grown_labels
    else:
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area) + 1
    too_small = count - 1 - len(keep)
    remap = np.zeros(count, dtype=np.int32)
    remap[keep] = np.arange(1, len(keep) + 1)
    labels = remap[labels]
    if len(keep) == 0:
        return labels, [], too_small
    band = border_band(valid, border_margin)
    if border_reach == "merge" and merge is not None:
        band = cv2.dilate(band.astype(np.uint8), merge) > 0
    flat = np.flatnonzero(labels)
    order = np.argsort(labels.flat[flat], kind="stable")
    flat = flat[order]
    starts = np.searchsorted(labels.flat[flat], np.arange(1, len(keep) + 1))
    ids = bev.instance_ids
    regions = []
    for idx in np.split(flat, starts[1:]):
        v, u = np.divmod(idx, labels.shape[1])
        pixels = np.stack([u, v], axis=1).astype(np.int32)
        truth = None
        if ids is not None:
            truth = majority_instance(np.asarray(ids).flat[idx], truth_min_fraction)
        regions.append(
            Region(
                pixels=pixels,
                saliency=float(prob.flat[idx].mean()),
                hu=hu_moments(pixels),
                touches_border=bool(band.flat[idx].any()),
                instance_id=truth,
            )
        )
    return labels, regions, too_small
