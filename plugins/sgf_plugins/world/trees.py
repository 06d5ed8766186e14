"""Trees in the camera view: trunks as quads, crowns as sprites of leaf clumps (blobs when far)."""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable

import cv2
import numpy as np

from sgf_plugins.world.drawing import CameraView, Item, Lighting, ToCamera, clip_near, in_view
from sgf_plugins.world.layout import CampusLayout, Tree
from sgf_plugins.world.noise import lattice_noise, rng_for

#: Memory budget of the scaled and lit tree sprites kept between frames.
SPRITE_CACHE_BYTES = 48 * 2**20


class Trees:
    """The campus trees: crown sprites per variant (a pyramid, scaled and lit sprites cached) and drawing."""

    def __init__(self, layout: CampusLayout, seed: int, tree_z: np.ndarray) -> None:
        self.layout = layout
        self.seed = seed
        self._canopies = [_pyramid(self._canopy_sprite(k)) for k in range(4)]
        self._sprite_bytes = 0
        # per canopy variant, each pyramid level as contiguous planes: uint8 colour, float32 alpha
        self._sprite_planes = [
            [
                (np.clip(level[..., :3], 0, 255).astype(np.uint8), np.ascontiguousarray(level[..., 3], np.float32))
                for level in p
            ]
            for p in self._canopies
        ]
        self._scaled_sprites: OrderedDict[tuple[int, int, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = (
            OrderedDict()
        )
        self._canopy_colours = [
            (p[0][..., :3] * p[0][..., 3:]).sum(axis=(0, 1)) / max(float(p[0][..., 3].sum()), 1e-6)
            for p in self._canopies
        ]
        self._trees = np.array(
            [
                [t.position[0], t.position[1], z, t.canopy_height, t.canopy_radius]
                for t, z in zip(layout.trees, tree_z, strict=True)
            ]
        ).reshape(-1, 5)

    def _canopy_sprite(self, variant: int) -> np.ndarray:
        """RGBA sprite of a tree crown: clumps of leaves, lit from above, ragged outline."""
        size = 128
        rng = rng_for(self.seed, 311, variant)
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        c = (size - 1) / 2
        r = np.hypot(xx - c, yy - c) / c
        ragged = lattice_noise(self.seed + 311 + variant, 0.0, float(size), size, size, 1.0, 12.0)
        alpha = np.clip((1.0 - r + 0.18 * ragged) * 8.0, 0.0, 1.0)
        clumps = lattice_noise(self.seed + 313 + variant, 0.0, float(size), size, size, 1.0, 6.0)
        leaves = rng.random((size, size)).astype(np.float32)
        base = np.asarray([(54, 92, 38), (70, 104, 44), (46, 82, 40), (88, 110, 50)][variant], np.float32)
        light = 0.65 + 0.35 * (1.0 - yy / size) + 0.25 * clumps + 0.15 * (leaves - 0.5)
        sprite = np.empty((size, size, 4), np.float32)
        sprite[..., :3] = base * light[..., None]
        sprite[..., 3] = alpha * (0.85 + 0.15 * (leaves > 0.3))
        return sprite

    def queue(self, items: list[Item], view: CameraView) -> None:
        """Queue the trees within 75 m whose trunk or crown can show in the image."""
        centre, rot, trans = view.centre, view.rot, view.trans
        image, K, light, project = view.image, view.K, view.light, view.project
        h, w = image.shape[:2]
        layout = self.layout
        if len(self._trees):
            tr = self._trees
            near = np.flatnonzero((tr[:, 0] - centre[0]) ** 2 + (tr[:, 1] - centre[1]) ** 2 < 75.0**2)
            if near.size:
                crowns = np.column_stack([tr[near, 0], tr[near, 1], tr[near, 2] + tr[near, 3]]) @ rot.T + trans
                bases = tr[near, :3] @ rot.T + trans
                pad = K[0, 0] * tr[near, 4] / np.maximum(crowns[:, 2], 0.3)
                show = in_view(crowns, K, w, h, pad) | in_view(bases, K, w, h, pad)
                show &= crowns[:, 2] >= 0.3
                idx = near[show]
                uv_base, uv_crown = project(bases[show]), project(crowns[show])
                r_px = K[0, 0] * tr[idx, 4] / crowns[show, 2]
                off = (
                    (uv_crown[:, 0] + r_px < 0)
                    | (uv_crown[:, 0] - r_px > w)
                    | (uv_crown[:, 1] - r_px > h)
                    | ((uv_base[:, 1] < 0) & (uv_crown[:, 1] + r_px < 0))
                )
                dist = np.hypot(tr[idx, 0] - centre[0], tr[idx, 1] - centre[1])
                # trunks: quads facing the camera, 0.28 m wide at the foot and 0.17 m under the crown
                foot = tr[idx, :3]
                top = foot + np.column_stack([np.zeros((len(idx), 2)), tr[idx, 3]])
                rel = foot[:, :2] - centre[:2]
                side = np.column_stack([-rel[:, 1], rel[:, 0], np.zeros(len(idx))])
                side *= 0.14 / np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
                trunks = np.stack([foot + side, foot - side, top - 0.6 * side, top + 0.6 * side], axis=1)
                trunks = trunks @ rot.T + trans
                for j in np.flatnonzero(~off):
                    i = int(idx[j])
                    draw = self._tree_item(
                        layout.trees[i],
                        tr[i, :3],
                        trunks[j],
                        uv_crown[j],
                        float(r_px[j]),
                        project,
                        image,
                        light,
                    )
                    items.append((float(dist[j]), draw))

    def _tree_item(
        self,
        tree: Tree,
        base: np.ndarray,
        trunk: np.ndarray,
        crown_px: np.ndarray,
        r_px: float,
        project: ToCamera,
        image: np.ndarray,
        light: Lighting,
    ) -> Callable[[], None]:
        """The drawing of a tree that shows (culled and projected in ``queue``)."""
        crown = base + np.array([0.0, 0.0, tree.canopy_height])

        def draw() -> None:
            level = light.at(crown) if light.night else (light.ambient + 0.6 * light.sun_strength) * light.gain
            tc = clip_near(trunk)
            if len(tc) >= 3:
                tuv = project(tc)
                col = (78.0 * level, 64.0 * level, 52.0 * level)
                cv2.fillPoly(image, [np.round(tuv * 16).astype(np.int32)], col, cv2.LINE_AA, 4)
            if r_px >= 12.0:
                self._sprite(image, tree.variant, crown_px, r_px, level)
            elif r_px >= 1.0:  # a far crown: a blob of its mean colour (its leaves are below a pixel)
                blob = tuple(float(v) for v in self._canopy_colours[tree.variant] * level)
                centre_px = (round(crown_px[0] * 16), round(crown_px[1] * 16))
                axes = (round(r_px * 16), round(r_px * 0.92 * 16))
                cv2.ellipse(image, centre_px, axes, 0.0, 0, 360, blob, -1, cv2.LINE_AA, 4)

        return draw

    def _sprite(self, image: np.ndarray, variant: int, centre: np.ndarray, r_px: float, level: float) -> None:
        """Blend a tree crown of canopy ``variant``, radius ``r_px`` around ``centre`` (px), lit by ``level``."""
        h, w = image.shape[:2]
        # sizes on a scale of 24 steps per octave (3 %): a tree keeps its cached sprite for a few frames
        size = max(2, round(2.0 ** (round(math.log2(max(2.0 * r_px, 1.0)) * 24.0) / 24.0)))
        planes = self._sprite_planes[variant]
        # the smallest pyramid level at least as large as the sprite (the largest if none is)
        level_index = next((i for i in range(len(planes) - 1, -1, -1) if planes[i][1].shape[0] >= size), 0)
        c0 = round(centre[0] - size / 2)
        r0 = round(centre[1] - size / 2)
        cc0, cc1 = max(0, c0), min(w, c0 + size)
        rr0, rr1 = max(0, r0), min(h, r0 + size)
        if cc1 <= cc0 or rr1 <= rr0:
            return
        # scaled and lit sprites are cached (by day every tree has the same light level)
        key = (variant, size, round(level, 3))
        scaled = self._scaled_sprites.get(key)
        if scaled is not None:
            self._scaled_sprites.move_to_end(key)
        else:
            rgb8, alpha8 = planes[level_index]
            rgb = cv2.resize(rgb8, (size, size), interpolation=cv2.INTER_LINEAR)
            alpha = cv2.resize(alpha8, (size, size), interpolation=cv2.INTER_LINEAR)
            scaled = (cv2.convertScaleAbs(rgb, alpha=level), alpha, 1.0 - alpha)
            self._scaled_sprites[key] = scaled
            self._sprite_bytes += sum(a.nbytes for a in scaled)
            while self._sprite_bytes > SPRITE_CACHE_BYTES and len(self._scaled_sprites) > 1:
                _, dropped = self._scaled_sprites.popitem(last=False)
                self._sprite_bytes -= sum(a.nbytes for a in dropped)
        rgb, alpha, rest = (a[rr0 - r0 : rr1 - r0, cc0 - c0 : cc1 - c0] for a in scaled)
        roi = image[rr0:rr1, cc0:cc1]
        roi[:] = cv2.blendLinear(rgb, np.ascontiguousarray(roi), alpha, rest)


def _pyramid(sprite: np.ndarray) -> list[np.ndarray]:
    """A sprite and its halvings down to 4 pixels (area-averaged), largest first."""
    levels = [sprite]
    while levels[-1].shape[0] > 4:
        prev = levels[-1]
        levels.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))
    return levels
