"""Procedurally drawn painted shapes on textured ground, with exact masks: data for tests and benchmarks.

This is not the synthetic campus world (a perspective renderer with real marking designs): it draws
simple shapes straight into a top view, so that the train, evaluate and benchmark paths can run
anywhere in seconds. Weights trained on it are toys and must never be shipped as a model.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np

DESIGNS = ("stripes", "arrow", "ring", "cross", "star", "glyph")


def ground_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """Asphalt- or paver-like RGB texture ``(size, size, 3)`` uint8."""
    base = rng.uniform(60, 140)
    tint = rng.uniform(-12, 12, size=3)
    noise = rng.normal(0, 1, (size, size)).astype(np.float32)
    fine = cv2.GaussianBlur(noise, (0, 0), 0.8) * rng.uniform(8, 18)
    coarse = cv2.GaussianBlur(rng.normal(0, 1, (size, size)).astype(np.float32), (0, 0), size / 12) * rng.uniform(
        60, 160
    )
    grey = base + fine + coarse
    if rng.random() < 0.4:  # paver joints
        step = int(rng.integers(size // 8, size // 4))
        joints = np.zeros((size, size), np.float32)
        joints[::step, :] = 1
        joints[:, :: step * 2] = 1
        grey -= cv2.GaussianBlur(joints, (0, 0), 0.7) * rng.uniform(20, 50)
    rgb = grey[:, :, None] + tint[None, None, :]
    return np.clip(rgb, 0, 255).astype(np.uint8)


def _polygon(design: str, rng: np.random.Generator, size: int) -> list[np.ndarray] | str:
    """Outline(s) of one design centred at the origin, in pixels (``str`` for glyphs)."""
    s = size * rng.uniform(0.12, 0.25)
    if design == "stripes":
        n = int(rng.integers(2, 5))
        width, gap = s * 0.25, s * 0.25
        return [
            np.array([[-s, y], [s, y], [s, y + width], [-s, y + width]])
            for y in (np.arange(n) * (width + gap) - n * (width + gap) / 2)
        ]
    if design == "arrow":
        return [np.array([[-0.15, -1], [0.15, -1], [0.15, 0.2], [0.45, 0.2], [0, 1], [-0.45, 0.2], [-0.15, 0.2]]) * s]
    if design == "cross":
        a = 0.25
        pts = [
            [-a, -1],
            [a, -1],
            [a, -a],
            [1, -a],
            [1, a],
            [a, a],
            [a, 1],
            [-a, 1],
            [-a, a],
            [-1, a],
            [-1, -a],
            [-a, -a],
        ]
        return [np.array(pts) * s]
    if design == "star":
        k = int(rng.integers(5, 8))
        t = np.arange(2 * k) * np.pi / k
        r = np.where(np.arange(2 * k) % 2 == 0, 1.0, 0.45)
        return [np.stack([np.cos(t) * r, np.sin(t) * r], axis=1) * s]
    if design == "glyph":
        return "".join(rng.choice(list("ABEFHKLMNPRTXYZ"), size=int(rng.integers(1, 3))))
    return "ring"


def draw_marking(
    canvas: np.ndarray, mask: np.ndarray, design: str, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Paint one marking of ``design`` at a random place and heading into an image and its mask."""
    size = canvas.shape[0]
    layer = np.zeros(mask.shape, np.uint8)
    centre = rng.uniform(0.25, 0.75, size=2) * size
    angle = rng.uniform(0, 2 * np.pi)
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    shape = _polygon(design, rng, size)
    if isinstance(shape, str) and shape == "ring":
        radius = int(size * rng.uniform(0.08, 0.15))
        cv2.circle(layer, (int(centre[0]), int(centre[1])), radius, 255, thickness=max(2, radius // 4))
    elif isinstance(shape, str):
        scale = size / 110 * rng.uniform(0.8, 1.4)
        (tw, th), _ = cv2.getTextSize(shape, cv2.FONT_HERSHEY_SIMPLEX, scale, max(2, int(scale * 3)))
        text = np.zeros_like(layer)
        org = (int(size / 2 - tw / 2), int(size / 2 + th / 2))
        cv2.putText(text, shape, org, cv2.FONT_HERSHEY_SIMPLEX, scale, 255, max(2, int(scale * 3)))
        M = np.asarray(cv2.getRotationMatrix2D((size / 2, size / 2), float(np.degrees(angle)), 1.0), np.float64)
        M[:, 2] += centre - size / 2
        layer = np.asarray(cv2.warpAffine(text, M, (size, size), flags=cv2.INTER_NEAREST), np.uint8)
    else:
        for poly in shape:
            pts = (poly @ R.T + centre).round().astype(np.int32)
            cv2.fillPoly(layer, [pts], 255)
    painted = layer > 127
    colour = np.array(
        [(235, 235, 230), (240, 200, 40), (60, 110, 200), (210, 60, 50)][int(rng.choice(4, p=[0.55, 0.25, 0.1, 0.1]))],
        np.float32,
    )
    wear = np.clip(1 - np.abs(rng.normal(0, 0.15, mask.shape)), 0.5, 1.0)[:, :, None]
    alpha = cv2.GaussianBlur(painted.astype(np.float32), (0, 0), 0.6)[:, :, None] * wear
    out = canvas.astype(np.float32) * (1 - alpha) + colour[None, None, :] * alpha
    return np.clip(out, 0, 255).astype(np.uint8), mask | painted


def camera_footprint(size: int, rng: np.random.Generator) -> np.ndarray:
    """A trapezoid of seen ground as a front camera's BEV has (far edge wider than the near one)."""
    near = rng.uniform(0.25, 0.45) * size
    far = rng.uniform(0.45, 0.5) * size
    c = size / 2
    pts = np.array([[c - far, 0], [c + far, 0], [c + near, size - 1], [c - near, size - 1]]).round().astype(np.int32)
    valid = np.zeros((size, size), np.uint8)
    cv2.fillPoly(valid, [pts], 1)
    return valid.astype(bool)


def sample(
    rng: np.random.Generator, size: int = 128, designs: tuple[str, ...] = DESIGNS, max_markings: int = 2
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """One ``(bev_rgb, mask, meta)`` sample: textured ground with 0 to ``max_markings`` painted designs."""
    rgb = ground_texture(rng, size)
    mask = np.zeros((size, size), bool)
    chosen = [str(d) for d in rng.choice(designs, size=int(rng.integers(0, max_markings + 1)))]
    for design in chosen:
        rgb, mask = draw_marking(rgb, mask, design, rng)
    valid = camera_footprint(size, rng)
    rgb = rgb * valid[:, :, None]
    mask &= valid
    return rgb.astype(np.uint8), mask, {"designs": sorted(set(chosen)), "valid": valid}


def samples(
    n: int, seed: int = 0, size: int = 128, designs: tuple[str, ...] = DESIGNS, max_markings: int = 2
) -> Iterator[tuple[np.ndarray, np.ndarray, dict[str, Any]]]:
    """``n`` samples from one seed."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield sample(rng, size, designs, max_markings)
