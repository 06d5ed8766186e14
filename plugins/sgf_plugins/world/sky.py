"""Sky and light: the sun, the robot's headlight and the street lamps on the ground, and the sky above.

By day the ground is lit by the sun (with an ambient term) under a blue gradient with clouds;
at night by the headlight and the lamps near the robot under a dark glow, with a higher camera gain.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.conditions import RenderConditions
from sgf_plugins.world.drawing import Lighting
from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.noise import lattice_noise
from sgf_plugins.world.raycast import OFFSET, STEP, RayCaster
from sgf_plugins.world.sun import Sun

NIGHT_GAIN = 2.0


class SkyAndLight:
    """The light of a frame (sun or headlight and lamps), the light on the ground samples, and the sky."""

    def __init__(self, layout: CampusLayout, lamp_z: np.ndarray, sun: Sun, seed: int, caster: RayCaster) -> None:
        self.layout = layout
        self.lamp_z = lamp_z
        self.sun = sun
        self.seed = seed
        self.caster = caster

    def lighting(self, pose: np.ndarray, conditions: RenderConditions) -> Lighting:
        """The frame's light: the sun by day; at night the headlight (if on) and the lamps within 45 m."""
        night = conditions.night
        headlight = conditions.headlight if conditions.headlight is not None else night
        origin = (pose @ np.array([0.28, 0.0, 0.42, 1.0]))[:3]
        lamps: list[tuple[np.ndarray, float]] = []
        if night and conditions.street_lamps:
            x, y = pose[0, 3], pose[1, 3]
            for i in self.layout.lamp_index.query(x - 45, y - 45, x + 45, y + 45):
                lamp = self.layout.lamps[i]
                z = float(self.lamp_z[i]) + lamp.height
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

    def ground_light(self, pts: np.ndarray, normal: np.ndarray, light: Lighting) -> np.ndarray:
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

    def horizon_colour(self, night: bool) -> np.ndarray:
        """Colour of the sky at the horizon (and of the haze)."""
        return np.array([13, 14, 21], np.float32) if night else np.array([196, 206, 214], np.float32)

    def sky(self, dirs: np.ndarray, rows: int, night: bool, gain: float) -> np.ndarray:
        """Sky of the top ``rows`` rows (uint8, exposed by ``gain``): a gradient with clouds, or a dark glow."""
        nb = min(self.caster.nv, math.ceil((rows + OFFSET) / STEP) + 2)
        d = dirs[:nb]
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        elev = np.clip(d[..., 2], -0.05, 1.0)
        t = np.sqrt(np.clip(elev, 0.0, 1.0))[..., None]
        if night:
            colour = np.array([13, 14, 21], np.float32) * (1 - t) + np.array([3, 4, 9], np.float32) * t
        else:
            colour = self.horizon_colour(False) * (1 - t) + np.array([92, 138, 204], np.float32) * t
            az = np.arctan2(d[..., 1], d[..., 0])
            cu = ((az + math.pi) / (2 * math.pi) * 2048.0).astype(np.float32)
            cv = (np.clip(elev, 0.0, 1.0) * 600.0).astype(np.float32)
            clouds = cv2.remap(self._clouds(), cu, cv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            c = np.clip((clouds - 0.1) * 2.2, 0.0, 0.85)[..., None]
            colour = colour * (1 - c) + np.array([238, 240, 242], np.float32) * c
        planes = self.caster.upsample_planes([colour[..., k] for k in range(3)], rows)
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
