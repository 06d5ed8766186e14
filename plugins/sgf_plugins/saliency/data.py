"""Training data for the saliency networks: a DUTS-style SOD folder, its splits, its writer, augmentation.

The writer (:func:`write_sod_folder`) fills a folder from any source of BEV images with masks (the
synthetic world, a real data set); the folder is then what ``sgf-train`` and ``sgf-sod-eval`` read.

Layout of a SOD folder (version 1)::

    images/<name>.png     BEV (or any) RGB image, PNG or JPEG
    masks/<name>.png      8-bit mask, > 128 = salient (soft masks are binarised by the metrics)
    valid/<name>.png      optional: 8-bit camera-visibility mask of a BEV (> 0 = seen)
    meta.jsonl            optional: one JSON object per line, {"name": ..., "designs": [...], "group": ...}
    splits.json           optional: {"format": "sgf-sod-splits", "spec": {...}, "splits": {"train": [...], ...}}

``images/`` and ``masks/`` alone are a DUTS-style folder (DUTS, ECSSD, ... need only be renamed).
Split names: ``train``, ``val``, ``test`` (random by seed, optionally by group) and ``test_heldout``
(every sample showing a held-out marking design, never seen in training).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline.errors import DataError
from sgf_pipeline.io import atomic_path, atomic_write_json, atomic_write_text
from sgf_pipeline.types import Bev, SequenceTruth

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
SPLITS_FORMAT = "sgf-sod-splits"
SPLIT_NAMES = ("train", "val", "test", "test_heldout")
#: Channel statistics used to normalise network inputs (ImageNet's, as in the reference implementations).
MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


@dataclass(frozen=True)
class SplitSpec:
    """How to split a folder: random by seed (whole groups at a time), held-out designs apart."""

    seed: int = 0
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    heldout_designs: tuple[str, ...] = ()
    group_key: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (as saved in ``splits.json``)."""
        return {
            "seed": self.seed,
            "val_fraction": self.val_fraction,
            "test_fraction": self.test_fraction,
            "heldout_designs": list(self.heldout_designs),
            "group_key": self.group_key,
        }


def make_splits(names: Sequence[str], metas: Mapping[str, Mapping[str, Any]], spec: SplitSpec) -> dict[str, list[str]]:
    """Assign every sample to train, val, test or test_heldout.

    A sample whose ``meta["designs"]`` contains a held-out design goes to ``test_heldout``. The others
    are grouped by ``meta[spec.group_key]`` (each sample alone when the key is unset or absent, so
    consecutive frames of one pass can be kept together), the groups shuffled with ``spec.seed``,
    and filled into test, then val, until each holds its fraction of those samples; the rest is train.
    """
    if not 0 <= spec.val_fraction < 1 or not 0 <= spec.test_fraction < 1 or spec.val_fraction + spec.test_fraction >= 1:
        raise ValueError(
            f"val_fraction {spec.val_fraction} and test_fraction {spec.test_fraction} must leave a train set"
        )
    held = set(spec.heldout_designs)
    splits: dict[str, list[str]] = {k: [] for k in SPLIT_NAMES}
    groups: dict[str, list[str]] = {}
    for name in sorted(names):
        meta = metas.get(name, {})
        if held and held.intersection(meta.get("designs", ())):
            splits["test_heldout"].append(name)
            continue
        key = str(meta.get(spec.group_key, name)) if spec.group_key else name
        groups.setdefault(key, []).append(name)
    keys = sorted(groups)
    order = np.random.default_rng(spec.seed).permutation(len(keys))
    total = sum(len(v) for v in groups.values())
    targets = {"test": round(spec.test_fraction * total), "val": round(spec.val_fraction * total)}
    for i in order:
        members = groups[keys[i]]
        for split in ("test", "val"):
            if len(splits[split]) < targets[split]:
                splits[split].extend(members)
                break
        else:
            splits["train"].extend(members)
    return {k: sorted(v) for k, v in splits.items()}


def _find_image(folder: Path, stem: str) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        p = folder / f"{stem}{suffix}"
        if p.is_file():
            return p
    return None


class SodFolder:
    """A DUTS-style folder of images and masks, with optional validity masks, metadata and splits."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).expanduser()
        images, masks = self.root / "images", self.root / "masks"
        if not images.is_dir() or not masks.is_dir():
            raise DataError(
                f"{self.root} is not a SOD folder: it needs images/ and masks/ (DUTS-style, same file stems); "
                "see docs/saliency.md"
            )
        stems = {p.stem for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        mask_stems = {p.stem for p in masks.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        self._names = sorted(stems & mask_stems)
        if not self._names:
            raise DataError(f"{self.root}: no image in images/ has a mask of the same name in masks/")
        self._meta: dict[str, dict[str, Any]] | None = None

    @property
    def names(self) -> list[str]:
        """Sample names (file stems present in both images/ and masks/), sorted."""
        return list(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def image(self, name: str) -> np.ndarray:
        """The RGB image ``(H, W, 3)`` uint8."""
        path = _find_image(self.root / "images", name)
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR) if path else None
        if bgr is None:
            raise DataError(f"{self.root}/images: cannot read the image of {name!r}")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def mask(self, name: str) -> np.ndarray:
        """The 8-bit grey mask ``(H, W)``."""
        path = _find_image(self.root / "masks", name)
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path else None
        if mask is None:
            raise DataError(f"{self.root}/masks: cannot read the mask of {name!r}")
        return mask

    def valid(self, name: str) -> np.ndarray | None:
        """The camera-visibility mask (bool), or ``None`` when the folder has none for this sample."""
        path = _find_image(self.root / "valid", name)
        if path is None:
            return None
        valid = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        return None if valid is None else valid > 0

    def meta(self, name: str) -> dict[str, Any]:
        """The sample's metadata from ``meta.jsonl`` (empty when absent)."""
        return self.metas().get(name, {})

    def metas(self) -> dict[str, dict[str, Any]]:
        """All metadata by sample name."""
        if self._meta is None:
            self._meta = {}
            path = self.root / "meta.jsonl"
            if path.is_file():
                for line_no, line in enumerate(path.read_text().splitlines(), 1):
                    if not line.strip():
                        continue
                    try:
                        row = json.loads(line)
                    except json.JSONDecodeError as exc:
                        raise DataError(f"{path}:{line_no}: not JSON: {exc}") from None
                    self._meta[str(row.get("name"))] = row
        return self._meta

    def splits(self) -> dict[str, list[str]] | None:
        """The splits saved in ``splits.json``, or ``None``."""
        path = self.root / "splits.json"
        if not path.is_file():
            return None
        data = json.loads(path.read_text())
        if data.get("format") != SPLITS_FORMAT:
            raise DataError(f"{path}: not an sgf-sod-splits file")
        known = set(self._names)
        splits = {k: [n for n in v if n in known] for k, v in data["splits"].items()}
        return splits

    def split(self, which: str, spec: SplitSpec | None = None) -> list[str]:
        """Names of one split (``all`` for every sample): from ``splits.json``, else made with ``spec``."""
        if which == "all":
            return self.names
        splits = self.splits()
        if splits is None:
            splits = make_splits(self._names, self.metas(), spec or SplitSpec())
        if which not in splits:
            raise DataError(f"{self.root}: no split named {which!r}; splits: {', '.join(splits)}, all")
        return splits[which]

    def write_splits(self, spec: SplitSpec) -> dict[str, list[str]]:
        """Make the splits with ``spec`` and save them as ``splits.json``."""
        splits = make_splits(self._names, self.metas(), spec)
        atomic_write_json(
            self.root / "splits.json", {"format": SPLITS_FORMAT, "spec": spec.to_dict(), "splits": splits}
        )
        return splits


def _as_mask_u8(mask: np.ndarray) -> np.ndarray:
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f"a mask must be (H, W), got shape {m.shape}")
    if m.dtype == bool:
        return m.astype(np.uint8) * 255
    if np.issubdtype(m.dtype, np.floating):
        return np.clip(np.rint(m * 255), 0, 255).astype(np.uint8)
    if m.dtype == np.uint8:
        return m
    return (m > 0).astype(np.uint8) * 255  # instance ids: any marking is salient


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an image as PNG atomically (BGR or grey, as OpenCV expects)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise DataError(f"cannot encode {path}")
        tmp.write_bytes(buf.tobytes())


@dataclass
class WriteReport:
    """What :func:`write_sod_folder` wrote."""

    root: Path
    count: int
    splits: dict[str, list[str]] = field(default_factory=dict)


def write_sod_folder(
    samples: Iterable[tuple[np.ndarray, np.ndarray, Mapping[str, Any]]],
    root: str | Path,
    split: SplitSpec | None = SplitSpec(),
    prefix: str = "",
) -> WriteReport:
    """Write ``(bev_rgb, mask, meta)`` samples as a SOD folder: the training-data generation interface.

    ``bev_rgb`` is ``(H, W, 3)`` uint8 RGB; ``mask`` is bool, uint8 (0-255), float in [0, 1], or
    integer instance ids (> 0 = salient). ``meta`` is JSON-able; its optional keys are ``name``
    (file stem; default ``<prefix><index:06d>``), ``valid`` (a bool array, written to valid/),
    ``designs`` (marking design names in view, for the held-out split) and a grouping key. Splits
    are made with ``split`` and saved to ``splits.json`` (``None`` writes none).
    """
    out = Path(root).expanduser()
    for sub in ("images", "masks"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rows = []
    count = 0
    seen: set[str] = set()
    for index, (rgb, mask, meta) in enumerate(samples):
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"sample {index}: bev_rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        m = _as_mask_u8(mask)
        if m.shape != rgb.shape[:2]:
            raise ValueError(f"sample {index}: mask shape {m.shape} differs from image shape {rgb.shape[:2]}")
        meta = dict(meta)
        name = str(meta.pop("name", f"{prefix}{index:06d}"))
        if name in seen:
            raise ValueError(f"sample {index}: duplicate name {name!r}")
        seen.add(name)
        valid = meta.pop("valid", None)
        write_png(out / "images" / f"{name}.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        write_png(out / "masks" / f"{name}.png", m)
        if valid is not None:
            write_png(out / "valid" / f"{name}.png", np.asarray(valid, dtype=bool).astype(np.uint8) * 255)
        rows.append(json.dumps({"name": name, **meta}, default=_json_default))
        count += 1
    atomic_write_text(out / "meta.jsonl", "\n".join(rows) + ("\n" if rows else ""))
    report = WriteReport(out, count)
    if split is not None and count:
        report.splits = SodFolder(out).write_splits(split)
    return report


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


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


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


@dataclass(frozen=True)
class Augmentation:
    """Random geometric and photometric changes for training on BEV images (markings may lie at any heading)."""

    rotate: bool = True
    flip: bool = True
    min_scale: float = 0.7
    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.3
    gamma: float = 0.3
    hue_probability: float = 0.0
    noise: float = 6.0
    blur_probability: float = 0.2
    shadow_probability: float = 0.3

    def __call__(self, rgb: np.ndarray, mask: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Augmented copies of an RGB image (uint8) and its mask (float32 in [0, 1]), same size."""
        h, w = mask.shape
        # 1. geometry: rotation about the centre, zoom in (crop), flip; uncovered pixels are black
        #    like the unseen part of a BEV
        angle = float(rng.uniform(0, 360)) if self.rotate else 0.0
        scale = 1.0 / float(rng.uniform(self.min_scale, 1.0))
        cx, cy = w / 2 + rng.uniform(-0.1, 0.1) * w, h / 2 + rng.uniform(-0.1, 0.1) * h
        M = np.asarray(cv2.getRotationMatrix2D((cx, cy), angle, scale), np.float64)
        M[:, 2] += (w / 2 - cx, h / 2 - cy)
        if self.flip and rng.random() < 0.5:
            M = np.array([[-1.0, 0.0, w - 1.0], [0.0, 1.0, 0.0]]) @ np.vstack([M, [0.0, 0.0, 1.0]])
        rgb = cv2.warpAffine(rgb, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mask = cv2.warpAffine(mask, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        # 2. photometry: hue, brightness, contrast, saturation, gamma, a soft shadow, blur, sensor noise
        if rng.random() < self.hue_probability:
            rgb = rotate_hue(rgb, float(rng.uniform(0.0, 360.0)))
        img = rgb.astype(np.float32) / 255.0
        img = img * float(rng.uniform(1 - self.brightness, 1 + self.brightness))
        mean = img.mean()
        img = (img - mean) * float(rng.uniform(1 - self.contrast, 1 + self.contrast)) + mean
        grey = img.mean(axis=2, keepdims=True)
        img = grey + (img - grey) * float(rng.uniform(1 - self.saturation, 1 + self.saturation))
        img = np.clip(img, 0.0, 1.0) ** float(math.exp(rng.uniform(-self.gamma, self.gamma)))
        if rng.random() < self.shadow_probability:
            img = img * _shadow(h, w, rng)[:, :, None]
        if rng.random() < self.blur_probability:
            img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.5, 1.5)))
        img = img * 255.0 + rng.normal(0.0, self.noise * float(rng.random()), img.shape).astype(np.float32)
        return np.clip(img, 0, 255).astype(np.uint8), np.clip(mask, 0.0, 1.0)


def rotate_hue(rgb: np.ndarray, degrees: float) -> np.ndarray:
    """An RGB image (uint8) with every hue turned by ``degrees``: paint of any colour is still paint."""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    shift = round(degrees / 2.0) % 180  # OpenCV's 8-bit hue runs over [0, 180)
    hsv[:, :, 0] = ((hsv[:, :, 0].astype(np.int32) + shift) % 180).astype(np.uint8)
    return np.asarray(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), np.uint8)


def salient_crop(
    rgb: np.ndarray, mask: np.ndarray, crop: int, on_marking: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A ``crop x crop`` window of an image and its mask at full resolution.

    With probability ``on_marking`` (when the mask has salient pixels) the window holds a random
    salient pixel at a random place inside it, else it lies anywhere.
    """
    h, w = mask.shape
    if crop > h or crop > w:
        raise ValueError(f"a crop of {crop} px does not fit a {h}x{w} image")
    ys, xs = np.nonzero(mask > 0.5)
    if len(ys) and rng.random() < on_marking:
        k = int(rng.integers(len(ys)))
        y0 = int(np.clip(ys[k] - rng.integers(crop), 0, h - crop))
        x0 = int(np.clip(xs[k] - rng.integers(crop), 0, w - crop))
    else:
        y0, x0 = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
    return rgb[y0 : y0 + crop, x0 : x0 + crop], mask[y0 : y0 + crop, x0 : x0 + crop]


def _shadow(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A soft-edged half-plane darkening (a building's or the robot's shadow)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    theta = rng.uniform(0, 2 * np.pi)
    offset = rng.uniform(-0.3, 0.3) * max(h, w)
    d = (xx - w / 2) * math.cos(theta) + (yy - h / 2) * math.sin(theta) - offset
    edge = max(1.0, float(rng.uniform(2, 0.1 * max(h, w))))
    darkness = float(rng.uniform(0.3, 0.7))
    return (1 - darkness * 0.5 * (1 + np.tanh(d / (2 * edge)))).astype(np.float32)  # a logistic step, no overflow
