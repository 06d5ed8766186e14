"""A contact sheet of the design library: every design drawn once, for documentation and eyeballing."""

from __future__ import annotations

import cv2
import numpy as np

from sgf_plugins.world.designs import DESIGNS
from sgf_plugins.world.marking_raster import rasterise


def contact_sheet(res: float = 0.01, seed: int = 0) -> np.ndarray:
    """Every design drawn once on asphalt grey, in a grid (for documentation and eyeballing)."""
    tiles = []
    for i, d in enumerate(DESIGNS.values()):
        r = rasterise(d, d.size[0], d.size[1], res, d.colours[0], seed + i)
        cell = np.full((int(3.2 / res), int(3.2 / res), 3), 90.0, np.float32)
        h, w = r.alpha.shape
        y0, x0 = (cell.shape[0] - h) // 2, (cell.shape[1] - w) // 2
        region = cell[y0 : y0 + h, x0 : x0 + w]
        a = r.alpha[:, :, None]
        cell[y0 : y0 + h, x0 : x0 + w] = region * (1 - a) + r.colour * a
        cv2.putText(cell, d.name, (6, cell.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
        tiles.append(cell)
    cols = 6
    while len(tiles) % cols:
        tiles.append(np.full_like(tiles[0], 60.0))
    rows = [np.hstack(tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    return np.clip(np.vstack(rows), 0, 255).astype(np.uint8)
