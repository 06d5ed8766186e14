"""Ground clutter that is not a marking: cracks, stains, asphalt repairs, fallen leaves and posts.

Every piece is anchored to an 8 m world cell and drawn from that cell's own random streams, so
neighbouring tiles and levels of detail agree and the clutter does not depend on what was drawn before.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from sgf_plugins.world.layout import MATERIAL_ID
from sgf_plugins.world.noise import rng_for

_ASPHALT = MATERIAL_ID["asphalt"]
FEATURE_CELL = 8.0

#: Colours of fallen leaves (RGB): brown, orange, yellow, dark red.
_LEAF_COLOURS = np.array([(118, 80, 42), (188, 108, 40), (204, 172, 64), (128, 52, 32)], np.float32)


@dataclass
class CellFeatures:
    """Clutter anchored to one world cell: cracks, stains, repairs, fallen leaves and posts.

    Cracks: (polyline, width); stains: (centre, axes, angle, darkness); leaves: (centre, axes, angle,
    colour index); posts: (position, height, width), whose shadows fall on the ground.
    """

    cracks: list[tuple[np.ndarray, float]]
    stains: list[tuple[np.ndarray, np.ndarray, float, float]]
    repairs: list[np.ndarray]
    leaves: list[tuple[np.ndarray, np.ndarray, float, int]] = field(default_factory=list)
    posts: list[tuple[np.ndarray, float, float]] = field(default_factory=list)


class GroundClutter:
    """The clutter of the 8 m world cells (cached) and its drawing into a region of the ground."""

    def __init__(self, seed: int, clutter: float = 1.0) -> None:
        self.seed = seed
        self.clutter = clutter  # cracks, stains, patches per cell against the campus's own; leaves, posts above 1
        self._features: OrderedDict[tuple[int, int], CellFeatures] = OrderedDict()

    def cells(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> list[tuple[int, int]]:
        """The 8 m world cells whose clutter can reach a region (one cell of margin)."""
        c = FEATURE_CELL
        i0, i1 = math.floor((x0 - c) / c), math.floor((x0 + nx * res + c) / c)
        j0, j1 = math.floor((y_top - ny * res - c) / c), math.floor((y_top + c) / c)
        return [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)]

    def cell_features(self, ci: int, cj: int) -> CellFeatures:
        """The cracks, stains, asphalt repairs, leaves and posts anchored to one 8 m world cell (cached)."""
        found = self._features.get((ci, cj))
        if found is not None:
            return found
        origin = np.array([ci * FEATURE_CELL, cj * FEATURE_CELL])
        clutter = self.clutter
        rng = rng_for(self.seed, 101, ci, cj)
        cracks = []
        for _ in range(int(rng.poisson(2.0 * clutter))):
            p = origin + rng.uniform(0, FEATURE_CELL, 2)
            steps = int(rng.integers(6, 30))
            headings = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, 0.45, steps))
            walk = np.cumsum(0.12 * np.stack([np.cos(headings), np.sin(headings)], 1), 0)
            cracks.append((p + np.concatenate([[[0.0, 0.0]], walk]), float(rng.uniform(0.004, 0.014))))
        repairs = []
        if rng.random() < min(1.0, 0.25 * clutter):
            p = origin + rng.uniform(0, FEATURE_CELL, 2)
            w, h = rng.uniform(0.6, 2.5, 2)
            a = rng.uniform(0, math.pi)
            corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
            rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            repairs.append(p + corners @ rot.T)
        rng = rng_for(self.seed, 102, ci, cj)
        stains = []
        for _ in range(int(rng.poisson(0.8 * clutter))):
            p = origin + rng.uniform(0, FEATURE_CELL, 2)
            axes = rng.uniform(0.15, 0.7, 2)
            stains.append((p, axes, float(rng.uniform(0, 180)), float(rng.uniform(0.3, 1.0))))
        leaves: list[tuple[np.ndarray, np.ndarray, float, int]] = []
        posts: list[tuple[np.ndarray, float, float]] = []
        if clutter > 1.0:  # a stream of its own: the campus's own clutter stays as it is
            rng = rng_for(self.seed, 103, ci, cj)
            for _ in range(int(rng.poisson(1.0 * (clutter - 1.0)))):  # a drift of leaves
                centre = origin + rng.uniform(0, FEATURE_CELL, 2)
                spread = rng.uniform(0.15, 0.6)
                for _ in range(int(rng.integers(8, 26))):
                    p = centre + rng.normal(0.0, spread, 2)
                    axes = np.array([rng.uniform(0.03, 0.06), rng.uniform(0.015, 0.03)])
                    leaves.append((p, axes, float(rng.uniform(0, 180)), int(rng.integers(len(_LEAF_COLOURS)))))
            for _ in range(int(rng.poisson(0.5 * (clutter - 1.0)))):  # lamp and sign posts off the paving
                posts.append((origin + rng.uniform(0, FEATURE_CELL, 2), float(rng.uniform(2.0, 4.5)), 0.1))
        features = CellFeatures(cracks, stains, repairs, leaves, posts)
        self._features[(ci, cj)] = features
        while len(self._features) > 4096:
            self._features.popitem(last=False)
        return features

    def stains(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> np.ndarray:
        """Oil and water stains (soft blotches in [0, 1]) anchored to 8 m world cells."""
        stain: np.ndarray = np.zeros((ny, nx), np.float32)
        for ci, cj in self.cells(x0, y_top, nx, ny, res):
            for p, axes, angle, value in self.cell_features(ci, cj).stains:
                centre = (round(((p[0] - x0) / res - 0.5) * 16), round(((y_top - p[1]) / res - 0.5) * 16))
                size = (max(1, int(axes[0] / res * 16)), max(1, int(axes[1] / res * 16)))
                cv2.ellipse(stain, centre, size, angle, 0, 360, value, -1, cv2.LINE_AA, 4)
        if stain.any():
            stain = cv2.GaussianBlur(stain, (0, 0), max(0.5, 0.08 / res))
        return stain

    def cracks(
        self,
        factor: np.ndarray,
        x0: float,
        y_top: float,
        nx: int,
        ny: int,
        res: float,
        paved: np.ndarray,
        mat: np.ndarray,
    ) -> None:
        """Darken ``factor`` with cracks (and asphalt repairs) on the paving, from 8 m world cells."""
        dark = np.zeros((ny, nx), np.float32)
        repair = np.zeros((ny, nx), np.float32)
        offset = np.array([x0, y_top])
        scale = np.array([16.0 / res, -16.0 / res])

        def to_px(pts: np.ndarray) -> np.ndarray:
            return np.round((pts - offset) * scale - 8.0).astype(np.int32)

        for ci, cj in self.cells(x0, y_top, nx, ny, res):
            cell = self.cell_features(ci, cj)
            for pts, width in cell.cracks if res < 0.08 else ():  # hair-line cracks vanish in coarse texels
                strength = min(1.0, width / res)
                cv2.polylines(dark, [to_px(pts)], False, strength, max(1, round(width / res)), cv2.LINE_AA, 4)
            for corners in cell.repairs:
                cv2.fillPoly(repair, [to_px(corners)], 1.0, cv2.LINE_AA, 4)
        if dark.any():
            factor -= 0.5 * dark * paved
        if repair.any():
            factor *= 1.0 - 0.18 * repair * (paved & (mat == _ASPHALT))

    def leaves(self, rgb: np.ndarray, x0: float, y_top: float, nx: int, ny: int, res: float) -> None:
        """Fallen leaves: small ellipses of autumn colours, in drifts anchored to 8 m world cells."""
        for ci, cj in self.cells(x0, y_top, nx, ny, res):
            for p, axes, angle, colour in self.cell_features(ci, cj).leaves:
                centre = (round(((p[0] - x0) / res - 0.5) * 16), round(((y_top - p[1]) / res - 0.5) * 16))
                size = (max(1, int(axes[0] / res * 16)), max(1, int(axes[1] / res * 16)))
                rgb_colour = tuple(float(c) for c in _LEAF_COLOURS[colour])
                cv2.ellipse(rgb, centre, size, angle, 0, 360, rgb_colour, -1, cv2.LINE_AA, 4)
