"""Ground texture tiles: paving, lawn, curbs, wear, shadows and the painted markings, made on demand.

The ground is never one big image: it is cut into square tiles at three levels of detail
(1, 4 and 16 cm per texel). A tile is generated from the layout only when the camera needs it,
from world-anchored noise and features, so neighbouring tiles and levels agree. Each tile has
four channels (RGB albedo and the sunlit fraction) and a layer of marking instance ids.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from sgf_plugins.world.designs import Raster, rasterise
from sgf_plugins.world.layout import MATERIAL_ID, CampusLayout, MarkingInstance
from sgf_plugins.world.noise import fbm, lattice_noise, rng_for


@dataclass(frozen=True)
class Level:
    """A level of detail: texel size (m), tile size (m), tiles per side of its mosaic, margin texels."""

    index: int
    res: float
    tile: float
    window: int
    margin: int
    geometry_step: int

    @property
    def texels(self) -> int:
        """Texels per tile side."""
        return round(self.tile / self.res)


LEVELS: tuple[Level, ...] = (
    Level(0, 0.01, 8.0, 3, 16, 4),
    Level(1, 0.04, 8.0, 7, 4, 2),
    Level(2, 0.16, 32.0, 9, 2, 2),
)

_ASPHALT, _SLABS, _BRICKS = MATERIAL_ID["asphalt"], MATERIAL_ID["slabs"], MATERIAL_ID["bricks"]
_LAWN, _CURB = MATERIAL_ID["lawn"], MATERIAL_ID["curb"]
CURB_WIDTH = 0.15
FEATURE_CELL = 8.0


@dataclass(frozen=True)
class Sun:
    """Direction of the sun: azimuth (rad, from +x towards +y) and elevation (rad)."""

    azimuth: float
    elevation: float

    @property
    def shadow_offset(self) -> np.ndarray:
        """Ground offset (m) of a shadow cast by a point 1 m high."""
        k = 1.0 / math.tan(self.elevation)
        return -k * np.array([math.cos(self.azimuth), math.sin(self.azimuth)])

    @property
    def direction(self) -> np.ndarray:
        """Unit vector towards the sun (x, y, z)."""
        ce = math.cos(self.elevation)
        return np.array([ce * math.cos(self.azimuth), ce * math.sin(self.azimuth), math.sin(self.elevation)])


def _periodic_cover(u: np.ndarray, period: float | np.ndarray, width: float, texel: float) -> np.ndarray:
    """Box-filtered coverage of lines ``width`` wide every ``period`` (at u = 0 mod period)."""

    def integral(v: np.ndarray) -> np.ndarray:
        k = np.floor(v / period)
        return k * width + np.clip(v - k * period, 0.0, width)

    half = 0.5 * texel
    return ((integral(u + half) - integral(u - half)) / texel).astype(np.float32)


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


class TileGenerator:
    """Makes the texture and instance-id tiles of the campus ground at any level of detail."""

    def __init__(self, layout: CampusLayout, sun: Sun, seed: int, clutter: float = 1.0) -> None:
        self.layout = layout
        self.sun = sun
        self.seed = seed
        self.clutter = clutter  # cracks, stains, patches per cell against the campus's own; leaves, posts above 1
        self._rasters: OrderedDict[tuple[int, int], Raster] = OrderedDict()
        self._features: OrderedDict[tuple[int, int], CellFeatures] = OrderedDict()
        self._tree_shadows: np.ndarray | None = None
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

    # -- rasters of markings (small LRU) --------------------------------------------------------

    def raster(self, marking: MarkingInstance, level: Level) -> Raster:
        """The marking drawn at a level's texel size (cached)."""
        key = (marking.instance_id, level.index)
        found = self._rasters.get(key)
        if found is not None:
            self._rasters.move_to_end(key)
            return found
        r = rasterise(
            marking.design,
            marking.length,
            marking.width,
            level.res,
            marking.colour,
            marking.content_seed,
            marking.wear,
            marking.wear_seed,
        )
        self._rasters[key] = r
        while len(self._rasters) > 96:
            self._rasters.popitem(last=False)
        return r

    # -- one tile -------------------------------------------------------------------------------

    def generate(self, level: Level, tx: int, ty: int) -> tuple[np.ndarray, np.ndarray]:
        """RGBA (albedo + sunlit fraction) uint8 and instance ids uint16 of tile ``(tx, ty)``."""
        n, m, res = level.texels, level.margin, level.res
        size = n + 2 * m
        x0 = tx * level.tile - m * res
        y_top = (ty + 1) * level.tile + m * res
        return self.region(x0, y_top, size, size, res, level.geometry_step, crop=m)

    def region(
        self, x0: float, y_top: float, nx: int, ny: int, res: float, geometry_step: int = 1, crop: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Texture of an axis-aligned region (texel centres at ``x0 + (c + 0.5) res``, ``y_top - (r + 0.5) res``).

        Smooth quantities (path distances and coordinates, noise, stains, shadows) are computed
        ``geometry_step`` times coarser and upsampled; joints, grain, cracks and markings are
        drawn at full resolution.
        """
        seed = self.seed
        step = geometry_step
        g = res * step
        gnx, gny = math.ceil(nx / step), math.ceil(ny / step)
        # 1. smooth fields on the coarse grid
        sdf, s, t, mat, area = self._geometry(x0, y_top, gnx, gny, g)
        large = fbm(seed + 10, x0, y_top, gnx, gny, g, (5.12, 2.56, 1.28))
        edge = lattice_noise(seed + 3, x0, y_top, gnx, gny, g, 0.32)
        sdf = sdf + 0.03 * edge * (sdf > -0.05)
        stains = 1.0 - 0.22 * self._stains(x0, y_top, gnx, gny, g) * (sdf < 0.0)
        shade = self._shadows(x0, y_top, gnx, gny, g)
        any_paving = bool((sdf < CURB_WIDTH + 0.1).any())
        any_lawn = bool((sdf > -0.1).any())

        def up(*channels: np.ndarray) -> list[np.ndarray]:
            # one channel at a time: several times faster than resizing them interleaved
            out = []
            for channel in channels:
                plane: np.ndarray = np.ascontiguousarray(channel, np.float32)
                if step > 1:
                    plane = cv2.resize(plane, (gnx * step, gny * step), interpolation=cv2.INTER_LINEAR)
                out.append(np.ascontiguousarray(plane[:ny, :nx]))
            return out

        sdf_f, factor, shade_f = up(sdf, stains, shade)
        # 2. full-resolution detail: lawn grain, paving patterns, curbs
        grain = self._grain(x0, y_top, nx, ny, res)
        if any_lawn:
            lawn = up(*np.moveaxis(self._lawn_base(x0, y_top, gnx, gny, g, large), -1, 0))
            shading = 1.0 + 0.25 * grain
            if res <= 0.04:
                shading += 0.15 * lattice_noise(seed + 22, x0, y_top, nx, ny, res, 0.08)
            rgb = np.dstack([c * shading for c in lawn])
        else:
            rgb = np.empty((ny, nx, 3), np.float32)
        paved = sdf_f < 0.0
        if any_paving:
            tone_c = 0.1 * large + 0.05 * lattice_noise(seed + 11, x0, y_top, gnx, gny, g, 0.16)
            s_f, t_f, tone = up(s, t, tone_c)
            if step > 1:
                mat, area = (
                    cv2.resize(
                        np.ascontiguousarray(c, np.int32), (gnx * step, gny * step), interpolation=cv2.INTER_NEAREST
                    )[:ny, :nx]
                    for c in (mat, area)
                )
            for material in np.unique(mat[paved]) if paved.any() else ():
                sel = paved & (mat == material)
                rgb[sel] = self._paving(int(material), s_f[sel], t_f[sel], area[sel], tone[sel], grain[sel], res)
            curb = (sdf_f >= 0.0) & (sdf_f < CURB_WIDTH)
            if curb.any():
                joints = _periodic_cover(s_f[curb], 1.0, 0.012, res)
                level = 176.0 * (1.0 + 0.05 * grain[curb] + 0.4 * tone[curb]) * (1.0 - 0.35 * joints)
                rgb[curb] = level[:, None] * np.array([1.0, 0.99, 0.96], np.float32)
            # 3. cracks and repairs on the paving
            self._cracks(factor, x0, y_top, nx, ny, res, paved, mat)
        rgb *= factor[..., None]
        if self.clutter > 1.0:
            self._leaves(rgb, x0, y_top, nx, ny, res)
        self._buildings(rgb, x0, y_top, nx, ny, res)
        # 4. markings
        ids = np.zeros((ny, nx), np.uint16)
        self._markings(rgb, ids, x0, y_top, nx, ny, res, grain)
        sunlit = cv2.convertScaleAbs(shade_f, alpha=-0.92 * 255.0, beta=255.0)
        out = cv2.merge([*cv2.split(cv2.convertScaleAbs(rgb)), sunlit])
        if crop:
            return out[crop:-crop, crop:-crop].copy(), ids[crop:-crop, crop:-crop].copy()
        return out, ids

    # -- pieces ---------------------------------------------------------------------------------

    def _grain(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> np.ndarray:
        """Per-texel white noise in [-1, 1], fading with texel size (sub-texel grain averages out)."""
        key = (round(x0 / res), round(y_top / res), round(res * 1e4))
        g = rng_for(self.seed + 97, *key).random((ny, nx), dtype=np.float32) * np.float32(2.0) - np.float32(1.0)
        return g * np.float32(min(1.0, math.sqrt(0.01 / res)))

    def _geometry(
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

    def _lawn_base(self, x0: float, y_top: float, gnx: int, gny: int, g: float, large: np.ndarray) -> np.ndarray:
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

    def _paving(
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
            joint = np.maximum(_periodic_cover(ss, period, 0.012, res), _periodic_cover(tt, period, 0.012, res))
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
            joint = np.maximum(_periodic_cover(tt, bw, 0.01, res), _periodic_cover(along, bl, 0.01, res))
            tone = 1.0 + 0.9 * tn + 0.07 * gr + 0.2 * detail * (h - pick - 0.5)
            mortar = np.array([160, 154, 140], np.float32)
            return colour * (tone * (1.0 - joint))[:, None] + mortar * joint[:, None]
        return np.array([150, 150, 150], np.float32) * (1.0 + 0.05 * gr)[:, None]

    def _cells(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> list[tuple[int, int]]:
        c = FEATURE_CELL
        i0, i1 = math.floor((x0 - c) / c), math.floor((x0 + nx * res + c) / c)
        j0, j1 = math.floor((y_top - ny * res - c) / c), math.floor((y_top + c) / c)
        return [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)]

    def _cell_features(self, ci: int, cj: int) -> CellFeatures:
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

    def _stains(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> np.ndarray:
        """Oil and water stains (soft blotches in [0, 1]) anchored to 8 m world cells."""
        stain: np.ndarray = np.zeros((ny, nx), np.float32)
        for ci, cj in self._cells(x0, y_top, nx, ny, res):
            for p, axes, angle, value in self._cell_features(ci, cj).stains:
                centre = (round(((p[0] - x0) / res - 0.5) * 16), round(((y_top - p[1]) / res - 0.5) * 16))
                size = (max(1, int(axes[0] / res * 16)), max(1, int(axes[1] / res * 16)))
                cv2.ellipse(stain, centre, size, angle, 0, 360, value, -1, cv2.LINE_AA, 4)
        if stain.any():
            stain = cv2.GaussianBlur(stain, (0, 0), max(0.5, 0.08 / res))
        return stain

    def _cracks(
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

        for ci, cj in self._cells(x0, y_top, nx, ny, res):
            cell = self._cell_features(ci, cj)
            for pts, width in cell.cracks if res < 0.08 else ():  # hair-line cracks vanish in coarse texels
                strength = min(1.0, width / res)
                cv2.polylines(dark, [to_px(pts)], False, strength, max(1, round(width / res)), cv2.LINE_AA, 4)
            for corners in cell.repairs:
                cv2.fillPoly(repair, [to_px(corners)], 1.0, cv2.LINE_AA, 4)
        if dark.any():
            factor -= 0.5 * dark * paved
        if repair.any():
            factor *= 1.0 - 0.18 * repair * (paved & (mat == _ASPHALT))

    def _leaves(self, rgb: np.ndarray, x0: float, y_top: float, nx: int, ny: int, res: float) -> None:
        """Fallen leaves: small ellipses of autumn colours, in drifts anchored to 8 m world cells."""
        for ci, cj in self._cells(x0, y_top, nx, ny, res):
            for p, axes, angle, colour in self._cell_features(ci, cj).leaves:
                centre = (round(((p[0] - x0) / res - 0.5) * 16), round(((y_top - p[1]) / res - 0.5) * 16))
                size = (max(1, int(axes[0] / res * 16)), max(1, int(axes[1] / res * 16)))
                rgb_colour = tuple(float(c) for c in _LEAF_COLOURS[colour])
                cv2.ellipse(rgb, centre, size, angle, 0, 360, rgb_colour, -1, cv2.LINE_AA, 4)

    def _buildings(self, rgb: np.ndarray, x0: float, y_top: float, nx: int, ny: int, res: float) -> None:
        """Concrete bases under the buildings (hidden by their walls in the camera, seen on maps)."""
        lo_x, hi_x = x0, x0 + nx * res
        lo_y, hi_y = y_top - ny * res, y_top
        base = np.array([104, 102, 100], np.float32)
        for i in self.layout.building_index.query(lo_x, lo_y, hi_x, hi_y):
            corners = self.layout.buildings[i].corners
            col = (corners[:, 0] - x0) / res - 0.5
            row = (y_top - corners[:, 1]) / res - 0.5
            c0, c1 = max(0, math.floor(col.min())), min(nx, math.ceil(col.max()) + 1)
            r0, r1 = max(0, math.floor(row.min())), min(ny, math.ceil(row.max()) + 1)
            if c1 <= c0 or r1 <= r0:
                continue
            mask = np.zeros((r1 - r0, c1 - c0), np.float32)
            pts = np.stack([col - c0, row - r0], 1)
            cv2.fillPoly(mask, [np.round(pts * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
            roi = rgb[r0:r1, c0:c1]
            roi[:] = roi * (1 - mask[..., None]) + base * mask[..., None]

    def _markings(
        self, rgb: np.ndarray, ids: np.ndarray, x0: float, y_top: float, nx: int, ny: int, res: float, grain: np.ndarray
    ) -> None:
        layout = self.layout
        lo_x, hi_x = x0, x0 + nx * res
        lo_y, hi_y = y_top - ny * res, y_top
        level = next((lv for lv in LEVELS if abs(lv.res - res) < 1e-12), None)
        for i in layout.marking_index.query(lo_x, lo_y, hi_x, hi_y):
            mk = layout.markings[i]
            if mk.x + mk.radius < lo_x or mk.x - mk.radius > hi_x or mk.y + mk.radius < lo_y or mk.y - mk.radius > hi_y:
                continue
            raster = (
                self.raster(mk, level)
                if level is not None
                else rasterise(mk.design, mk.length, mk.width, res, mk.colour, mk.content_seed, mk.wear, mk.wear_seed)
            )
            # Region of the region's texels that the marking can touch.
            c0 = max(0, math.floor((mk.x - mk.radius - x0) / res) - 1)
            c1 = min(nx, math.ceil((mk.x + mk.radius - x0) / res) + 2)
            r0 = max(0, math.floor((y_top - mk.y - mk.radius) / res) - 1)
            r1 = min(ny, math.ceil((y_top - mk.y + mk.radius) / res) + 2)
            if c1 <= c0 or r1 <= r0:
                continue
            # texel (c, r) of the ROI -> world -> marking local -> raster pixel
            cy, sy = math.cos(mk.yaw), math.sin(mk.yaw)
            a = raster.local_to_pixel_matrix()
            # world (X, Y) of ROI texel (c, r): X = x0 + (c0 + c + 0.5) res, Y = y_top - (r0 + r + 0.5) res
            world = np.array([[res, 0.0, x0 + (c0 + 0.5) * res], [0.0, -res, y_top - (r0 + 0.5) * res], [0, 0, 1]])
            to_local = np.array([[cy, sy, -(cy * mk.x + sy * mk.y)], [-sy, cy, (sy * mk.x - cy * mk.y)], [0, 0, 1]])
            m = (a @ to_local @ world)[:2]
            size = (c1 - c0, r1 - r0)
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            alpha = cv2.warpAffine(raster.alpha, m, size, flags=flags, borderValue=0.0)
            if not alpha.any():
                continue
            colour = cv2.warpAffine(raster.colour, m, size, flags=flags, borderValue=(0.0, 0.0, 0.0))
            mask = cv2.warpAffine(raster.mask.astype(np.float32), m, size, flags=flags, borderValue=0.0) >= 0.5
            roi = rgb[r0:r1, c0:c1]
            if mk.design.material == "paint":
                colour = colour * (0.93 + 0.07 * grain[r0:r1, c0:c1])[..., None]
            alpha3 = alpha[..., None]
            roi[:] = roi * (1.0 - alpha3) + colour * alpha3
            ids[r0:r1, c0:c1][mask] = mk.instance_id

    def _shadows(self, x0: float, y_top: float, nx: int, ny: int, res: float) -> np.ndarray:
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
        if self.clutter > 1.0:
            for ci, cj in self._cells(x0, y_top, nx, ny, res):
                for position, height, width in self._cell_features(ci, cj).posts:
                    bar = np.stack([position, position + off * height])
                    cv2.polylines(shade, [to_px(bar)], False, 1.0, max(1, round(width / res)), cv2.LINE_AA, 4)
        if canopy.any():
            holes = lattice_noise(self.seed + 51, x0, y_top, nx, ny, res, 0.32)
            canopy *= np.clip(0.85 + 0.6 * holes, 0.35, 1.0)
            shade = np.maximum(shade, canopy)
        if shade.any():
            shade = cv2.GaussianBlur(shade, (0, 0), max(0.4, 0.06 / res))
        return shade


class TileCache:
    """A bounded LRU of generated tiles per level (the memory does not grow with the route)."""

    def __init__(self, generator: TileGenerator, capacity: tuple[int, ...] = (6, 24, 48)) -> None:
        self.generator = generator
        self.capacity = capacity
        self._tiles: OrderedDict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.generated = 0

    def get(self, level: Level, tx: int, ty: int) -> tuple[np.ndarray, np.ndarray]:
        """The tile, generated if it is not cached."""
        key = (level.index, tx, ty)
        found = self._tiles.get(key)
        if found is not None:
            self._tiles.move_to_end(key)
            return found
        tile = self.generator.generate(level, tx, ty)
        self.generated += 1
        self._tiles[key] = tile
        per_level = [k for k in self._tiles if k[0] == level.index]
        while len(per_level) > self.capacity[level.index]:
            self._tiles.pop(per_level.pop(0))
        return tile

    def __len__(self) -> int:
        return len(self._tiles)
