"""The camera: every pixel's ray cast onto the terrain, textured from tile mosaics, lit, and exposed.

Per frame the rays of a coarse grid (every 4th pixel) are intersected with the height field
(plane start, Newton steps); the hit points, depths and lighting are upsampled bilinearly to
full resolution (exact bilinear interpolation of the coarse samples; under 0.1 px of the true
projective map below the horizon's first rows), and the ground colour and marking ids are
looked up with one ``cv2.remap`` per level of detail in toroidal tile mosaics. Sky, walls,
trees, people and vehicles are drawn on top; exposure and sensor noise come last.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_plugins.world.layout import Agent, CampusLayout
from sgf_plugins.world.noise import lattice_noise, rng_for
from sgf_plugins.world.scenery import Lighting, Scenery
from sgf_plugins.world.terrain import Terrain
from sgf_plugins.world.texture import LEVELS, Level, Sun, TileCache, TileGenerator

STEP = 4
MAX_DISTANCE = 150.0
NIGHT_GAIN = 2.2
#: Speed bumps and rough patches farther than this from the camera are not ray cast (sub-pixel).
DETAIL_RADIUS = 45.0
#: Near-camera grain: texel size (m) and the depth (m) up to which it shows.
DETAIL_TEXEL = 0.0025
DETAIL_DEPTH = 5.0


@dataclass(frozen=True)
class RenderConditions:
    """How a frame looks: night or day, the time (moving people), exposure, occluders and noise."""

    night: bool = False
    time: float = 0.0
    exposure: float = 1.0
    occluders: bool = True
    extra_occluders: int = 0
    sensor_noise: bool = True
    headlight: bool | None = None
    street_lamps: bool = True
    far_field: bool = True
    noise_seed: int = 0


@dataclass
class RenderLayers:
    """A rendered frame with its by-products: marking ids, ground depth, occlusion, ground points."""

    image: np.ndarray
    ids: np.ndarray
    depth: np.ndarray
    occluded: np.ndarray
    texel_maps: np.ndarray
    texel_shift: tuple[int, int]
    ground: np.ndarray

    def ground_xy(self) -> np.ndarray:
        """World ``(x, y)`` (H, W, 2) of the ground point seen by every pixel (NaN for sky)."""
        res = LEVELS[0].res
        xy = np.empty(self.texel_maps.shape, np.float64)
        xy[..., 0] = (self.texel_maps[..., 0].astype(np.float64) + 0.5 + self.texel_shift[0]) * res
        xy[..., 1] = -(self.texel_maps[..., 1].astype(np.float64) + 0.5 + self.texel_shift[1]) * res
        xy[~self.ground] = np.nan
        return xy


class Mosaic:
    """One level's tiles around the camera in a toroidal buffer (tile ``(tx, ty)`` in slot ``tx mod W``)."""

    def __init__(self, level: Level) -> None:
        self.level = level
        self.size = level.texels * level.window
        self.rgba = np.zeros((self.size, self.size, 4), np.uint8)
        self.ids = np.zeros((self.size, self.size), np.uint16)
        self.slots: dict[tuple[int, int], tuple[int, int]] = {}
        self.centre = (0, 0)

    def set_centre(self, x: float, y: float) -> None:
        """Centre the window of usable tiles on the tile holding ``(x, y)``."""
        t = self.level.tile
        self.centre = (math.floor(x / t), math.floor(y / t))

    def in_window(self, tx: int, ty: int) -> bool:
        """Whether a tile may be held this frame (inside the window around the centre)."""
        half = self.level.window // 2
        return abs(tx - self.centre[0]) <= half and abs(ty - self.centre[1]) <= half

    def ensure(self, cache: TileCache, tiles: set[tuple[int, int]]) -> None:
        """Load tiles into their slots (each slot holds one tile of the window)."""
        n, w = self.level.texels, self.level.window
        for tx, ty in sorted(tiles):
            slot = (tx % w, (-ty - 1) % w)
            if self.slots.get(slot) == (tx, ty):
                continue
            rgba, ids = cache.get(self.level, tx, ty)
            c0, r0 = slot[0] * n, slot[1] * n
            self.rgba[r0 : r0 + n, c0 : c0 + n] = rgba
            self.ids[r0 : r0 + n, c0 : c0 + n] = ids
            self.slots[slot] = (tx, ty)

    def texel_bounds(self) -> tuple[float, float, float, float]:
        """Global texel column and row range (min, max) covered by the window, less one texel."""
        n, half = self.level.texels, self.level.window // 2
        cx, cy = self.centre
        col_lo, col_hi = (cx - half) * n, (cx + half + 1) * n - 1.0
        row_lo, row_hi = (-(cy + half) - 1) * n, (-(cy - half)) * n - 1.0
        return col_lo, col_hi, row_lo, row_hi


class Renderer:
    """Renders camera images and marking-id images of the campus for any base pose."""

    def __init__(self, layout: CampusLayout, terrain: Terrain, calibration: Calibration, sun: Sun, seed: int) -> None:
        self.layout = layout
        self.terrain = terrain
        self.calibration = calibration
        self.sun = sun
        self.seed = seed
        self.generator = TileGenerator(layout, sun, seed)
        self.cache = TileCache(self.generator)
        self.mosaics = [Mosaic(level) for level in LEVELS]
        self.scenery = Scenery(layout, seed, terrain.height)
        intr = calibration.intrinsics
        self.width, self.height = intr.width, intr.height
        self.K = intr.matrix
        self.camera_to_base = calibration.camera_to_base_matrix
        # Coarse samples at u = 4a - 2.5, v = 4b - 2.5: resizing x4 then cropping 4 gives exact
        # bilinear interpolation at every integer pixel (see _upsample).
        self.nu = math.ceil(self.width / STEP) + 2
        self.nv = math.ceil(self.height / STEP) + 2
        us = STEP * np.arange(self.nu) - 2.5
        vs = STEP * np.arange(self.nv) - 2.5
        uu, vv = np.meshgrid(us, vs)
        self.rays = np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], axis=-1)
        r = np.hypot((uu - intr.cx) / (0.5 * self.width), (vv - intr.cy) / (0.5 * self.height)) / math.sqrt(2)
        self.vignette = (1.0 - 0.22 * r**2).astype(np.float32)
        rng = rng_for(seed, 401)
        self.noise_bank = rng.standard_normal((2, self.height + 32, self.width + 32, 3)).astype(np.float32)
        self._agent_boxes: np.ndarray | None = None
        self.detail = _detail_texture(rng)

    # -- public --------------------------------------------------------------------------------

    def render(self, pose: np.ndarray, conditions: RenderConditions) -> RenderLayers:
        """Render the camera of a robot whose base is at ``pose`` (4x4, world frame)."""
        cam = pose @ self.camera_to_base
        rot, centre = cam[:3, :3], cam[:3, 3]
        dirs = self.rays @ rot.T
        t, hit, gx, gy = self._intersect(centre, dirs, float(pose[2, 3]))
        pts = centre + t[..., None] * dirs
        horiz = np.hypot(pts[..., 0] - centre[0], pts[..., 1] - centre[1])
        # 1. level of detail per sample; the tiles each level needs are loaded into its mosaic
        lam = self._levels(pose, pts, hit, t, conditions.far_field)
        hit &= lam < 2.5
        # 2. light and haze per sample
        night = conditions.night
        light = self._lighting(pose, conditions)
        normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        s1, s2 = self._ground_light(pts, normal, light)
        haze = 1.0 - np.exp(-horiz / (900.0 if not night else 300.0))
        haze = np.where(hit, np.maximum(haze, np.clip((horiz - 95.0) / 30.0, 0.0, 1.0)), 1.0)
        # L0 texel coordinates (small numbers: relative to a multiple of the mosaic size)
        lv0, m0 = LEVELS[0], self.mosaics[0]
        shift = (
            math.floor((pose[0, 3] / lv0.res) / m0.size) * m0.size,
            math.floor((-pose[1, 3] / lv0.res) / m0.size) * m0.size,
        )
        mx = np.where(hit, pts[..., 0] / lv0.res - 0.5 - shift[0], 0.0)
        my = np.where(hit, -pts[..., 1] / lv0.res - 0.5 - shift[1], 0.0)
        depth = np.where(hit, t, 1e4)
        maps = self._upsample(np.stack([mx, my], axis=-1).astype(np.float32))
        s1_f = self._upsample((s1 * self.vignette).astype(np.float32))
        s2_f = self._upsample((s2 * self.vignette).astype(np.float32))
        depth_f = self._upsample(depth.astype(np.float32))
        # rows below ``top`` see only near ground (level 0, inside its window): the fast path
        pure_coarse = ((lam == 0.0) & hit).all(axis=1)
        full_rows = np.arange(self.height)
        b = np.floor((full_rows + 2.5) / STEP).astype(np.int64)
        pure_row = pure_coarse[np.clip(b, 0, self.nv - 1)] & pure_coarse[np.clip(b + 1, 0, self.nv - 1)]
        not_pure = np.flatnonzero(~pure_row)
        top = int(not_pure[-1]) + 1 if not_pure.size else 0
        h, w = self.height, self.width
        band = max(top, 1)
        lam_f = self._upsample(lam.astype(np.float32), band)
        haze_f = self._upsample(haze.astype(np.float32), band)
        ground_top = self._upsample(hit.astype(np.float32), band) >= 0.999
        ground = np.ones((h, w), bool)
        ground[:band] = ground_top
        rgba = np.zeros((h, w, 4), np.uint8)
        ids = np.zeros((h, w), np.uint16)
        if top < h:
            rgba[top:] = _remap(m0.rgba, maps[top:], cv2.INTER_LINEAR)
            ids[top:] = _remap(m0.ids, maps[top:], cv2.INTER_NEAREST)
        if top > 0:
            self._blend_levels(rgba, ids, maps, lam_f, ground, top, shift)
        # 3. shadows of people and vehicles, light, haze, sky
        self.scenery.set_frame(conditions.time, cam)
        agents = self._agents(conditions, pose) if conditions.occluders or conditions.extra_occluders else []
        sunlit = rgba[..., 3].astype(np.float32)
        if agents and not night:
            shadow = self._agent_shadows(agents, cam)
            if shadow is not None:
                sunlit *= 1.0 - 0.85 * shadow
        light_f = s1_f + s2_f * sunlit
        self._add_detail(light_f, maps, depth_f, top)
        image = rgba[..., :3].astype(np.float32)
        image *= light_f[..., None]
        sky_rows = np.flatnonzero((haze_f > 0.01).any(axis=1) | ~ground[:band].all(axis=1))
        if sky_rows.size:
            r1 = int(sky_rows[-1]) + 1
            sky = self._sky(dirs, r1, night)
            hz = haze_f[:r1, :, None]
            g = ground[:r1, :, None]
            horizon = self._horizon_colour(night)
            image[:r1] = np.where(g, image[:r1] * (1 - hz) + horizon * hz, sky)
        # 4. things above the ground
        occlusion = np.zeros((h, w), np.uint8)
        self.scenery.draw(image, occlusion, depth_f, cam, self.K, light, agents, conditions.far_field)
        ids[occlusion > 0] = 0
        # 5. exposure and sensor noise
        image = self._expose(image, conditions)
        return RenderLayers(image, ids.astype(np.int32), depth_f, occlusion > 0, maps, shift, ground)

    def _levels(self, pose: np.ndarray, pts: np.ndarray, hit: np.ndarray, t: np.ndarray, far_field: bool) -> np.ndarray:
        """Level of detail (0..2, 3 = none) per sample; loads the tiles each level needs."""
        heading = math.atan2(pose[1, 0], pose[0, 0])
        fwd = np.array([math.cos(heading), math.sin(heading)])
        base_xy = pose[:2, 3]
        anchors = (base_xy + 4.0 * fwd, base_xy + 16.0 * fwd, base_xy)
        lam = np.interp(np.where(hit, t, 1e9), [8.0, 9.5, 28.0, 34.0], [0.0, 1.0, 1.0, 2.0])
        for k, mosaic in enumerate(self.mosaics):
            mosaic.set_centre(*anchors[k])
            tile = mosaic.level.tile
            half = mosaic.level.window // 2
            # usable when 1 m or more inside the window
            margin = 1.0 / tile
            fx = pts[..., 0] / tile - (mosaic.centre[0] - half)
            fy = pts[..., 1] / tile - (mosaic.centre[1] - half)
            size = mosaic.level.window
            inside = (fx > margin) & (fx < size - margin) & (fy > margin) & (fy < size - margin)
            lam = np.where(hit & ~inside & (lam < k + 1), float(k + 1) if k < 2 else 3.0, lam)
            if k == 2:
                lam = np.where(hit & ~inside, 3.0, lam)
        if not far_field:
            lam = np.where(lam > 0.0, 3.0, 0.0)
        usable = hit & (lam < 2.5)
        for k, mosaic in enumerate(self.mosaics):
            weight = np.clip(1.0 - np.abs(lam - k), 0.0, 1.0)
            use = usable & (weight > 0)
            if not use.any():
                continue
            tile = mosaic.level.tile
            xs, ys = pts[..., 0][use], pts[..., 1][use]
            packed = np.unique(np.floor(xs / tile).astype(np.int64) * 1_000_003 + np.floor(ys / tile).astype(np.int64))
            keys = np.stack([np.floor_divide(packed + 500_000, 1_000_003), 0 * packed], axis=1)
            keys[:, 1] = packed - keys[:, 0] * 1_000_003
            lo_x, hi_x, lo_y, hi_y = xs.min() - 1.0, xs.max() + 1.0, ys.min() - 1.0, ys.max() + 1.0
            grown = set()
            for a, b in keys.tolist():
                for da in (-1, 0, 1):
                    for db in (-1, 0, 1):
                        ta, tb = a + da, b + db
                        if (
                            mosaic.in_window(ta, tb)
                            and (ta + 1) * tile >= lo_x
                            and ta * tile <= hi_x
                            and (tb + 1) * tile >= lo_y
                            and tb * tile <= hi_y
                        ):
                            grown.add((ta, tb))
            mosaic.ensure(self.cache, grown)
        return lam

    def _blend_levels(
        self,
        rgba: np.ndarray,
        ids: np.ndarray,
        maps: np.ndarray,
        lam_f: np.ndarray,
        ground_all: np.ndarray,
        top: int,
        shift: tuple[int, int],
    ) -> None:
        """Rows above ``top``: blend the levels of detail by weight; ids from the nearest level."""
        lv0 = LEVELS[0]
        lam = lam_f[:top]
        ground = ground_all[:top]
        acc = np.zeros((top, self.width, 4), np.float32)
        total = np.zeros((top, self.width), np.float32)
        level_here = np.clip(np.floor(lam + 0.5), 0, 2)
        for k, mosaic in enumerate(self.mosaics):
            weight = np.clip(1.0 - np.abs(lam - k), 0.0, 1.0) * ground
            rows = np.flatnonzero(weight.max(axis=1) > 0)
            if rows.size == 0:
                continue
            r0, r1 = int(rows[0]), int(rows[-1]) + 1
            lv = mosaic.level
            # texel coordinates of level k from those of level 0 (both world-aligned)
            ratio = lv0.res / lv.res
            ox = (shift[0] + 0.5) * ratio - 0.5
            oy = (shift[1] + 0.5) * ratio - 0.5
            sx = math.floor(ox / mosaic.size) * mosaic.size
            sy = math.floor(oy / mosaic.size) * mosaic.size
            map_x = maps[r0:r1, :, 0] * np.float32(ratio) + np.float32(ox - sx)
            map_y = maps[r0:r1, :, 1] * np.float32(ratio) + np.float32(oy - sy)
            col_lo, col_hi, row_lo, row_hi = mosaic.texel_bounds()
            valid = (map_x >= col_lo - sx) & (map_x <= col_hi - sx) & (map_y >= row_lo - sy) & (map_y <= row_hi - sy)
            wk = weight[r0:r1] * valid
            sample = cv2.remap(mosaic.rgba, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            ident = cv2.remap(mosaic.ids, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_WRAP)
            acc[r0:r1] += sample.astype(np.float32) * wk[..., None]
            total[r0:r1] += wk
            choose = valid & (level_here[r0:r1] == k) & ground[r0:r1]
            ids[r0:r1] = np.where(choose, ident, ids[r0:r1])
        acc /= np.maximum(total, 1e-6)[..., None]
        rgba[:top] = np.clip(acc, 0, 255).astype(np.uint8)

    def _add_detail(self, light: np.ndarray, maps: np.ndarray, depth: np.ndarray, top: int) -> None:
        """Modulate the light near the camera with 2.5 mm grain, where texels are larger than pixels."""
        near = np.flatnonzero((depth[top:, :: STEP * 4] < DETAIL_DEPTH).any(axis=1))
        if near.size == 0:
            return
        r0 = top + int(near[0])
        scale = np.float32(LEVELS[0].res / DETAIL_TEXEL)
        offset = np.float32(0.5 * scale - 0.5)
        dx = maps[r0:, :, 0] * scale + offset
        dy = maps[r0:, :, 1] * scale + offset
        grain = cv2.remap(self.detail, dx, dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        fade = np.clip((DETAIL_DEPTH - depth[r0:]) / 2.5, 0.0, 1.0)
        light[r0:] *= 1.0 + grain * fade

    # -- geometry ------------------------------------------------------------------------------

    def _intersect(
        self, centre: np.ndarray, dirs: np.ndarray, z_ref: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ray parameter (camera depth) of each sample's ground hit, whether it hits, and dH/dx, dH/dy.

        1. Newton steps on the smooth hills, from the horizontal plane under the robot (robust:
           slopes stay under 10 %). 2. Rays whose hit lies near a speed bump or rough patch are
           marched through the band of heights the feature spans, and the first crossing is
           refined by bisection, so that the near face of a bump is found, not the ground behind.
        """
        shape = dirs.shape[:2]
        d = dirs.reshape(-1, 3)
        dz = d[:, 2]
        t_max = MAX_DISTANCE / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        down = dz < -1e-9
        t = np.where(down, (z_ref - centre[2]) / np.where(down, dz, -1.0), t_max)
        t = np.clip(t, 0.0, t_max)
        gx = np.zeros_like(t)
        gy = np.zeros_like(t)
        if self.terrain.flat:
            return t.reshape(shape), (down & (t < t_max)).reshape(shape), gx.reshape(shape), gy.reshape(shape)
        residual = np.full_like(t, np.inf)
        slope = np.full_like(t, -1.0)
        active = np.flatnonzero(down)
        for _ in range(6):
            if active.size == 0:
                break
            ta, da = t[active], d[active]
            hgt, gxa, gya = self.terrain.height_and_gradient(
                centre[0] + ta * da[:, 0], centre[1] + ta * da[:, 1], detail=False
            )
            f = centre[2] + ta * da[:, 2] - hgt
            fp = da[:, 2] - gxa * da[:, 0] - gya * da[:, 1]
            ok = fp < -1e-6
            step = np.where(ok, f / np.where(ok, fp, -1.0), 0.0)
            gx[active], gy[active], residual[active], slope[active] = gxa, gya, np.abs(f), fp
            t[active] = np.clip(ta - step, 0.0, t_max[active])
            active = active[np.abs(step) > 1e-4]
        hit = down & (residual < 0.02) & (t > 0.0) & (t < t_max * 0.999)
        boxes = self.terrain.detail_boxes(float(centre[0]), float(centre[1]), DETAIL_RADIUS)
        if len(boxes):
            x = centre[0] + t * d[:, 0]
            y = centre[1] + t * d[:, 1]
            margin = 2.0
            near = np.zeros(len(t), bool)
            for x0, y0, x1, y1 in boxes:
                near |= (x > x0 - margin) & (x < x1 + margin) & (y > y0 - margin) & (y < y1 + margin)
            idx = np.flatnonzero(near & hit & (t < DETAIL_RADIUS))
            if idx.size:
                t[idx], gx[idx], gy[idx] = self._march(centre, d[idx], t[idx], slope[idx])
        return t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape)

    def _march(
        self, centre: np.ndarray, d: np.ndarray, t_smooth: np.ndarray, slope: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First crossing of rays with the full terrain within the height band of bumps and patches."""
        rate = np.maximum(-slope, 1e-3)  # metres of height lost per unit of t, relative to the smooth ground
        lo = np.maximum(t_smooth - 0.16 / rate, 1e-3)
        hi = t_smooth + 0.04 / rate
        n = 16
        ts = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, n)[None, :]
        px = centre[0] + ts * d[:, 0:1]
        py = centre[1] + ts * d[:, 1:2]
        hgt = self.terrain.height(px, py)
        f = centre[2] + ts * d[:, 2:3] - hgt
        below = f <= 0.0
        first = np.where(below.any(axis=1), below.argmax(axis=1), n - 1)
        rows = np.arange(len(d))
        a = ts[rows, np.maximum(first - 1, 0)]
        b = ts[rows, first]
        for _ in range(8):
            m = 0.5 * (a + b)
            hm = self.terrain.height(centre[0] + m * d[:, 0], centre[1] + m * d[:, 1])
            above = centre[2] + m * d[:, 2] - hm > 0.0
            a = np.where(above, m, a)
            b = np.where(above, b, m)
        t = 0.5 * (a + b)
        _, gx, gy = self.terrain.height_and_gradient(centre[0] + t * d[:, 0], centre[1] + t * d[:, 1])
        return t, gx, gy

    def _upsample(self, coarse: np.ndarray, rows: int | None = None) -> np.ndarray:
        """Exact bilinear interpolation of the coarse samples at every pixel (of the top ``rows`` rows)."""
        rows = self.height if rows is None else rows
        nb = min(self.nv, math.ceil((rows - 1 + 2.5) / STEP) + 2)
        big = cv2.resize(coarse[:nb], (self.nu * STEP, nb * STEP), interpolation=cv2.INTER_LINEAR)
        return big[STEP : STEP + rows, STEP : STEP + self.width]

    # -- light -----------------------------------------------------------------------------------

    def _lighting(self, pose: np.ndarray, conditions: RenderConditions) -> Lighting:
        night = conditions.night
        headlight = conditions.headlight if conditions.headlight is not None else night
        origin = (pose @ np.array([0.28, 0.0, 0.42, 1.0]))[:3]
        lamps: list[tuple[np.ndarray, float]] = []
        if night and conditions.street_lamps:
            x, y = pose[0, 3], pose[1, 3]
            for i in self.layout.lamp_index.query(x - 45, y - 45, x + 45, y + 45):
                lamp = self.layout.lamps[i]
                z = float(self.scenery.lamp_z[i]) + lamp.height
                lamps.append((np.array([lamp.position[0], lamp.position[1], z]), 4.0))
        return Lighting(
            night=night,
            ambient=0.05 if night else 0.5,
            sun=self.sun.direction,
            sun_strength=0.0 if night else 0.62,
            headlight_origin=origin,
            headlight_frame=pose[:3, :3].copy(),
            headlight_power=3.2 if headlight else 0.0,
            lamps=lamps,
        )

    def _ground_light(self, pts: np.ndarray, normal: np.ndarray, light: Lighting) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample light not depending on shadows (s1) and the sunlit part (s2, times sunlit/255)."""
        if not light.night:
            cos_sun = np.clip(normal @ light.sun, 0.0, None) / max(light.sun[2], 1e-3)
            s1 = np.full(pts.shape[:2], light.ambient)
            s2 = light.sun_strength * cos_sun / 255.0
            return s1, s2
        s1 = np.full(pts.shape[:2], light.ambient)
        if light.headlight_power > 0:
            to = pts - light.headlight_origin
            r2 = np.maximum((to**2).sum(axis=-1), 0.25)
            facing = np.clip(-(normal * to).sum(axis=-1) / np.sqrt(r2), 0.0, None)
            s1 = s1 + light.beam(to) * facing / r2
        for pos, power in light.lamps:
            to = pts - pos
            r2 = np.maximum((to**2).sum(axis=-1), 1.0)
            facing = np.clip(-(normal * to).sum(axis=-1) / np.sqrt(r2), 0.0, None)
            s1 = s1 + power * facing / r2
        return s1, np.zeros_like(s1)

    def _horizon_colour(self, night: bool) -> np.ndarray:
        return np.array([13, 14, 21], np.float32) if night else np.array([196, 206, 214], np.float32)

    def _sky(self, dirs: np.ndarray, rows: int, night: bool) -> np.ndarray:
        """Sky colour of the top ``rows`` rows: a gradient with clouds (day) or a dark glow (night)."""
        nb = min(self.nv, math.ceil((rows + 2.5) / STEP) + 2)
        d = dirs[:nb]
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        elev = np.clip(d[..., 2], -0.05, 1.0)
        t = np.sqrt(np.clip(elev, 0.0, 1.0))[..., None]
        if night:
            colour = np.array([13, 14, 21], np.float32) * (1 - t) + np.array([3, 4, 9], np.float32) * t
        else:
            colour = self._horizon_colour(False) * (1 - t) + np.array([92, 138, 204], np.float32) * t
            az = np.arctan2(d[..., 1], d[..., 0])
            cu = ((az + math.pi) / (2 * math.pi) * 2048.0).astype(np.float32)
            cv = (np.clip(elev, 0.0, 1.0) * 600.0).astype(np.float32)
            clouds = cv2.remap(self._clouds(), cu, cv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            c = np.clip((clouds - 0.1) * 2.2, 0.0, 0.85)[..., None]
            colour = colour * (1 - c) + np.array([238, 240, 242], np.float32) * c
        big = cv2.resize(colour.astype(np.float32), (self.nu * STEP, nb * STEP), interpolation=cv2.INTER_LINEAR)
        return big[STEP : STEP + rows, STEP : STEP + self.width]

    _cloud_cache: np.ndarray | None = None

    def _clouds(self) -> np.ndarray:
        if self._cloud_cache is None:
            self._cloud_cache = (
                lattice_noise(self.seed + 405, 0.0, 600.0, 2048, 600, 1.0, 64.0) * 0.7
                + lattice_noise(self.seed + 406, 0.0, 600.0, 2048, 600, 1.0, 16.0) * 0.3
            )
        return self._cloud_cache

    # -- occluders -------------------------------------------------------------------------------

    def _agents(self, conditions: RenderConditions, pose: np.ndarray) -> list[tuple[Agent, float]]:
        """The people and vehicles near the camera at this time, with their ground heights."""
        out: list[Agent] = []
        x, y = pose[0, 3], pose[1, 3]
        if conditions.occluders and self.layout.agents:
            if self._agent_boxes is None:
                self._agent_boxes = np.array(
                    [[*a.points.min(axis=0), *a.points.max(axis=0)] for a in self.layout.agents], np.float64
                )
            box = self._agent_boxes
            near = (box[:, 0] < x + 60) & (box[:, 2] > x - 60) & (box[:, 1] < y + 60) & (box[:, 3] > y - 60)
            for i in np.flatnonzero(near):
                agent = self.layout.agents[int(i)]
                p, _, _ = agent.state(conditions.time)
                if abs(p[0] - x) < 60 and abs(p[1] - y) < 60:
                    out.append(agent)
        if conditions.extra_occluders:
            rng = rng_for(self.seed, 411, conditions.noise_seed)
            heading = math.atan2(pose[1, 0], pose[0, 0])
            for _ in range(conditions.extra_occluders):
                fwd, side = rng.uniform(1.2, 7.0), rng.uniform(-2.5, 2.5)
                px = x + fwd * math.cos(heading) - side * math.sin(heading)
                py = y + fwd * math.sin(heading) + side * math.cos(heading)
                a = rng.uniform(-math.pi, math.pi)
                pts = np.array([[px, py], [px + math.cos(a) * 0.01, py + math.sin(a) * 0.01]])
                colours = (
                    tuple(int(v) for v in rng.integers(20, 230, 3)),
                    tuple(int(v) for v in rng.integers(20, 160, 3)),
                    tuple(int(v) for v in rng.integers(140, 235, 3)),
                    (30, 30, 30),
                )
                out.append(Agent("pedestrian", pts, 0.0, 0.0, 0.0, (0.3, 0.45, float(rng.uniform(1.55, 1.9))), colours))  # type: ignore[arg-type]
        if not out:
            return []
        xy = np.array([a.state(conditions.time)[0] for a in out])
        z = self.terrain.height(xy[:, 0], xy[:, 1])
        return [(a, float(zz)) for a, zz in zip(out, z, strict=True)]

    def _agent_shadows(self, agents: list[tuple[Agent, float]], cam: np.ndarray) -> np.ndarray | None:
        """Shadow mask (float, 1 = shadow) of the people and vehicles on the ground, or None if none shows."""
        h, w = self.height, self.width
        mask = np.zeros((h, w), np.float32)
        world_to_cam = np.linalg.inv(cam)
        off = self.sun.shadow_offset
        drawn = False
        for agent, z0 in agents:
            p, heading, _ = agent.state(self.scenery._time)
            length, width, height = agent.size
            if agent.kind == "pedestrian":
                a = np.linspace(0, 2 * math.pi, 16, endpoint=False)
                body = np.stack([0.18 * np.cos(a), 0.18 * np.sin(a)], axis=1)
                ground = np.concatenate([p + body, p + off * height * 0.92 + body * 0.8])
            else:
                c, s = math.cos(heading), math.sin(heading)
                fp = np.array(
                    [
                        [length / 2, width / 2],
                        [-length / 2, width / 2],
                        [-length / 2, -width / 2],
                        [length / 2, -width / 2],
                    ]
                ) @ np.array([[c, s], [-s, c]])
                ground = np.concatenate([p + fp, p + fp + off * height])
            hull = cv2.convexHull(ground.astype(np.float32))[:, 0, :].astype(np.float64)
            pts = np.column_stack([hull, np.full(len(hull), z0 + 0.01), np.ones(len(hull))])
            pc = (pts @ world_to_cam.T)[:, :3]
            from sgf_plugins.world.scenery import clip_near

            pc = clip_near(pc)
            if len(pc) < 3:
                continue
            uv = np.stack(
                [self.K[0, 0] * pc[:, 0] / pc[:, 2] + self.K[0, 2], self.K[1, 1] * pc[:, 1] / pc[:, 2] + self.K[1, 2]],
                1,
            )
            if np.abs(uv).max() > 1e5:
                continue
            cv2.fillPoly(mask, [np.round(uv * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
            drawn = True
        return mask if drawn else None

    # -- sensor ----------------------------------------------------------------------------------

    def _expose(self, image: np.ndarray, conditions: RenderConditions) -> np.ndarray:
        """Camera gain, read and shot noise (approximated per frame), and 8-bit saturation."""
        gain = conditions.exposure * (NIGHT_GAIN if conditions.night else 1.0)
        if conditions.sensor_noise:
            rng = rng_for(self.seed, 421, conditions.noise_seed)
            k = int(rng.integers(len(self.noise_bank)))
            oy, ox = (int(v) for v in rng.integers(0, 32, 2))
            noise = self.noise_bank[k, oy : oy + self.height, ox : ox + self.width]
            sigma = (2.4 if conditions.night else 1.3) / gain
            cv2.scaleAdd(noise, sigma, image, dst=image)
        return cv2.convertScaleAbs(image, alpha=gain)


def _detail_texture(rng: np.random.Generator, size: int = 600) -> np.ndarray:
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


def _remap(src: np.ndarray, maps: np.ndarray, interpolation: int) -> np.ndarray:
    """``cv2.remap`` with one two-channel float map and wrap-around borders (the toroidal mosaics)."""
    out: np.ndarray = cv2.remap(src, maps, None, interpolation, borderMode=cv2.BORDER_WRAP)  # type: ignore[call-overload]
    return out
