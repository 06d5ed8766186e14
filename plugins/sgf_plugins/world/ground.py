"""The ground's texture in the camera: tile mosaics per level of detail, blended, and near-camera grain.

Ground colour and marking ids come from one ``cv2.remap`` per level of detail in window mosaics
of generated tiles; near the camera the light is modulated by a fine grain fixed to the ground.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.raycast import STEP
from sgf_plugins.world.sun import Sun
from sgf_plugins.world.texture import LEVELS, Level, TileCache, TileGenerator

#: Near-camera grain: texel size (m) and the depth (m) up to which it shows.
DETAIL_TEXEL = 0.0025
DETAIL_DEPTH = 4.0


class Mosaic:
    """One level's tiles in a window of ``W x W`` tiles around a centre tile, laid out in one buffer.

    Tile ``(tx, ty)`` sits at buffer column ``(tx - cx + W // 2) n`` and row ``(cy + W // 2 - ty) n``
    (north up). When the centre moves, the tiles still in the window are moved along (a copy into
    a second buffer) and the new ones are generated on demand, so every texel the camera may
    sample lies inside the buffer: ``cv2.remap`` never wraps.
    """

    def __init__(self, level: Level) -> None:
        self.level = level
        self.size = level.texels * level.window
        self.rgba = np.zeros((self.size, self.size, 4), np.uint8)
        self.ids = np.zeros((self.size, self.size), np.uint16)
        self._spare: tuple[np.ndarray, np.ndarray] | None = None
        self.loaded: set[tuple[int, int]] = set()
        self.centre: tuple[int, int] | None = None

    def set_centre(self, x: float, y: float) -> None:
        """Centre the window on the tile holding ``(x, y)``, moving the tiles that stay in it."""
        t = self.level.tile
        centre = (math.floor(x / t), math.floor(y / t))
        if centre == self.centre:
            return
        old, self.centre = self.centre, centre
        keep = {tile for tile in self.loaded if self.in_window(*tile)}
        if old is not None and keep:
            if self._spare is None:
                self._spare = (np.empty_like(self.rgba), np.empty_like(self.ids))
            rgba, ids = self._spare
            n, half = self.level.texels, self.level.window // 2
            for tx, ty in keep:
                c_old, r_old = (tx - old[0] + half) * n, (old[1] + half - ty) * n
                c_new, r_new = self._corner(tx, ty)
                rgba[r_new : r_new + n, c_new : c_new + n] = self.rgba[r_old : r_old + n, c_old : c_old + n]
                ids[r_new : r_new + n, c_new : c_new + n] = self.ids[r_old : r_old + n, c_old : c_old + n]
            self._spare = (self.rgba, self.ids)
            self.rgba, self.ids = rgba, ids
        self.loaded = keep

    def _corner(self, tx: int, ty: int) -> tuple[int, int]:
        assert self.centre is not None
        n, half = self.level.texels, self.level.window // 2
        return (tx - self.centre[0] + half) * n, (self.centre[1] + half - ty) * n

    def in_window(self, tx: int, ty: int) -> bool:
        """Whether a tile is inside the window around the centre."""
        if self.centre is None:
            return False
        half = self.level.window // 2
        return abs(tx - self.centre[0]) <= half and abs(ty - self.centre[1]) <= half

    def ensure(self, cache: TileCache, tiles: set[tuple[int, int]]) -> None:
        """Load tiles of the window that are not in the buffer yet."""
        n = self.level.texels
        for tx, ty in sorted(tiles):
            if (tx, ty) in self.loaded or not self.in_window(tx, ty):
                continue
            rgba, ids = cache.get(self.level, tx, ty)
            c0, r0 = self._corner(tx, ty)
            self.rgba[r0 : r0 + n, c0 : c0 + n] = rgba
            self.ids[r0 : r0 + n, c0 : c0 + n] = ids
            self.loaded.add((tx, ty))

    @property
    def shift(self) -> tuple[int, int]:
        """Global texel index (col, row) of the buffer's top-left texel: map = global - shift."""
        assert self.centre is not None
        n, half = self.level.texels, self.level.window // 2
        return (self.centre[0] - half) * n, -(self.centre[1] + half + 1) * n


class GroundTexture:
    """Tile generator, tile cache and one mosaic per level of detail; samples them for a frame."""

    def __init__(
        self, layout: CampusLayout, sun: Sun, seed: int, clutter: float, width: int, height: int, detail: np.ndarray
    ) -> None:
        self.generator = TileGenerator(layout, sun, seed, clutter)
        self.cache = TileCache(self.generator)
        self.mosaics = [Mosaic(level) for level in LEVELS]
        self.width, self.height = width, height
        self.detail = detail

    def levels(self, pose: np.ndarray, pts: np.ndarray, hit: np.ndarray, t: np.ndarray, far_field: bool) -> np.ndarray:
        """Weights (3, nv, nu) of the levels of detail per sample; loads the tiles each level needs.

        Level 0 up to 6 m of depth, level 1 from 7.5 to 28 m, level 2 beyond 34 m, blended in
        between; a level whose window does not hold the point hands its weight to the next one.
        """
        heading = math.atan2(pose[1, 0], pose[0, 0])
        fwd = np.array([math.cos(heading), math.sin(heading)])
        base_xy = pose[:2, 3]
        anchors = (base_xy + 4.0 * fwd, base_xy + 16.0 * fwd, base_xy)
        lam = np.interp(np.where(hit, t, 1e9), [6.0, 7.5, 28.0, 34.0], [0.0, 1.0, 1.0, 2.0])
        weights = np.stack([np.clip(1.0 - np.abs(lam - k), 0.0, 1.0) for k in range(3)]) * hit
        for k, mosaic in enumerate(self.mosaics):
            mosaic.set_centre(*anchors[k])
            tile = mosaic.level.tile
            half = mosaic.level.window // 2
            # usable when 1 m or more inside the window
            margin = 1.0 / tile
            cx, cy = mosaic.centre or (0, 0)
            fx = pts[..., 0] / tile - (cx - half)
            fy = pts[..., 1] / tile - (cy - half)
            size = mosaic.level.window
            inside = (fx > margin) & (fx < size - margin) & (fy > margin) & (fy < size - margin)
            if k < 2:
                weights[k + 1] += np.where(inside, 0.0, weights[k])
            weights[k] *= inside
        if not far_field:
            weights[0] = np.where(weights[0] == 1.0, 1.0, 0.0)
            weights[1:] = 0.0
        # every pixel lies between four samples: the bounding box of each cell's ground corners
        corners = [
            (slice(None, -1), slice(None, -1)),
            (slice(1, None), slice(None, -1)),
            (slice(None, -1), slice(1, None)),
            (slice(1, None), slice(1, None)),
        ]
        bounds = []
        for coord in (pts[..., 0], pts[..., 1]):
            lo_in, hi_in = np.where(hit, coord, np.inf), np.where(hit, coord, -np.inf)
            bounds.append(np.minimum.reduce([lo_in[rs, cs] for rs, cs in corners]))
            bounds.append(np.maximum.reduce([hi_in[rs, cs] for rs, cs in corners]))
        lo_x, hi_x, lo_y, hi_y = bounds
        for k, mosaic in enumerate(self.mosaics):
            use = weights[k] > 0.0
            if not use.any():
                continue
            # load the tiles under each used cell's bounding box
            cell_use = use[:-1, :-1] | use[1:, :-1] | use[:-1, 1:] | use[1:, 1:]
            tile = mosaic.level.tile
            margin = 0.05
            ranges = np.stack(
                [
                    np.floor((lo_x[cell_use] - margin) / tile),
                    np.floor((hi_x[cell_use] + margin) / tile),
                    np.floor((lo_y[cell_use] - margin) / tile),
                    np.floor((hi_y[cell_use] + margin) / tile),
                ],
                axis=1,
            ).astype(np.int64)
            # the window's tiles covered by any range, marked on a grid by 2-D prefix sums
            size = mosaic.level.window
            assert mosaic.centre is not None
            ox, oy = mosaic.centre[0] - size // 2, mosaic.centre[1] - size // 2
            a0 = np.clip(ranges[:, 0] - ox, 0, size)
            a1 = np.clip(ranges[:, 1] - ox + 1, 0, size)
            b0 = np.clip(ranges[:, 2] - oy, 0, size)
            b1 = np.clip(ranges[:, 3] - oy + 1, 0, size)
            n = size + 1
            corners = np.concatenate([b0 * n + a0, b0 * n + a1, b1 * n + a0, b1 * n + a1])
            signs = np.repeat(np.array([1.0, -1.0, -1.0, 1.0]), len(a0))
            diff = np.bincount(corners, signs, minlength=n * n).reshape(n, n)
            covered = diff.cumsum(axis=0).cumsum(axis=1)[:size, :size] > 0.5
            rows, cols = np.nonzero(covered)
            needed = {(ox + int(c), oy + int(r)) for r, c in zip(rows, cols, strict=True)}
            mosaic.ensure(self.cache, needed)
        return weights

    def blend_levels(
        self,
        rgba: np.ndarray,
        ids: np.ndarray,
        maps: np.ndarray,
        weights_f: list[np.ndarray],
        ground_all: np.ndarray,
        top: int,
        shift: tuple[int, int],
        renormalise: bool,
    ) -> None:
        """Rows above ``top``: blend the levels of detail by weight; ids from the heaviest level.

        The colour of pixels off the ground does not matter (the sky covers them), so only the
        ids and the renormalisation look at ``ground_all``; ``renormalise`` says whether any
        sample lost weight to a window running out (else the weights of ground pixels sum to one).
        """
        lv0 = LEVELS[0]
        ground = ground_all[:top]
        # uint8 arithmetic (weights in 1/255): an order of magnitude faster than float blending
        acc = rgba[:top]  # zeros: accumulated in place
        total = np.zeros((top, self.width), np.float32) if renormalise else None
        for k, mosaic in enumerate(self.mosaics):
            weight = weights_f[k][:top]
            used = weight > 0
            rows = np.flatnonzero(used.any(axis=1))
            if rows.size == 0:
                continue
            cols = np.flatnonzero(used[rows[0] : rows[-1] + 1].any(axis=0))
            # the box of the pixels this level weighs in
            box = np.s_[int(rows[0]) : int(rows[-1]) + 1, int(cols[0]) : int(cols[-1]) + 1]
            # texel coordinates of level k from those of level 0 (both world-aligned); pixels with
            # weight lie in the window (their tiles are loaded), clipping keeps the others on
            # remap's fast in-range path
            top_texel = np.float32(mosaic.size - 1)
            if k == 0:
                map_k = np.clip(maps[box], 0.0, top_texel)
            else:
                ratio = lv0.res / mosaic.level.res
                sx, sy = mosaic.shift
                offset = ((shift[0] + 0.5) * ratio - 0.5 - sx, (shift[1] + 0.5) * ratio - 0.5 - sy)
                map_k = np.multiply(maps[box], np.float32(ratio))
                map_k += np.array(offset, np.float32)
                np.clip(map_k, 0.0, top_texel, out=map_k)
            wk = weight[box]
            sample = _remap(mosaic.rgba, map_k, cv2.INTER_LINEAR)
            w8 = cv2.convertScaleAbs(wk, alpha=255.0)
            w4 = cv2.merge([w8, w8, w8, w8])  # (GRAY2RGBA would set the sunlit channel to 255)
            cv2.add(acc[box], cv2.multiply(sample, w4, scale=1.0 / 255.0), dst=acc[box])
            if total is not None:
                total[box] += wk
            # ids from the heaviest level (never blended), on the ground only
            heavy = (wk > 0.5) & ground[box]
            if heavy.any():
                np.copyto(ids[box], _remap(mosaic.ids, map_k, cv2.INTER_NEAREST), where=heavy)
        if total is None:
            return
        # the weights sum to one except where a level's window ran out: renormalise those pixels
        short = (total > 0.0) & (total < 0.99) & ground
        if short.any():
            acc[short] = np.clip(acc[short] / total[short][:, None], 0, 255).astype(np.uint8)

    def add_detail(
        self, light: np.ndarray, maps: np.ndarray, depth_f: np.ndarray, depth: np.ndarray, hit: np.ndarray, top: int
    ) -> None:
        """Modulate the light near the camera with 2.5 mm grain, where texels are larger than pixels.

        The grain's texture coordinates are the level-0 texel coordinates scaled (the grain's
        period divides the mosaic, so it stays fixed to the ground); one remap of the grain.
        """
        near = hit & (depth < DETAIL_DEPTH)
        rows = np.flatnonzero(near.any(axis=1))
        if rows.size == 0:
            return
        r0 = max(top, STEP * int(rows[0]) - STEP)
        if r0 >= self.height:
            return
        scale = np.float32(LEVELS[0].res / DETAIL_TEXEL)
        coords: np.ndarray = cv2.addWeighted(maps[r0:], float(scale), maps[r0:], 0.0, float(0.5 * scale - 0.5))
        period = np.float32(self.detail.shape[0])
        # in range (truncation is the floor of the coordinates >= 0): remap's fast path; the
        # rare negative ones stay correct through the wrapping border
        whole = np.multiply(coords, 1 / period)
        np.trunc(whole, out=whole)
        whole *= period
        coords -= whole
        grain = _remap(self.detail, coords, cv2.INTER_LINEAR, cv2.BORDER_WRAP)
        fade = cv2.addWeighted(depth_f[r0:], -0.5, depth_f[r0:], 0.0, 0.5 * DETAIL_DEPTH)
        np.clip(fade, 0.0, 1.0, out=fade)
        grain *= fade
        grain += 1.0
        light[r0:] *= grain


def detail_texture(rng: np.random.Generator, size: int = 600) -> np.ndarray:
    """A periodic grain texture (mean 0, within +-0.2): small stones and pores of 3 to 12 mm.

    Its period (600 texels of 2.5 mm = 1.5 m) divides the level-0 mosaic, so the grain stays fixed
    to the ground as the mosaic moves.
    """
    white = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.fftfreq(size)[None, :]
    f = np.hypot(fx, fy) / DETAIL_TEXEL  # cycles per metre
    band = np.exp(-((np.log(np.maximum(f, 1e-9) / 120.0)) ** 2) / 0.6)
    grain = np.real(np.fft.ifft2(np.fft.fft2(white) * band))
    grain /= grain.std()
    stones = np.tanh(1.6 * grain)
    return (0.2 * stones / np.abs(stones).max()).astype(np.float32)


def _remap(src: np.ndarray, maps: np.ndarray, interpolation: int, border: int = cv2.BORDER_REPLICATE) -> np.ndarray:
    """``cv2.remap`` with one two-channel float map."""
    out: np.ndarray = cv2.remap(src, maps, None, interpolation, borderMode=border)  # type: ignore[call-overload]
    return out
