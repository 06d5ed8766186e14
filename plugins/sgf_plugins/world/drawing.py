"""Shared pieces of drawing things above the ground: the light on them, placed agents, clipping, blending."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_plugins.world.layout import Agent

#: A queued drawing: its distance from the camera (far ones are drawn first) and the drawing itself.
Item = tuple[float, Callable[[], None]]
#: A map of points (N, 3): world to camera coordinates, or camera coordinates to pixels.
ToCamera = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class CameraView:
    """One camera view the builders queue their drawings for: the pose, the image and its maps."""

    centre: np.ndarray  # camera position in the world
    rot: np.ndarray  # world to camera rotation
    trans: np.ndarray  # world to camera translation
    image: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    light: Lighting
    to_cam: ToCamera
    project: ToCamera


@dataclass
class Lighting:
    """Light falling on upright things: ambient level, sun (day) and the robot's headlight (night)."""

    night: bool
    ambient: float
    sun: np.ndarray
    sun_strength: float
    headlight_origin: np.ndarray
    headlight_frame: np.ndarray
    headlight_power: float
    lamps: list[tuple[np.ndarray, float]]
    gain: float = 1.0

    def beam(self, to: np.ndarray) -> np.ndarray:
        """Headlight intensity towards offsets ``to`` (..., 3) from the lamp: a wide, low-aimed LED beam."""
        local = to @ self.headlight_frame
        ahead = np.maximum(local[..., 0], 1e-6)
        psi = np.arctan2(local[..., 1], ahead)
        phi = np.arctan2(-local[..., 2], np.hypot(ahead, local[..., 1]))
        shape = np.exp(-((psi / 0.65) ** 2) - ((phi - 0.2) / 0.3) ** 2)
        return self.headlight_power * shape * (local[..., 0] > 0)

    def at(self, point: np.ndarray, normal: np.ndarray | None = None) -> float:
        """Light level (1 = sunny ground) times the camera gain, on a surface at ``point`` facing ``normal``."""
        level = self.ambient
        if not self.night:
            if normal is None:
                return (level + 0.45 * self.sun_strength) * self.gain
            return (level + self.sun_strength * max(0.0, float(normal @ self.sun)) * 0.9) * self.gain
        to = point - self.headlight_origin
        r = float(np.linalg.norm(to))
        if r > 1e-6 and self.headlight_power > 0:
            facing = 0.6 if normal is None else max(0.0, float(-(normal @ to)) / r)
            level += float(self.beam(to)) * facing / max(r * r, 0.5)
        for pos, power in self.lamps:
            d2 = float(((point - pos) ** 2).sum())
            level += power / max(d2, 16.0)
        return level * self.gain


@dataclass(frozen=True)
class PlacedAgent:
    """A person or vehicle where it is at the frame's time: position, heading, distance walked, ground height."""

    agent: Agent
    position: np.ndarray
    heading: float
    walked: float
    z: float


def clip_near(points: np.ndarray, z_near: float = 0.05) -> np.ndarray:
    """Clip a convex polygon (N, 3) in camera coordinates against the plane ``z = z_near``."""
    front = points[:, 2] >= z_near
    if front.all():
        return points
    if not front.any():
        return points[:0]
    out: list[np.ndarray] = []
    n = len(points)
    for i in range(n):
        a, b = points[i], points[(i + 1) % n]
        ina, inb = a[2] >= z_near, b[2] >= z_near
        if ina:
            out.append(a)
        if ina != inb:
            t = (z_near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.asarray(out).reshape(-1, 3)


def in_view(pc: np.ndarray, K: np.ndarray, w: int, h: int, pad: np.ndarray) -> np.ndarray:
    """Which points (N, 3) in camera coordinates are in front and within ``pad`` px of the image."""
    z = np.maximum(pc[:, 2], 1e-6)
    u = K[0, 0] * pc[:, 0] / z + K[0, 2]
    v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    return (pc[:, 2] > 0.3) & (u > -pad) & (u < w + pad) & (v > -pad) & (v < h + pad)


def blend_into(roi: np.ndarray, colour: np.ndarray, alpha: np.ndarray, level: float = 1.0) -> None:
    """Alpha-blend ``colour`` x ``level`` (an RGB image or one RGB triple) into a uint8 image region in place."""
    if np.ndim(colour) == 1:
        src = np.empty_like(roi)
        src[:] = np.clip(np.asarray(colour, np.float32) * level, 0.0, 255.0).astype(np.uint8)
    else:
        src = cv2.convertScaleAbs(colour, alpha=level)  # saturates at 255 (colours are never negative)
    a = np.ascontiguousarray(alpha, np.float32)
    roi[:] = cv2.blendLinear(src, np.ascontiguousarray(roi), a, 1.0 - a)
