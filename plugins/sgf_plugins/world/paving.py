"""The ground's layout in a tile: paving and lawn, path coordinates, and the colours of asphalt, slabs and bricks."""

from __future__ import annotations

import math

import numpy as np

from sgf_plugins.world.layout import MATERIAL_ID, CampusLayout
from sgf_plugins.world.noise import lattice_noise, rng_for

_ASPHALT, _SLABS, _BRICKS = MATERIAL_ID["asphalt"], MATERIAL_ID["slabs"], MATERIAL_ID["bricks"]
_LAWN = MATERIAL_ID["lawn"]


def periodic_cover(u: np.ndarray, period: float | np.ndarray, width: float, texel: float) -> np.ndarray:
    """Box-filtered coverage of lines ``width`` wide every ``period`` (at u = 0 mod period)."""

    def integral(v: np.ndarray) -> np.ndarray:
        k = np.floor(v / period)
        return k * width + np.clip(v - k * period, 0.0, width)

    half = 0.5 * texel
    return ((integral(u + half) - integral(u - half)) / texel).astype(np.float32)


class Paving:
    """Where the paths and plazas lie (distance, path coordinates, material) and how their surfaces look."""

    def __init__(self, layout: CampusLayout, seed: int) -> None:
        self.layout = layout
        self.seed = seed
        brick_palettes = [
            [(152, 74, 58), (168, 92, 66), (136, 64, 52)],
            [(176, 110, 72), (160, 98, 64), (186, 124, 84)],
            [(128, 124, 118), (112, 108, 104), (142, 138, 130)],
            [(96, 92, 90), (110, 104, 100), (84, 82, 80)],
        ]
        tables = rng_for(seed, 201)
        self._tints = tables.random((256, 256), dtype=np.float32)
        self._palettes = np.asarray(brick_palettes, np.float32)
        self._area_palette = tables.integers(0, len(brick_palettes), 2048)

    def geometry(
        self, x0: float, y_top: float, gnx: int, gny: int, g: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance to the paving, path coordinates (along, across), material and area id per texel.

        Every path piece near the region is measured at once (arrays of pieces x texels); plazas
        win inside their outline. Area ids are path edges, or 1000 + plaza index.
        """
        layout = self.layout
        xs = x0 + (np.arange(gnx) + 0.5) * g
        ys = y_top - (np.arange(gny) + 0.5) * g
        best = np.full((gny, gnx), 50.0)
        s_best = np.zeros((gny, gnx))
        t_best = np.zeros((gny, gnx))
        mat = np.full((gny, gnx), _LAWN, np.int32)
        area = np.zeros((gny, gnx), np.int32)
        lo_x, hi_x = xs[0] - 1.0, xs[-1] + 1.0
        lo_y, hi_y = ys[-1] - 1.0, ys[0] + 1.0
        found = layout.segment_index.query(lo_x, lo_y, hi_x, hi_y)
        if found:
            segs = [layout.segments[i] for i in found]
            p0 = np.array([sg.p0 for sg in segs])
            d = np.array([sg.direction for sg in segs])
            length = np.array([sg.length for sg in segs])
            hw = np.array([sg.half_width for sg in segs])
            rx = xs[None, None, :] - p0[:, 0, None, None]
            ry = ys[None, :, None] - p0[:, 1, None, None]
            along = rx * d[:, 0, None, None] + ry * d[:, 1, None, None]
            lat = ry * d[:, 0, None, None] - rx * d[:, 1, None, None]
            dist = np.hypot(along - np.clip(along, 0.0, length[:, None, None]), lat) - hw[:, None, None]
            k = np.argmin(dist, axis=0)[None]
            best = np.take_along_axis(dist, k, 0)[0]
            s0 = np.array([sg.s0 for sg in segs])
            s_best = np.take_along_axis(along, k, 0)[0] + s0[k[0]]
            t_best = np.take_along_axis(lat, k, 0)[0] + hw[k[0]]
            mat = np.array([sg.material for sg in segs], np.int32)[k[0]]
            area = np.array([sg.edge for sg in segs], np.int32)[k[0]]
        px, py = np.meshgrid(xs, ys)
        for i in layout.plaza_index.query(lo_x, lo_y, hi_x, hi_y):
            pz = layout.plazas[i]
            c, sn = math.cos(pz.yaw), math.sin(pz.yaw)
            rx, ry = px - pz.centre[0], py - pz.centre[1]
            u, v = c * rx + sn * ry, -sn * rx + c * ry
            if pz.round:
                dist = np.hypot(u, v) - pz.half
            else:
                lx, ly = np.abs(u) - pz.half, np.abs(v) - pz.half
                dist = np.hypot(np.maximum(lx, 0), np.maximum(ly, 0)) + np.minimum(np.maximum(lx, ly), 0)
            better = (dist < best) | (dist < 0.0)  # inside a plaza its paving wins over the paths
            if better.any():
                best = np.where(better, np.minimum(dist, best), best)
                s_best = np.where(better, u + 100.0, s_best)
                t_best = np.where(better, v + 100.0, t_best)
                mat = np.where(better, MATERIAL_ID[pz.material], mat)
                area = np.where(better, 1000 + i, area)
        return best, s_best, t_best, mat, area

    def lawn_base(self, x0: float, y_top: float, gnx: int, gny: int, g: float, large: np.ndarray) -> np.ndarray:
        """Lawn colour (3 channels) before grain: green, drier and bare patches."""
        patches = lattice_noise(self.seed + 21, x0, y_top, gnx, gny, g, 2.56)
        dry = np.clip(0.5 + 0.9 * patches, 0.0, 1.0)
        soil = np.clip((patches - 0.55) * 6.0, 0.0, 1.0) * 0.6
        green = np.array([60, 102, 40], np.float32)
        yellow = np.array([118, 122, 64], np.float32)
        bare = np.array([112, 92, 68], np.float32)
        base = (green + (0.7 * dry)[..., None] * (yellow - green)) * (1.0 + 0.1 * large)[..., None]
        out: np.ndarray = base * (1.0 - soil)[..., None] + bare * soil[..., None]
        return out

    def colours(
        self,
        material: int,
        ss: np.ndarray,
        tt: np.ndarray,
        area: np.ndarray,
        tn: np.ndarray,
        gr: np.ndarray,
        res: float,
    ) -> np.ndarray:
        """Colours (K, 3) of paved texels from their path coordinates, area, tone and grain.

        Per-slab and per-brick tints come from a 256 x 256 random table indexed by the unit's
        row and column (repeating every 256 units, far beyond what a camera sees at once).
        """
        table = self._tints
        if material == _ASPHALT:
            tone = 1.0 + 1.2 * tn + 0.12 * gr + (gr > 0.97) * np.float32(0.15)
            return tone[:, None] * np.array([86, 87, 90], np.float32)
        if material == _SLABS:
            period = np.where(area >= 1000, np.float32(0.6), np.float32(1.0))
            i = np.floor(ss / period).astype(np.int64)
            j = np.floor(tt / period).astype(np.int64)
            tint = table[i & 255, j & 255] - 0.5
            joint = np.maximum(periodic_cover(ss, period, 0.012, res), periodic_cover(tt, period, 0.012, res))
            detail = min(1.0, 0.6 / (4 * res))
            tone = (1.0 + tn + 0.06 * gr + 0.12 * detail * tint) * (1.0 - 0.45 * joint)
            return tone[:, None] * np.array([166, 163, 156], np.float32)
        if material == _BRICKS:
            bl, bw = 0.21, 0.105
            row = np.floor(tt / bw).astype(np.int64)
            shift = (row & 1) * np.float32(bl / 2)
            along = ss + shift
            col = np.floor(along / bl).astype(np.int64)
            h = table[row & 255, col & 255] * 3.0
            pick = np.minimum(h.astype(np.int64), 2)
            palettes = self._palettes
            which = self._area_palette[area & 2047]
            detail = min(1.0, bl / (4 * res))
            colour = palettes[which, pick]
            if detail < 1.0:
                colour = colour * detail + palettes[which].mean(axis=1) * (1 - detail)
            joint = np.maximum(periodic_cover(tt, bw, 0.01, res), periodic_cover(along, bl, 0.01, res))
            tone = 1.0 + 0.9 * tn + 0.07 * gr + 0.2 * detail * (h - pick - 0.5)
            mortar = np.array([160, 154, 140], np.float32)
            return colour * (tone * (1.0 - joint))[:, None] + mortar * joint[:, None]
        return np.array([150, 150, 150], np.float32) * (1.0 + 0.05 * gr)[:, None]
