"""Training data from the synthetic campus: BEVs made by the project's own enhance + IPM stages, with exact masks.

Each world (a dataset variant with its seed and overrides) is streamed through the pipeline
``dataset -> enhance -> ipm`` with keyframes every ``keyframe_distance`` metres; every BEV with a
marking in view becomes a sample (mask: ``Bev.instance_ids > 0``, warped with the image), and a
fraction of the BEVs without one too, so that a network also learns to answer "nothing here".
The samples of all worlds go into one SOD folder; its splits keep each pass over a marking in
one split, and every sample showing a held-out design goes to ``test_heldout``.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline import Pipeline
from sgf_pipeline.errors import ConfigError
from sgf_pipeline.truth import SequenceTruth
from sgf_pipeline.types import Bev
from sgf_plugins.saliency.data import SplitSpec, WriteReport, write_sod_folder


def samples_from_bevs(
    bevs: Iterable[Bev],
    truth: SequenceTruth | None,
    sequence: str,
    blank_group_frames: int = 50,
    min_pixels: int = 20,
) -> Iterator[tuple[np.ndarray, np.ndarray, dict[str, Any]]]:
    """``(bev_rgb, mask, meta)`` samples from BEVs that carry ground-truth marking instances (a synthetic world).

    The mask is every pixel of a marking instance (``Bev.instance_ids > 0``); ``meta`` holds the
    frame, the designs and categories (standard/custom) of the instances with at least
    ``min_pixels`` pixels in view, the validity mask, and a ``group``: the sequence, instance and
    pass of the first marking in view (so that the frames of one pass never straddle splits), or a
    block of ``blank_group_frames`` frames when none is. BEVs without instance ids are skipped.
    """
    for bev in bevs:
        if bev.instance_ids is None:
            continue
        found_ids, counts = np.unique(bev.instance_ids[bev.instance_ids > 0], return_counts=True)
        ids = [int(i) for i, c in zip(found_ids, counts, strict=True) if c >= min_pixels]
        markings = [truth.markings[i] for i in ids if truth is not None and i in truth.markings]
        group = f"{sequence}:blank:{bev.frame_index // blank_group_frames}"
        for i in ids:
            found = truth.pass_of(i, bev.frame_index) if truth is not None else None
            if found is not None:
                group = f"{sequence}:{i}:{found.number}"
                break
        else:
            if ids:
                group = f"{sequence}:{ids[0]}:{bev.frame_index // blank_group_frames}"
        meta = {
            "name": f"{sequence}_{bev.frame_index:06d}",
            "sequence": sequence,
            "frame": bev.frame_index,
            "instances": ids,
            "designs": sorted({m.design for m in markings}),
            "categories": sorted({m.category for m in markings}),
            "group": group,
            "valid": bev.valid,
        }
        yield bev.image, bev.instance_ids > 0, meta


@dataclass(frozen=True)
class ObjectMaskParams:
    """How a marking's paint becomes a salient-object mask (see :func:`object_mask`)."""

    close_px: int = 7
    ring_px: int = 6
    min_contrast: float = 12.0


def object_mask(rgb: np.ndarray, paint: np.ndarray, valid: np.ndarray | None, p: ObjectMaskParams) -> np.ndarray:
    """The salient-object mask of a BEV: each visible marking, its strokes closed into one object.

    SOD annotates objects, not strokes: the paint of a marking is closed with a ``close_px`` disk
    (14 cm at 2 cm/px) so that the glyphs of painted text or the outline of a sign form one region.
    A marking the camera cannot see -- at night beyond the headlight, washed out far away -- is
    not salient: a region whose paint differs from a ``ring_px`` band around it by less than
    ``min_contrast`` (Lab distance, 8-bit units) is left out of the mask.
    """
    paint = np.asarray(paint, dtype=bool)
    if not paint.any():
        return paint
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (p.close_px, p.close_px))
    closed = cv2.morphologyEx(paint.astype(np.uint8), cv2.MORPH_CLOSE, kernel) > 0
    lab = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2LAB).astype(np.float32)
    seen = np.ones_like(paint) if valid is None else np.asarray(valid, dtype=bool)
    ring_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * p.ring_px + 1, 2 * p.ring_px + 1))
    count, labels = cv2.connectedComponents(closed.astype(np.uint8))
    out = np.zeros_like(paint)
    for k in range(1, count):
        region = labels == k
        ring = (cv2.dilate(region.astype(np.uint8), ring_kernel) > 0) & ~closed & seen
        inside = region & paint & seen
        if not inside.any():
            continue
        if ring.sum() >= 10:
            contrast = float(np.linalg.norm(lab[inside].mean(axis=0) - lab[ring].mean(axis=0)))
            if contrast < p.min_contrast:
                continue
        out |= region
    return out & seen


@dataclass(frozen=True)
class WorldSpec:
    """One world to draw samples from: a dataset variant, its seed and scale, parameter overrides."""

    preset: str
    seed: int
    scale: float = 1.0
    overrides: Mapping[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """A short unique name for sample names and groups."""
        night = "_night" if self.overrides.get("night") else ""
        return f"{self.preset}{night}_s{self.seed}"


def world_bevs(
    spec: WorldSpec,
    keyframe_distance: float,
    enhance: Mapping[str, Any],
    ipm: Mapping[str, Any],
    blank_fraction: float,
    rng: np.random.Generator,
    mask: ObjectMaskParams | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray, dict[str, Any]]]:
    """Samples ``(bev_rgb, mask, meta)`` of one world, through the project's own stages."""
    cfg = {
        "pipeline": ["dataset", "enhance", "ipm"],
        "dataset": {"name": spec.preset, "seed": spec.seed, "scale": spec.scale, **dict(spec.overrides)},
        "enhance": dict(enhance),
        "ipm": dict(ipm),
        "run": {"progress": False, "plots": False, "keyframe_distance": keyframe_distance},
    }
    pipeline = Pipeline.from_config(cfg)
    pipeline.begin()
    if pipeline.context.truth is None:
        raise ConfigError(f"dataset {spec.preset} has no ground-truth markings: it cannot make training masks")
    bevs = (pipeline.process(frame).outputs["bev"] for frame in pipeline.frames())
    for rgb, paint, meta in samples_from_bevs(bevs, pipeline.context.truth, spec.label):
        salient = object_mask(rgb, paint, meta.get("valid"), mask or ObjectMaskParams())
        if not salient.any() and rng.random() >= blank_fraction:
            continue
        meta["world"] = spec.label
        meta["night"] = bool(spec.overrides.get("night", False))
        yield rgb, salient, meta


def generate(
    root: str | Path,
    worlds: Sequence[WorldSpec],
    heldout_designs: Sequence[str],
    keyframe_distance: float = 0.6,
    enhance: Mapping[str, Any] | None = None,
    ipm: Mapping[str, Any] | None = None,
    blank_fraction: float = 0.15,
    split_seed: int = 0,
    val_fraction: float = 0.1,
    test_fraction: float = 0.1,
    progress: bool = True,
    mask: ObjectMaskParams | None = None,
) -> WriteReport:
    """Write one SOD folder with the BEV samples of every world and its splits."""
    out = Path(root)
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out} is not empty; choose a new folder for the training data")
    enhance = dict(enhance or {"name": "none"})
    ipm = dict(ipm or {"name": "mc"})
    rng = np.random.default_rng(split_seed)

    def samples() -> Iterator[tuple[np.ndarray, np.ndarray, dict[str, Any]]]:
        from tqdm import tqdm

        for spec in tqdm(worlds, desc="worlds", unit="world", disable=not progress):
            yield from world_bevs(spec, keyframe_distance, enhance, ipm, blank_fraction, rng, mask)

    spec = SplitSpec(
        seed=split_seed,
        val_fraction=val_fraction,
        test_fraction=test_fraction,
        heldout_designs=tuple(heldout_designs),
        group_key="group",
    )
    return write_sod_folder(samples(), out, spec)
