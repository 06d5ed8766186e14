"""The camera: every pixel's ray cast onto the terrain, textured from tile mosaics, lit, and exposed.

Per frame the rays of a coarse grid (every 8th pixel) are intersected with the height field
(plane start, Newton steps on the hills, a march through the height band of nearby bumps). The
hit points are carried to every pixel perspective-correctly: texel coordinates over depth and
inverse depth are interpolated bilinearly and divided, which is exact on a plane and within a
few hundredths of a pixel on the campus hills. Pixels that see a speed bump are ray cast one by
one (its faces are too sharp to interpolate). Ground colour and marking ids come from one
``cv2.remap`` per level of detail in window mosaics of generated tiles; sky, walls, trees, lamps,
people and vehicles are drawn on top; the camera gain, sensor noise and 8-bit output come last.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_plugins.world.layout import Agent, CampusLayout
from sgf_plugins.world.noise import lattice_noise, rng_for
from sgf_plugins.world.scenery import Lighting, PlacedAgent, Scenery, clip_near
from sgf_plugins.world.terrain import Terrain
from sgf_plugins.world.texture import LEVELS, Level, Sun, TileCache, TileGenerator

#: The ray grid: every STEP-th pixel; its samples sit at pixel coordinates STEP k - OFFSET.
STEP = 8
OFFSET = (STEP + 1) / 2
MAX_DISTANCE = 150.0
NIGHT_GAIN = 2.0
#: Fixed-point scale of the light factor (light x gain in [0, 255 / LIGHT_SCALE]).
LIGHT_SCALE = 64.0
#: Speed bumps and rough patches farther than this from the camera are not ray cast (sub-pixel).
DETAIL_RADIUS = 45.0
#: Near-camera grain: texel size (m) and the depth (m) up to which it shows.
DETAIL_TEXEL = 0.0025
DETAIL_DEPTH = 4.0


#: A person's footprint (16 points on a circle of 0.18 m), for their shadow.
_BODY = 0.18 * np.stack([np.cos(np.arange(16) * math.pi / 8), np.sin(np.arange(16) * math.pi / 8)], axis=1)


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


class Stopwatch:
    """Optional per-stage CPU timing of the renderer (off unless ``enabled``; used by the benchmark)."""

    def __init__(self) -> None:
        self.enabled = False
        self.totals: dict[str, float] = {}
        self.frames = 0
        self._last = 0.0

    def start(self) -> None:
        """Begin a frame."""
        if self.enabled:
            self.frames += 1
            self._last = time.process_time()

    def lap(self, name: str) -> None:
        """Charge the CPU time since the last lap to ``name``."""
        if self.enabled:
            now = time.process_time()
            self.totals[name] = self.totals.get(name, 0.0) + now - self._last
            self._last = now

    def report(self) -> dict[str, float]:
        """Mean milliseconds per frame of each stage."""
        return {k: 1000.0 * v / max(self.frames, 1) for k, v in self.totals.items()}


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


class Renderer:
    """Renders camera images and marking-id images of the campus for any base pose."""

    def __init__(
        self,
        layout: CampusLayout,
        terrain: Terrain,
        calibration: Calibration,
        sun: Sun,
        seed: int,
        clutter: float = 1.0,
    ) -> None:
        self.layout = layout
        self.terrain = terrain
        self.calibration = calibration
        self.sun = sun
        self.seed = seed
        self.generator = TileGenerator(layout, sun, seed, clutter)
        self.cache = TileCache(self.generator)
        self.mosaics = [Mosaic(level) for level in LEVELS]
        self.scenery = Scenery(layout, seed, terrain.height)
        intr = calibration.intrinsics
        self.width, self.height = intr.width, intr.height
        self.K = intr.matrix
        self.camera_to_base = calibration.camera_to_base_matrix
        # Coarse samples at u = STEP a - OFFSET (and v alike): resizing STEP times then cropping
        # STEP gives exact bilinear interpolation at every integer pixel (see _upsample).
        self.nu = math.ceil(self.width / STEP) + 2
        self.nv = math.ceil(self.height / STEP) + 2
        us = STEP * np.arange(self.nu) - OFFSET
        vs = STEP * np.arange(self.nv) - OFFSET
        uu, vv = np.meshgrid(us, vs)
        self.rays = np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], axis=-1)
        r = np.hypot((uu - intr.cx) / (0.5 * self.width), (vv - intr.cy) / (0.5 * self.height)) / math.sqrt(2)
        self.vignette = (1.0 - 0.22 * r**2).astype(np.float32)
        rng = rng_for(seed, 401)
        bank = 128.0 + 32.0 * rng.standard_normal((2, self.height + 32, self.width + 32, 3))
        self.noise_bank = np.clip(bank, 0, 255).astype(np.uint8)
        self._agent_boxes: np.ndarray | None = None
        self._smooth_hits = np.zeros((4, self.nv, self.nu))
        self.detail = _detail_texture(rng)
        self.stopwatch = Stopwatch()
        self.vignette_f = np.ascontiguousarray(self._upsample(self.vignette))  # at every pixel

    # -- public --------------------------------------------------------------------------------

    def render(self, pose: np.ndarray, conditions: RenderConditions) -> RenderLayers:
        """Render the camera of a robot whose base is at ``pose`` (4x4, world frame)."""
        watch = self.stopwatch
        watch.start()
        cam = pose @ self.camera_to_base
        rot, centre = cam[:3, :3], cam[:3, 3]
        dirs = self.rays @ rot.T
        t, hit, gx, gy, bumpy = self._intersect(centre, dirs, float(pose[2, 3]))
        pts = centre + t[..., None] * dirs
        horiz = np.hypot(pts[..., 0] - centre[0], pts[..., 1] - centre[1])
        # 1. level of detail per sample; the tiles each level needs are loaded into its mosaic
        watch.lap("ray cast")
        weights = self._levels(pose, pts, hit, t, conditions.far_field)
        weight_sum = weights.sum(axis=0)
        hit &= weight_sum > 0.0
        # ground samples whose weights do not sum to one (a level's window ran out)
        short = bool((weight_sum[hit] < 0.999).any())
        watch.lap("levels and tiles")
        # 2. light and haze per sample
        night = conditions.night
        light = self._lighting(pose, conditions)
        normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        ground_light = self._ground_light(pts, normal, light)
        haze = 1.0 - np.exp(-horiz / (900.0 if not night else 300.0))
        haze = np.where(hit, np.maximum(haze, np.clip((horiz - 95.0) / 30.0, 0.0, 1.0)), 1.0)
        # L0 texel coordinates (small numbers: relative to a multiple of the mosaic size)
        lv0, m0 = LEVELS[0], self.mosaics[0]
        shift = m0.shift
        # Around bumps the samples keep their smooth-ground hit (the bump faces are ray cast per
        # pixel below), so that interpolation between samples stays exact for the ground.
        t_map = np.where(bumpy, self._smooth_hits[0], t)
        ground_pts = centre + t_map[..., None] * dirs
        mx = np.where(hit, ground_pts[..., 0] / lv0.res - 0.5 - shift[0], 0.0)
        my = np.where(hit, -ground_pts[..., 1] / lv0.res - 0.5 - shift[1], 0.0)
        depth = np.where(hit, t_map, 1e4)
        # Texel coordinates over depth, and inverse depth, are linear in the pixel coordinates on a
        # plane: interpolating them and dividing is exact on flat ground (perspective-correct).
        inv = np.where(hit, 1.0 / np.maximum(t_map, 1e-3), 1e-4)
        hx, hy, inv_f = self._upsample_planes([mx * inv, my * inv, inv])
        maps = cv2.merge([cv2.divide(hx, inv_f), cv2.divide(hy, inv_f)])
        light_f, depth_f = self._upsample_planes([ground_light * self.vignette, depth])
        if bumpy.any():
            self._refine_bumps(maps, inv_f, depth_f, bumpy, cam, shift)
        # rows below ``top`` see only near ground (level 0, inside its window): the fast path
        pure_coarse = ((weights[0] == 1.0) & hit).all(axis=1)
        full_rows = np.arange(self.height)
        b = np.floor((full_rows + OFFSET) / STEP).astype(np.int64)
        pure_row = pure_coarse[np.clip(b, 0, self.nv - 1)] & pure_coarse[np.clip(b + 1, 0, self.nv - 1)]
        not_pure = np.flatnonzero(~pure_row)
        top = int(not_pure[-1]) + 1 if not_pure.size else 0
        h, w = self.height, self.width
        band = max(top, 1)
        *weights_f, haze_f, hit_f = self._upsample_planes([*weights, haze, hit], band)
        ground_top = hit_f >= 0.999
        ground = np.ones((h, w), bool)
        ground[:band] = ground_top
        watch.lap("light and upsampling")
        rgba = np.zeros((h, w, 4), np.uint8)
        ids = np.zeros((h, w), np.uint16)
        if top < h:
            cv2.remap(m0.rgba, maps[top:], None, cv2.INTER_LINEAR, dst=rgba[top:], borderMode=cv2.BORDER_REPLICATE)  # type: ignore[call-overload]
            cv2.remap(m0.ids, maps[top:], None, cv2.INTER_NEAREST, dst=ids[top:], borderMode=cv2.BORDER_REPLICATE)  # type: ignore[call-overload]
        watch.lap("near ground lookup")
        if top > 0:
            self._blend_levels(rgba, ids, maps, weights_f, ground, top, shift, short)
        watch.lap("far ground lookup")
        # 3. shadows of people and vehicles, light, haze, sky
        self.scenery.set_frame(conditions.time, cam)
        agents = self._agents(conditions, pose) if conditions.occluders or conditions.extra_occluders else []
        if not night:
            # sunlit fraction x sun + ambient, both vignetted
            sunlit = cv2.extractChannel(rgba, 3)
            if agents:
                self._agent_shadows(agents, cam, sunlit)
            light_f = cv2.multiply(sunlit, light_f, dtype=cv2.CV_32F)
            cv2.scaleAdd(self.vignette_f, light.ambient, light_f, dst=light_f)
        watch.lap("shadows")
        self._add_detail(light_f, maps, depth_f, t, hit, top)
        watch.lap("grain")
        # light times the camera gain, in fixed point (1/LIGHT_SCALE), multiplied into the albedo
        gain = light.gain
        light8 = cv2.convertScaleAbs(light_f, alpha=LIGHT_SCALE * gain)
        albedo = cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB)
        image = cv2.multiply(albedo, cv2.cvtColor(light8, cv2.COLOR_GRAY2RGB), scale=1.0 / LIGHT_SCALE)
        watch.lap("shading")
        # haze reaches further down the image than the sky: each over its own rows
        sky_rows = np.flatnonzero(~ground[:band].all(axis=1))
        haze_rows = np.flatnonzero((haze_f > 0.01).any(axis=1))
        r_sky = int(sky_rows[-1]) + 1 if sky_rows.size else 0
        r1 = max(r_sky, int(haze_rows[-1]) + 1 if haze_rows.size else 0)
        if r1:
            # image (1 - haze) + horizon haze in uint8 arithmetic (haze in 1/255): far cheaper than blendLinear
            haze3 = cv2.cvtColor(cv2.convertScaleAbs(haze_f[:r1], alpha=255.0), cv2.COLOR_GRAY2RGB)
            clear = cv2.multiply(image[:r1], cv2.bitwise_not(haze3), scale=1.0 / 255.0)
            horizon = np.clip(self._horizon_colour(night) * gain, 0.0, 255.0)
            red, green, blue = (float(v) for v in horizon)
            hazed = cv2.add(clear, cv2.multiply(haze3, (red, green, blue, 0.0), scale=1.0 / 255.0))  # type: ignore[call-overload]
            if r_sky:
                cv2.copyTo(self._sky(dirs, r_sky, night, gain), (~ground[:r_sky]).view(np.uint8), hazed[:r_sky])
            image[:r1] = hazed
        watch.lap("sky and haze")
        # 4. things above the ground
        occlusion = np.zeros((h, w), np.uint8)
        self.scenery.draw(image, occlusion, depth_f, cam, self.K, light, agents, conditions.far_field)
        occluded = occlusion > 0
        ids[occluded] = 0
        watch.lap("walls, trees, people")
        # 5. sensor noise
        if conditions.sensor_noise:
            image = self._noise(image, conditions)
        watch.lap("exposure and noise")
        return RenderLayers(image, ids.astype(np.int32), depth_f, occluded, maps, shift, ground)

    def _levels(self, pose: np.ndarray, pts: np.ndarray, hit: np.ndarray, t: np.ndarray, far_field: bool) -> np.ndarray:
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

    def _blend_levels(
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

    def _add_detail(
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

    # -- geometry ------------------------------------------------------------------------------

    def _intersect(
        self, centre: np.ndarray, dirs: np.ndarray, z_ref: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ray parameter (camera depth) of each sample's hit, whether it hits, dH/dx, dH/dy, near a bump.

        1. Newton steps on the smooth hills, from the horizontal plane under the robot (robust:
           slopes stay under 10 %). 2. Rays whose hit lies near a speed bump or rough patch are
           marched through the band of heights the feature spans, and the first crossing is
           refined by bisection, so that the near face of a bump is found, not the ground behind.
        """
        shape = dirs.shape[:2]
        d = dirs.reshape(-1, 3)
        n = len(d)
        t = np.full(n, 1e4)
        gx = np.zeros(n)
        gy = np.zeros(n)
        hit = np.zeros(n, bool)
        down = np.flatnonzero(d[:, 2] < -1e-9)
        if down.size == 0:
            return t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape), hit.reshape(shape)
        dd = d[down]
        t_max = MAX_DISTANCE / np.sqrt(dd[:, 0] ** 2 + dd[:, 1] ** 2 + 1e-18)
        td = np.minimum((z_ref - centre[2]) / dd[:, 2], t_max)
        gxd = np.zeros(len(down))
        gyd = np.zeros(len(down))
        if self.terrain.flat:
            t[down] = td
            hit[down] = td < t_max
            return t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape), np.zeros(shape, bool)
        residual = np.full(len(down), np.inf)
        slope = np.full(len(down), -1.0)
        active = np.arange(len(down))
        for _ in range(4):
            ta, da = td[active], dd[active]
            xa = centre[0] + ta * da[:, 0]
            ya = centre[1] + ta * da[:, 1]
            hgt, gxa, gya = self.terrain.hill_heights(xa, ya, single=True)
            f = centre[2] + ta * da[:, 2] - hgt
            fp = da[:, 2] - gxa * da[:, 0] - gya * da[:, 1]
            step = f / np.minimum(fp, -1e-6)
            gxd[active], gyd[active], residual[active], slope[active] = gxa, gya, np.abs(f), fp
            td[active] = np.clip(ta - step, 0.0, t_max[active])
            active = active[np.abs(step) > 1e-3 + 2e-4 * ta]
            if active.size == 0:
                break
        ok = (residual < 0.02) & (td > 0.0) & (td < t_max * 0.999)
        # the smooth solution, kept for the exact pixels around speed bumps
        smooth = np.zeros((4, n))
        smooth[0, down], smooth[1, down], smooth[2, down], smooth[3, down] = td, slope, gxd, gyd
        self._smooth_hits = smooth.reshape(4, *shape)
        near_feature = (float(centre[0]), float(centre[1]), DETAIL_RADIUS)
        x = centre[0] + td * dd[:, 0]
        y = centre[1] + td * dd[:, 1]
        # rough paving (low, gentle waves): two Newton steps on the full height field
        rough = self._near_boxes(centre, x, y, self.terrain.detail_boxes(*near_feature, kind="rough"), 0.5)
        idx = np.flatnonzero(rough & ok & (td < DETAIL_RADIUS))
        for _ in range(2 if idx.size else 0):
            ti, di = td[idx], dd[idx]
            hgt, gxi, gyi = self.terrain.height_and_gradient(
                centre[0] + ti * di[:, 0], centre[1] + ti * di[:, 1], near_feature
            )
            f = centre[2] + ti * di[:, 2] - hgt
            fp = np.minimum(di[:, 2] - gxi * di[:, 0] - gyi * di[:, 1], -1e-3)
            td[idx] = np.clip(ti - np.clip(f / fp, -0.5, 0.5), 0.0, t_max[idx])
            gxd[idx], gyd[idx] = gxi, gyi
        # speed bumps (tall, steep): march through their height band for the first crossing
        bumps = self._near_boxes(centre, x, y, self.terrain.detail_boxes(*near_feature, kind="bumps"), 2.0)
        idx = np.flatnonzero(bumps & ok & (td < DETAIL_RADIUS))
        bumpy = np.zeros(n, bool)
        if idx.size:
            before = td[idx]
            td[idx], gxd[idx], gyd[idx] = self._march(centre, dd[idx], before, slope[idx], gxd[idx], gyd[idx])
            # the samples whose ray meets a bump (on it, or cut short by it) need exact pixels around them
            xi, yi = centre[0] + td[idx] * dd[idx, 0], centre[1] + td[idx] * dd[idx, 1]
            on_bump, _, _ = self.terrain.height_and_gradient(xi, yi, near_feature, smooth=False, rough=False)
            bumpy[down[idx]] = (on_bump > 0.002) | (np.abs(td[idx] - before) > 0.01)
        t[down], hit[down], gx[down], gy[down] = td, ok, gxd, gyd
        return (t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape), bumpy.reshape(shape))

    def _refine_bumps(
        self,
        maps: np.ndarray,
        inverse_depth: np.ndarray,
        depth: np.ndarray,
        bumpy: np.ndarray,
        cam: np.ndarray,
        shift: tuple[int, int],
    ) -> None:
        """Ray cast exactly the pixels that see a speed bump (its faces are too sharp to interpolate).

        The maps hold every pixel's smooth-ground hit; the pixels whose hit lies within a bump's
        reach (its box grown by the 0.8 m a bump can hide behind it) are marched through its
        height band and their ground point and depth replaced.
        """
        rows = np.flatnonzero(cv2.dilate(bumpy.astype(np.uint8), np.ones((3, 3), np.uint8)).any(axis=1))
        r0 = max(0, STEP * int(rows[0]) - STEP)
        r1 = min(self.height, STEP * int(rows[-1]) + STEP)
        res = LEVELS[0].res
        x = (maps[r0:r1, :, 0] + np.float32(0.5 + shift[0])) * np.float32(res)
        y = -(maps[r0:r1, :, 1] + np.float32(0.5 + shift[1])) * np.float32(res)
        c = cam[:3, 3]
        reach = np.zeros(x.shape, bool)
        for b in self.terrain.bumps_near(float(c[0]), float(c[1]), DETAIL_RADIUS):
            rx, ry = x - np.float32(b.centre[0]), y - np.float32(b.centre[1])
            along = rx * np.float32(b.direction[0]) + ry * np.float32(b.direction[1])
            across = ry * np.float32(b.direction[0]) - rx * np.float32(b.direction[1])
            reach |= (np.abs(along) < b.half_length + 0.8) & (np.abs(across) < b.half_width + 0.4)
        vs, us = np.nonzero(reach)
        if vs.size == 0:
            return
        vs = vs + r0
        _, slope_s, gx_s, gy_s = self._smooth_hits
        coarse = np.stack([slope_s, gx_s, gy_s], axis=-1).astype(np.float32)
        up = self._upsample(coarse, rows=r1, start=r0)[vs - r0, us].astype(np.float64)
        intr = self.calibration.intrinsics
        d = np.stack([(us - intr.cx) / intr.fx, (vs - intr.cy) / intr.fy, np.ones(us.size)], axis=1) @ cam[:3, :3].T
        t = np.clip(1.0 / np.maximum(inverse_depth[vs, us].astype(np.float64), 1e-4), 0.05, 2 * DETAIL_RADIUS)
        t, _, _ = self._march(c, d, t, np.minimum(up[:, 0], -1e-3), up[:, 1], up[:, 2], rough=False)
        maps[vs, us, 0] = (c[0] + t * d[:, 0]) / res - 0.5 - shift[0]
        maps[vs, us, 1] = -(c[1] + t * d[:, 1]) / res - 0.5 - shift[1]
        depth[vs, us] = t

    def _near_boxes(
        self, centre: np.ndarray, x: np.ndarray, y: np.ndarray, boxes: np.ndarray, grow: float
    ) -> np.ndarray:
        """Whether points lie in any of the boxes grown by ``grow`` m (via 1 m cells around the camera)."""
        if len(boxes) == 0:
            return np.zeros(len(x), bool)
        half = int(DETAIL_RADIUS) + 4
        grid = np.zeros((2 * half, 2 * half), bool)
        for x0, y0, x1, y1 in boxes:
            c0 = max(0, int((x0 - grow - centre[0]) // 1.0) + half)
            c1 = min(2 * half, int((x1 + grow - centre[0]) // 1.0) + half + 1)
            r0 = max(0, int((y0 - grow - centre[1]) // 1.0) + half)
            r1 = min(2 * half, int((y1 + grow - centre[1]) // 1.0) + half + 1)
            grid[r0:r1, c0:c1] = True
        ci = np.clip(np.floor(x - centre[0]).astype(np.int64) + half, 0, 2 * half - 1)
        ri = np.clip(np.floor(y - centre[1]).astype(np.int64) + half, 0, 2 * half - 1)
        found: np.ndarray = grid[ri, ci]
        return found

    def _march(
        self,
        centre: np.ndarray,
        d: np.ndarray,
        t_smooth: np.ndarray,
        slope: np.ndarray,
        gx: np.ndarray,
        gy: np.ndarray,
        rough: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First crossing of rays with the full terrain within the height band of bumps and patches.

        Within the band the hills are linear (``f = slope (t - t_smooth)`` is the ray's height over
        them), so only the bumps and patches are evaluated along the ray.
        """
        near = (float(centre[0]), float(centre[1]), DETAIL_RADIUS)
        rate = np.maximum(-slope, 1e-3)  # metres of height lost per unit of t over the smooth ground
        lo = np.maximum(t_smooth - 0.16 / rate, 1e-3)
        hi = t_smooth + 0.04 / rate
        n = 8
        ts = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, n)[None, :]

        def clearance(t: np.ndarray) -> np.ndarray:
            """Height of the ray over the ground (hills linearised) at ray parameters ``t``."""
            x = centre[0] + t * d[:, 0:1] if t.ndim == 2 else centre[0] + t * d[:, 0]
            y = centre[1] + t * d[:, 1:2] if t.ndim == 2 else centre[1] + t * d[:, 1]
            bump, _, _ = self.terrain.height_and_gradient(x, y, near, smooth=False, rough=rough, gradient=False)
            base = slope[:, None] * (t - t_smooth[:, None]) if t.ndim == 2 else slope * (t - t_smooth)
            out: np.ndarray = base - bump
            return out

        f = clearance(ts)
        below = f <= 0.0
        first = np.where(below.any(axis=1), below.argmax(axis=1), n - 1)
        rows = np.arange(len(d))
        a, b = ts[rows, np.maximum(first - 1, 0)], ts[rows, first]
        fa, fb = f[rows, np.maximum(first - 1, 0)], f[rows, first]
        for _ in range(3):
            m = 0.5 * (a + b)
            fm = clearance(m)
            up = fm > 0.0
            a, fa = np.where(up, m, a), np.where(up, fm, fa)
            b, fb = np.where(up, b, m), np.where(up, fb, fm)
        # a last secant step inside the bracket
        t = np.where(fa - fb > 1e-12, a + (b - a) * fa / np.maximum(fa - fb, 1e-12), 0.5 * (a + b))
        _, dx, dy = self.terrain.height_and_gradient(
            centre[0] + t * d[:, 0], centre[1] + t * d[:, 1], near, smooth=False, rough=rough
        )
        return t, gx + dx, gy + dy

    def _upsample_planes(self, planes: list[np.ndarray], rows: int | None = None) -> list[np.ndarray]:
        """``_upsample`` of single-channel planes (each resized alone: several times faster than interleaved)."""
        return [self._upsample(np.ascontiguousarray(p, np.float32), rows) for p in planes]

    def _upsample(self, coarse: np.ndarray, rows: int | None = None, start: int = 0) -> np.ndarray:
        """Exact bilinear interpolation of the coarse samples at every pixel of rows ``start .. rows - 1``.

        Coarse sample ``b`` sits at image row ``STEP b - OFFSET``; resizing a block of samples from
        ``b0`` STEP times puts image row ``v`` at block row ``v - STEP b0 + STEP``.
        """
        rows = self.height if rows is None else rows
        b0 = max(0, math.floor((start + OFFSET) / STEP) - 1)
        b1 = min(self.nv, math.ceil((rows - 1 + OFFSET) / STEP) + 2)
        big = cv2.resize(coarse[b0:b1], (self.nu * STEP, (b1 - b0) * STEP), interpolation=cv2.INTER_LINEAR)
        q0 = start - STEP * b0 + STEP
        return big[q0 : q0 + rows - start, STEP : STEP + self.width]

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
                lamps.append((np.array([lamp.position[0], lamp.position[1], z]), 2.5))
        return Lighting(
            night=night,
            ambient=0.03 if night else 0.5,
            sun=self.sun.direction,
            sun_strength=0.0 if night else 0.62,
            headlight_origin=origin,
            headlight_frame=pose[:3, :3].copy(),
            headlight_power=3.2 if headlight else 0.0,
            lamps=lamps,
            gain=conditions.exposure * (NIGHT_GAIN if night else 1.0),
        )

    def _ground_light(self, pts: np.ndarray, normal: np.ndarray, light: Lighting) -> np.ndarray:
        """Per-sample light: by day the sun's (times sunlit/255; the ambient is added per pixel), at night all of it."""
        if not light.night:
            cos_sun = np.clip(normal @ light.sun, 0.0, None) / max(light.sun[2], 1e-3)
            sun: np.ndarray = light.sun_strength * cos_sun / 255.0
            return sun
        s1 = np.full(pts.shape[:2], light.ambient)
        if light.headlight_power > 0:
            to = (pts - light.headlight_origin).reshape(-1, 3)
            r2 = np.maximum(np.einsum("ij,ij->i", to, to), 0.25)
            facing = np.maximum(-np.einsum("ij,ij->i", normal.reshape(-1, 3), to), 0.0) / np.sqrt(r2)
            s1 = s1 + (light.beam(to) * facing / r2).reshape(s1.shape)
        if light.lamps:
            # all lamps at once, the offsets expanded into matrix products (relative to the first
            # lamp: small numbers); power x facing / r2 with facing = max(0, -n.(p - q)) / r
            ref = light.lamps[0][0]
            p = (pts - ref).reshape(-1, 3)
            n = normal.reshape(-1, 3)
            q = np.array([pos for pos, _ in light.lamps]) - ref
            power = np.array([w for _, w in light.lamps])
            r2 = np.einsum("ij,ij->i", p, p)[:, None] - 2.0 * (p @ q.T) + np.einsum("ij,ij->i", q, q)
            np.maximum(r2, 1.0, out=r2)
            facing = (n @ q.T) - np.einsum("ij,ij->i", n, p)[:, None]
            np.maximum(facing, 0.0, out=facing)
            facing /= r2 * np.sqrt(r2)
            s1 = s1 + (facing @ power).reshape(s1.shape)
        return s1

    def _horizon_colour(self, night: bool) -> np.ndarray:
        return np.array([13, 14, 21], np.float32) if night else np.array([196, 206, 214], np.float32)

    def _sky(self, dirs: np.ndarray, rows: int, night: bool, gain: float) -> np.ndarray:
        """Sky of the top ``rows`` rows (uint8, exposed by ``gain``): a gradient with clouds, or a dark glow."""
        nb = min(self.nv, math.ceil((rows + OFFSET) / STEP) + 2)
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
        planes = self._upsample_planes([colour[..., k] for k in range(3)], rows)
        sky: np.ndarray = cv2.merge([cv2.convertScaleAbs(plane, alpha=gain) for plane in planes])
        return sky

    _cloud_cache: np.ndarray | None = None

    def _clouds(self) -> np.ndarray:
        if self._cloud_cache is None:
            self._cloud_cache = (
                lattice_noise(self.seed + 405, 0.0, 600.0, 2048, 600, 1.0, 64.0) * 0.7
                + lattice_noise(self.seed + 406, 0.0, 600.0, 2048, 600, 1.0, 16.0) * 0.3
            )
        return self._cloud_cache

    # -- occluders -------------------------------------------------------------------------------

    def _agents(self, conditions: RenderConditions, pose: np.ndarray) -> list[PlacedAgent]:
        """The people and vehicles near the camera at this time, where they are."""
        candidates: list[Agent] = []
        x, y = pose[0, 3], pose[1, 3]
        if conditions.occluders and self.layout.agents:
            if self._agent_boxes is None:
                self._agent_boxes = np.array(
                    [[*a.points.min(axis=0), *a.points.max(axis=0)] for a in self.layout.agents], np.float64
                )
            box = self._agent_boxes
            near = (box[:, 0] < x + 60) & (box[:, 2] > x - 60) & (box[:, 1] < y + 60) & (box[:, 3] > y - 60)
            candidates = [self.layout.agents[int(i)] for i in np.flatnonzero(near)]
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
                size = (0.3, 0.45, float(rng.uniform(1.55, 1.9)))
                candidates.append(Agent("pedestrian", pts, 0.0, 0.0, 0.0, size, colours))  # type: ignore[arg-type]
        states = [a.state(conditions.time) for a in candidates]
        cam_xy = (pose @ self.camera_to_base)[:2, 3]
        kept = [
            (a, s)
            for a, s in zip(candidates, states, strict=True)
            # within 60 m, and people step aside: nobody is closer than 1.2 m to the camera
            if abs(s[0][0] - x) < 60 and abs(s[0][1] - y) < 60 and math.hypot(*(s[0] - cam_xy)) > 1.2
        ]
        if not kept:
            return []
        xy = np.array([s[0] for _, s in kept])
        z = self.terrain.height(xy[:, 0], xy[:, 1])
        return [PlacedAgent(a, s[0], s[1], s[2], float(zz)) for (a, s), zz in zip(kept, z, strict=True)]

    def _agent_shadows(self, agents: list[PlacedAgent], cam: np.ndarray, sunlit: np.ndarray) -> None:
        """Darken the sunlit fraction (uint8) where people and vehicles shade the ground."""
        h, w = self.height, self.width
        world_to_cam = np.linalg.inv(cam)
        off = self.sun.shadow_offset
        for placed in agents:
            agent, p, heading, z0 = placed.agent, placed.position, placed.heading, placed.z
            length, width, height = agent.size
            if agent.kind == "pedestrian":
                body = _BODY
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
            pc = clip_near(pc)
            if len(pc) < 3:
                continue
            uv = np.stack(
                [self.K[0, 0] * pc[:, 0] / pc[:, 2] + self.K[0, 2], self.K[1, 1] * pc[:, 1] / pc[:, 2] + self.K[1, 2]],
                1,
            )
            if np.abs(uv).max() > 1e5:
                continue
            c0, c1 = max(0, math.floor(uv[:, 0].min())), min(w, math.ceil(uv[:, 0].max()) + 1)
            r0, r1 = max(0, math.floor(uv[:, 1].min())), min(h, math.ceil(uv[:, 1].max()) + 1)
            if c1 <= c0 or r1 <= r0:
                continue
            mask = np.zeros((r1 - r0, c1 - c0), np.float32)
            cv2.fillPoly(mask, [np.round((uv - [c0, r0]) * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
            roi = sunlit[r0:r1, c0:c1]
            roi[:] = cv2.multiply(roi, 1.0 - 0.85 * mask, dtype=cv2.CV_8U)

    # -- sensor ----------------------------------------------------------------------------------

    def _noise(self, image: np.ndarray, conditions: RenderConditions) -> np.ndarray:
        """Add the sensor's read noise (stronger at night, where the gain is high)."""
        rng = rng_for(self.seed, 421, conditions.noise_seed)
        k = int(rng.integers(len(self.noise_bank)))
        oy, ox = (int(v) for v in rng.integers(0, 32, 2))
        noise = self.noise_bank[k, oy : oy + self.height, ox : ox + self.width]
        sigma = 2.4 if conditions.night else 1.3
        # the bank holds 128 + 32 n (uint8): image + sigma n = image + sigma / 32 (bank - 128)
        out: np.ndarray = cv2.addWeighted(image, 1.0, noise, sigma / 32.0, -128.0 * sigma / 32.0)
        return out


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


def _remap(src: np.ndarray, maps: np.ndarray, interpolation: int, border: int = cv2.BORDER_REPLICATE) -> np.ndarray:
    """``cv2.remap`` with one two-channel float map."""
    out: np.ndarray = cv2.remap(src, maps, None, interpolation, borderMode=border)  # type: ignore[call-overload]
    return out
