"""Shadows on the ground: cast by the buildings, the tree canopies (with gaps) and, with extra clutter, posts."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.clutter import GroundClutter
from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.noise import lattice_noise
from sgf_plugins.world.sun import Sun


class GroundShadows:
    """The shade of a region of the ground under the sun of the world."""

    def __init__(self, layout: CampusLayout, sun: Sun, seed: int, clutter: GroundClutter) -> None:
        self.layout = layout
        self.sun = sun
        self.seed = seed
        self.ground_clutter = clutter
        self._tree_shadows: np.ndarray | None = None

    def shade(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> np.ndarray:
        """Shade in [0, 1] (1 = full shadow) cast by the buildings and tree canopies nearby."""
        layout = self.layout
        shade: np.ndarray = np.zeros((ny, nx), np.float32)
        off = self.sun.shadow_offset
        x1, y0 = x0 + nx * res, y_top - ny * res

        def to_px(pts: np.ndarray) -> np.ndarray:
            col = (pts[:, 0] - x0) / res - 0.5
            row = (y_top - pts[:, 1]) / res - 0.5
            return np.round(np.stack([col, row], axis=1) * 16).astype(np.int32)

        reach = 27.0 * float(np.linalg.norm(off)) + 2.0
        for i in layout.building_index.query(x0 - reach, y0 - reach, x1 + reach, y_top + reach):
            b = layout.buildings[i]
            pts = np.concatenate([b.corners, b.corners + off * b.height])
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            if hi[0] < x0 or lo[0] > x1 or hi[1] < y0 or lo[1] > y_top:
                continue
            hull = cv2.convexHull(pts.astype(np.float32))[:, 0, :].astype(np.float64)
            cv2.fillPoly(shade, [to_px(hull)], 1.0, cv2.LINE_AA, 4)
        if self._tree_shadows is None:
            self._tree_shadows = np.array(
                [
                    [*(t.position + off * t.canopy_height), t.canopy_radius / math.sin(self.sun.elevation)]
                    for t in layout.trees
                ]
            ).reshape(-1, 3)
        ts = self._tree_shadows
        near = np.flatnonzero(
            (ts[:, 0] + ts[:, 2] > x0)
            & (ts[:, 0] - ts[:, 2] < x1)
            & (ts[:, 1] + ts[:, 2] > y0)
            & (ts[:, 1] - ts[:, 2] < y_top)
        )
        canopy = np.zeros((ny, nx), np.float32)
        angle = math.degrees(math.atan2(-off[1], off[0]))
        for i in near:
            tr = layout.trees[int(i)]
            c = to_px(ts[i : i + 1, :2])[0]
            axes = (max(1, int(ts[i, 2] / res * 16)), max(1, int(tr.canopy_radius / res * 16)))
            cv2.ellipse(canopy, (int(c[0]), int(c[1])), axes, angle, 0, 360, 1.0, -1, cv2.LINE_AA, 4)
            trunk = np.stack([tr.position, tr.position + off * tr.trunk_height])
            cv2.polylines(canopy, [to_px(trunk)], False, 1.0, max(1, round(0.25 / res)), cv2.LINE_AA, 4)
        if self.ground_clutter.clutter > 1.0:
            for ci, cj in self.ground_clutter.cells(x0, y_top, nx, ny, res):
                for position, height, width in self.ground_clutter.cell_features(ci, cj).posts:
                    bar = np.stack([position, position + off * height])
                    cv2.polylines(shade, [to_px(bar)], False, 1.0, max(1, round(width / res)), cv2.LINE_AA, 4)
        if canopy.any():
            holes = lattice_noise(self.seed + 51, x0, y_top, nx, ny, res, 0.32)
            canopy *= np.clip(0.85 + 0.6 * holes, 0.35, 1.0)
            shade = np.maximum(shade, canopy)
        if shade.any():
            shade = cv2.GaussianBlur(shade, (0, 0), max(0.4, 0.06 / res))
        return shade
