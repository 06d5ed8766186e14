"""People in the camera view: a walking figure of limbs, drawn into the image and the occlusion mask."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.drawing import Lighting, ToCamera
from sgf_plugins.world.layout import Agent


def draw_person(
    agent: Agent,
    base: np.ndarray,
    heading: float,
    walked: float,
    to_cam: ToCamera,
    project: ToCamera,
    image: np.ndarray,
    occlusion: np.ndarray,
    K: np.ndarray,
    light: Lighting,
) -> None:
    """Draw a walking person as limbs (legs swinging with the distance walked), far limbs first."""
    height = agent.size[2]
    shirt, trousers, skin, shoes = (np.asarray(c, np.float32) for c in agent.colours)
    f = np.array([math.cos(heading), math.sin(heading), 0.0])
    left = np.array([-f[1], f[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    swing = 0.28 * math.sin(2 * math.pi * walked / 1.4) if agent.speed > 0 else 0.0
    hip_h, shoulder_h = 0.52 * height, 0.81 * height
    starts, ends, widths, colours = [], [], [], []

    def limb(a: np.ndarray, b: np.ndarray, width: float, colour: np.ndarray) -> None:
        starts.append(a)
        ends.append(b)
        widths.append(width)
        colours.append(colour)

    for side in (1.0, -1.0):
        hip = base + side * 0.09 * left + hip_h * up
        foot = base + side * 0.1 * left + side * swing * f + 0.05 * up
        knee = 0.5 * (hip + foot) + 0.04 * f + 0.02 * up
        limb(hip, knee, 0.14, trousers)
        limb(knee, foot, 0.12, trousers)
        limb(foot, foot + 0.22 * f, 0.09, shoes)
        shoulder = base + side * 0.19 * left + shoulder_h * up
        hand = base + side * 0.22 * left - side * 0.7 * swing * f + 0.43 * height * up
        limb(shoulder, hand, 0.09, shirt)
        limb(hand, hand - 0.06 * up, 0.08, skin)
    limb(base + (hip_h - 0.02) * up, base + (shoulder_h - 0.03) * up, 0.36, shirt)
    limb(base + 0.87 * height * up, base + 0.96 * height * up, 0.2, skin)
    a = to_cam(np.asarray(starts))
    b = to_cam(np.asarray(ends))
    # clip every limb to the part in front of the camera
    za, zb = a[:, 2], b[:, 2]
    keep = np.maximum(za, zb) >= 0.05
    s = np.clip((0.05 - za) / np.where(np.abs(zb - za) > 1e-9, zb - za, 1e-9), 0.0, 1.0)
    a = np.where((za < 0.05)[:, None], a + s[:, None] * (b - a), a)
    s = np.clip((0.05 - zb) / np.where(np.abs(za - zb) > 1e-9, za - zb, 1e-9), 0.0, 1.0)
    b = np.where((zb < 0.05)[:, None], b + s[:, None] * (a - b), b)
    depth = 0.5 * (a[:, 2] + b[:, 2])
    ua, ub = project(a), project(b)
    lit = light.at(base + 1.0 * up)
    # everything per limb as plain numbers first (one numpy pass), then the far limbs drawn first
    thick = np.maximum(1, np.round(K[0, 0] * np.asarray(widths) / np.maximum(depth, 0.05))).astype(np.int64)
    ends16 = np.round(np.concatenate([ua, ub], axis=1) * 16)
    draw = keep & (thick <= 4000) & (np.abs(ends16).max(axis=1) <= 2_000_000)
    lit_colours = (np.asarray(colours, np.float64) * lit).tolist()
    ends_px = ends16.astype(np.int64).tolist()
    thick_px = thick.tolist()
    order = np.argsort(-depth)
    for i in order[draw[order]].tolist():
        x0, y0, x1, y1 = ends_px[i]
        cv2.line(image, (x0, y0), (x1, y1), lit_colours[i], thick_px[i], cv2.LINE_AA, 4)
        cv2.line(occlusion, (x0, y0), (x1, y1), 255, thick_px[i], cv2.LINE_8, 4)
