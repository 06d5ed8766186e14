"""SOD examples side by side (paper Fig. 8): each BEV, its ground-truth mask and every model's map."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sgf_plugins.saliency.data import write_png

#: Side of one picture in the grid (px), the gap between pictures and the height of the title row.
TILE = 160
GAP = 4
HEADER = 26


@dataclass
class Example:
    """One row of the figure: an RGB image, its 8-bit mask and each model's 8-bit saliency map."""

    name: str
    image: np.ndarray
    mask: np.ndarray
    maps: dict[str, np.ndarray] = field(default_factory=dict)


def example_names(names: Sequence[str], salient_pixels: Callable[[str], int], count: int) -> list[str]:
    """Up to ``count`` names spread evenly over those whose mask shows an object (all names if none does)."""
    if count <= 0 or not names:
        return []
    pool = [n for n in names if salient_pixels(n) > 0] or list(names)
    count = min(count, len(pool))
    return [pool[(i * len(pool)) // count] for i in range(count)]


def _tile(picture: np.ndarray, size: int) -> np.ndarray:
    """A picture (RGB, or grey shown as grey) resized to ``size`` x ``size`` RGB uint8."""
    rgb = picture if picture.ndim == 3 else np.repeat(picture[..., None], 3, axis=2)
    inter = cv2.INTER_AREA if max(rgb.shape[:2]) > size else cv2.INTER_NEAREST
    return cv2.resize(np.ascontiguousarray(rgb, dtype=np.uint8), (size, size), interpolation=inter)


def example_grid(examples: Sequence[Example], columns: Sequence[str], tile: int = TILE) -> np.ndarray:
    """The figure as an RGB image: a title row, then one row per example (image, truth, each column)."""
    titles = ["BEV", "ground truth", *columns]
    width = len(titles) * tile + (len(titles) - 1) * GAP
    height = HEADER + len(examples) * tile + max(len(examples) - 1, 0) * GAP
    grid = np.full((height, width, 3), 255, np.uint8)
    for c, title in enumerate(titles):
        x = c * (tile + GAP)
        cv2.putText(grid, title[:22], (x + 4, HEADER - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for r, ex in enumerate(examples):
        missing = [c for c in columns if c not in ex.maps]
        if missing:
            raise ValueError(f"example {ex.name!r} has no map for {', '.join(missing)}")
        y = HEADER + r * (tile + GAP)
        for c, picture in enumerate([ex.image, ex.mask, *(ex.maps[col] for col in columns)]):
            x = c * (tile + GAP)
            grid[y : y + tile, x : x + tile] = _tile(picture, tile)
    return grid


def write_examples(path: Path, examples: Sequence[Example], columns: Sequence[str]) -> None:
    """Write the figure as PNG (atomically)."""
    write_png(path, cv2.cvtColor(example_grid(examples, columns), cv2.COLOR_RGB2BGR))
