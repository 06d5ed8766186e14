"""Vehicles in the camera view: cars, vans and carts as lit boxes, drawn into the image and the occlusion mask."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.drawing import Lighting, ToCamera, clip_near
from sgf_plugins.world.layout import Agent


def draw_vehicle(
    agent: Agent,
    base: np.ndarray,
    heading: float,
    camera: np.ndarray,
    to_cam: ToCamera,
    project: ToCamera,
    image: np.ndarray,
    occlusion: np.ndarray,
    light: Lighting,
) -> None:
    """Draw a car, van or cart as lit boxes (faces turned to ``camera``, the camera's world position)."""
    length, width, height = agent.size
    colour = np.asarray(agent.colours[0], np.float32)
    glass = np.array([44, 54, 64], np.float32)
    tyre = np.array([22, 22, 24], np.float32)
    boxes: list[tuple[tuple[float, float, float, float, float, float], np.ndarray]] = []
    if agent.kind == "car":
        boxes.append(((-length / 2, length / 2, -width / 2, width / 2, 0.28, 0.92), colour))
        boxes.append(((-0.32 * length, 0.2 * length, -0.44 * width, 0.44 * width, 0.92, height), glass))
    elif agent.kind == "van":
        boxes.append(((-length / 2, length / 2, -width / 2, width / 2, 0.3, height), colour))
        boxes.append(((0.36 * length, 0.5 * length, -0.46 * width, 0.46 * width, 1.1, 0.92 * height), glass))
    else:
        boxes.append(((-length / 2, length / 2, -width / 2, width / 2, 0.3, 0.85), colour))
        boxes.append(((-length / 2, length / 2, -width / 2, width / 2, height - 0.08, height), colour * 0.95))
        for px in (-0.45 * length, 0.45 * length):
            for py in (-0.45 * width, 0.45 * width):
                boxes.append(((px - 0.03, px + 0.03, py - 0.03, py + 0.03, 0.85, height - 0.08), tyre * 2))
    for px in (-0.33 * length, 0.33 * length):
        for py in (-0.5 * width, 0.5 * width - 0.22):
            boxes.append(((px - 0.3, px + 0.3, py, py + 0.22, 0.0, 0.6), tyre))
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    faces: list[tuple[float, np.ndarray, np.ndarray]] = []
    for (x0, x1, y0, y1, z0, z1), col in boxes:
        corners = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)])
        world = corners @ rot.T + base
        for idx, n_local in (
            ((0, 1, 3, 2), (0, 0, -1)),
            ((4, 5, 7, 6), (0, 0, 1)),
            ((0, 1, 5, 4), (0, -1, 0)),
            ((2, 3, 7, 6), (0, 1, 0)),
            ((0, 2, 6, 4), (-1, 0, 0)),
            ((1, 3, 7, 5), (1, 0, 0)),
        ):
            quad = world[list(idx)]
            normal = rot @ np.asarray(n_local, np.float64)
            if (camera - quad.mean(axis=0)) @ normal <= 0:
                continue
            level = light.at(quad.mean(axis=0), normal)
            pc = clip_near(to_cam(quad))
            if len(pc) < 3:
                continue
            faces.append((float(pc[:, 2].mean()), pc, col * level))
    for _, pc, col in sorted(faces, key=lambda f: -f[0]):
        uv = project(pc)
        if np.abs(uv).max() > 100_000:
            continue
        pts = np.round(uv * 16).astype(np.int32)
        cv2.fillPoly(image, [pts], tuple(float(v) for v in col), cv2.LINE_AA, 4)
        cv2.fillPoly(occlusion, [pts], 255, cv2.LINE_8, 4)
