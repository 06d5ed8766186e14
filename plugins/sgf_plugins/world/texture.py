"""Ground texture tiles: paving, lawn, curbs, wear, shadows and the painted markings, made on demand.

The ground is never one big image: it is cut into square tiles at three levels of detail
(1, 4 and 16 cm per texel). A tile is generated from the layout only when the camera needs it,
from world-anchored noise and features, so neighbouring tiles and levels agree. Each tile has
four channels (RGB albedo and the sunlit fraction) and a layer of marking instance ids.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_plugins.world.clutter import GroundClutter
from sgf_plugins.world.ground_shadows import GroundShadows
from sgf_plugins.world.layout import CampusLayout, MarkingInstance
from sgf_plugins.world.marking_raster import Raster, rasterise
from sgf_plugins.world.noise import fbm, lattice_noise, rng_for
from sgf_plugins.world.paving import Paving, periodic_cover
from sgf_plugins.world.sun import Sun


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

CURB_WIDTH = 0.15


class TileGenerator:
    """Makes the texture and instance-id tiles of the campus ground at any level of detail.

    Its collaborators: the paving (layout of paths and lawn, surface colours), the ground clutter
    (cracks, stains, leaves, posts) and the ground shadows; it adds grain, building bases and the
    painted markings, and assembles the tile.
    """

    def __init__(self, layout: CampusLayout, sun: Sun, seed: int, clutter: float = 1.0) -> None:
        self.layout = layout
        self.sun = sun
        self.seed = seed
        self.clutter = clutter  # cracks, stains, patches per cell against the campus's own; leaves, posts above 1
        self._rasters: OrderedDict[tuple[int, int], Raster] = OrderedDict()
        self.paving = Paving(layout, seed)
        self.ground_clutter = GroundClutter(seed, clutter)
        self.shadows = GroundShadows(layout, sun, seed, self.ground_clutter)

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
        sdf, s, t, mat, area = self.paving.geometry(x0, y_top, gnx, gny, g)
        large = fbm(seed + 10, x0, y_top, gnx, gny, g, (5.12, 2.56, 1.28))
        edge = lattice_noise(seed + 3, x0, y_top, gnx, gny, g, 0.32)
        sdf = sdf + 0.03 * edge * (sdf > -0.05)
        stains = 1.0 - 0.22 * self.ground_clutter.stains(x0, y_top, gnx, gny, g) * (sdf < 0.0)
        shade = self.shadows.shade(x0, y_top, gnx, gny, g)
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
            lawn = up(*np.moveaxis(self.paving.lawn_base(x0, y_top, gnx, gny, g, large), -1, 0))
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
                rgb[sel] = self.paving.colours(int(material), s_f[sel], t_f[sel], area[sel], tone[sel], grain[sel], res)
            curb = (sdf_f >= 0.0) & (sdf_f < CURB_WIDTH)
            if curb.any():
                joints = periodic_cover(s_f[curb], 1.0, 0.012, res)
                level = 176.0 * (1.0 + 0.05 * grain[curb] + 0.4 * tone[curb]) * (1.0 - 0.35 * joints)
                rgb[curb] = level[:, None] * np.array([1.0, 0.99, 0.96], np.float32)
            # 3. cracks and repairs on the paving
            self.ground_clutter.cracks(factor, x0, y_top, nx, ny, res, paved, mat)
        rgb *= factor[..., None]
        if self.clutter > 1.0:
            self.ground_clutter.leaves(rgb, x0, y_top, nx, ny, res)
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
