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

import time
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_plugins.world.conditions import RenderConditions
from sgf_plugins.world.ground import GroundTexture, detail_texture
from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.noise import rng_for
from sgf_plugins.world.occluders import Occluders
from sgf_plugins.world.raycast import OFFSET, STEP, RayCaster
from sgf_plugins.world.scenery import Scenery
from sgf_plugins.world.sensor import Sensor
from sgf_plugins.world.sky import SkyAndLight
from sgf_plugins.world.sun import Sun
from sgf_plugins.world.terrain import Terrain
from sgf_plugins.world.texture import LEVELS

#: Fixed-point scale of the light factor (light x gain in [0, 255 / LIGHT_SCALE]).
LIGHT_SCALE = 64.0


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


class Renderer:
    """Renders camera images and marking-id images of the campus for any base pose.

    Its collaborators: the ray caster (rays on the terrain), the ground texture (tile mosaics and
    grain), sky and light, the occluders (people and vehicles, their shadows), the scenery
    (walls, trees, lamps drawn over the ground) and the sensor (vignetting and read noise).
    """

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
        intr = calibration.intrinsics
        self.width, self.height = intr.width, intr.height
        self.K = intr.matrix
        self.camera_to_base = calibration.camera_to_base_matrix
        self.caster = RayCaster(terrain, calibration)
        # one stream for the sensor's read noise bank, then the ground's grain
        rng = rng_for(seed, 401)
        self.sensor = Sensor(self.caster, seed, rng)
        detail = detail_texture(rng)
        self.ground_texture = GroundTexture(layout, sun, seed, clutter, self.width, self.height, detail)
        self.generator = self.ground_texture.generator
        self.cache = self.ground_texture.cache
        self.mosaics = self.ground_texture.mosaics
        self.scenery = Scenery(layout, seed, terrain.height)
        self.sky = SkyAndLight(layout, self.scenery.lamp_z, sun, seed, self.caster)
        size = (self.width, self.height)
        self.occluders = Occluders(layout, terrain, sun, seed, self.camera_to_base, self.K, size)
        self.stopwatch = Stopwatch()

    def render(self, pose: np.ndarray, conditions: RenderConditions) -> RenderLayers:
        """Render the camera of a robot whose base is at ``pose`` (4x4, world frame)."""
        watch = self.stopwatch
        watch.start()
        cam = pose @ self.camera_to_base
        rot, centre = cam[:3, :3], cam[:3, 3]
        dirs = self.caster.rays @ rot.T
        t, hit, gx, gy, bumpy = self.caster.intersect(centre, dirs, float(pose[2, 3]))
        pts = centre + t[..., None] * dirs
        horiz = np.hypot(pts[..., 0] - centre[0], pts[..., 1] - centre[1])
        # 1. level of detail per sample; the tiles each level needs are loaded into its mosaic
        watch.lap("ray cast")
        weights = self.ground_texture.levels(pose, pts, hit, t, conditions.far_field)
        weight_sum = weights.sum(axis=0)
        hit &= weight_sum > 0.0
        # ground samples whose weights do not sum to one (a level's window ran out)
        short = bool((weight_sum[hit] < 0.999).any())
        watch.lap("levels and tiles")
        # 2. light and haze per sample
        night = conditions.night
        light = self.sky.lighting(pose, conditions)
        normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        ground_light = self.sky.ground_light(pts, normal, light)
        haze = 1.0 - np.exp(-horiz / (900.0 if not night else 300.0))
        haze = np.where(hit, np.maximum(haze, np.clip((horiz - 95.0) / 30.0, 0.0, 1.0)), 1.0)
        # L0 texel coordinates (small numbers: relative to a multiple of the mosaic size)
        lv0, m0 = LEVELS[0], self.ground_texture.mosaics[0]
        shift = m0.shift
        # Around bumps the samples keep their smooth-ground hit (the bump faces are ray cast per
        # pixel below), so that interpolation between samples stays exact for the ground.
        t_map = np.where(bumpy, self.caster.smooth_hits[0], t)
        ground_pts = centre + t_map[..., None] * dirs
        mx = np.where(hit, ground_pts[..., 0] / lv0.res - 0.5 - shift[0], 0.0)
        my = np.where(hit, -ground_pts[..., 1] / lv0.res - 0.5 - shift[1], 0.0)
        depth = np.where(hit, t_map, 1e4)
        # Texel coordinates over depth, and inverse depth, are linear in the pixel coordinates on a
        # plane: interpolating them and dividing is exact on flat ground (perspective-correct).
        inv = np.where(hit, 1.0 / np.maximum(t_map, 1e-3), 1e-4)
        hx, hy, inv_f = self.caster.upsample_planes([mx * inv, my * inv, inv])
        maps = cv2.merge([cv2.divide(hx, inv_f), cv2.divide(hy, inv_f)])
        light_f, depth_f = self.caster.upsample_planes([ground_light * self.sensor.vignette, depth])
        if bumpy.any():
            self.caster.refine_bumps(maps, inv_f, depth_f, bumpy, cam, shift)
        # rows below ``top`` see only near ground (level 0, inside its window): the fast path
        pure_coarse = ((weights[0] == 1.0) & hit).all(axis=1)
        full_rows = np.arange(self.height)
        b = np.floor((full_rows + OFFSET) / STEP).astype(np.int64)
        pure_row = pure_coarse[np.clip(b, 0, self.caster.nv - 1)] & pure_coarse[np.clip(b + 1, 0, self.caster.nv - 1)]
        not_pure = np.flatnonzero(~pure_row)
        top = int(not_pure[-1]) + 1 if not_pure.size else 0
        h, w = self.height, self.width
        band = max(top, 1)
        *weights_f, haze_f, hit_f = self.caster.upsample_planes([*weights, haze, hit], band)
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
            self.ground_texture.blend_levels(rgba, ids, maps, weights_f, ground, top, shift, short)
        watch.lap("far ground lookup")
        # 3. shadows of people and vehicles, light, haze, sky
        self.scenery.set_frame(conditions.time, cam)
        agents = self.occluders.agents(conditions, pose) if conditions.occluders or conditions.extra_occluders else []
        if not night:
            # sunlit fraction x sun + ambient, both vignetted
            sunlit = cv2.extractChannel(rgba, 3)
            if agents:
                self.occluders.shadows(agents, cam, sunlit)
            light_f = cv2.multiply(sunlit, light_f, dtype=cv2.CV_32F)
            cv2.scaleAdd(self.sensor.vignette_f, light.ambient, light_f, dst=light_f)
        watch.lap("shadows")
        self.ground_texture.add_detail(light_f, maps, depth_f, t, hit, top)
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
            horizon = np.clip(self.sky.horizon_colour(night) * gain, 0.0, 255.0)
            red, green, blue = (float(v) for v in horizon)
            hazed = cv2.add(clear, cv2.multiply(haze3, (red, green, blue, 0.0), scale=1.0 / 255.0))  # type: ignore[call-overload]
            if r_sky:
                cv2.copyTo(self.sky.sky(dirs, r_sky, night, gain), (~ground[:r_sky]).view(np.uint8), hazed[:r_sky])
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
            image = self.sensor.noise(image, conditions)
        watch.lap("exposure and noise")
        return RenderLayers(image, ids.astype(np.int32), depth_f, occluded, maps, shift, ground)
