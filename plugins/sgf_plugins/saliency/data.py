"""Training data for the saliency networks: a DUTS-style SOD folder, its splits and its writer.

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
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline.errors import DataError
from sgf_pipeline.io import atomic_path, atomic_write_json, atomic_write_text

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
SPLITS_FORMAT = "sgf-sod-splits"
SPLIT_NAMES = ("train", "val", "test", "test_heldout")


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


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
