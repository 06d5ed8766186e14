"""Training augmentation of BEV images and their masks: geometry, photometry, hue, shadows and salient crops."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Augmentation:
    """Random geometric and photometric changes for training on BEV images (markings may lie at any heading)."""

    rotate: bool = True
    flip: bool = True
    min_scale: float = 0.7
    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.3
    gamma: float = 0.3
    hue_probability: float = 0.0
    noise: float = 6.0
    blur_probability: float = 0.2
    shadow_probability: float = 0.3

    def __call__(self, rgb: np.ndarray, mask: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Augmented copies of an RGB image (uint8) and its mask (float32 in [0, 1]), same size."""
        h, w = mask.shape
        # 1. geometry: rotation about the centre, zoom in (crop), flip; uncovered pixels are black
        #    like the unseen part of a BEV
        angle = float(rng.uniform(0, 360)) if self.rotate else 0.0
        scale = 1.0 / float(rng.uniform(self.min_scale, 1.0))
        cx, cy = w / 2 + rng.uniform(-0.1, 0.1) * w, h / 2 + rng.uniform(-0.1, 0.1) * h
        M = np.asarray(cv2.getRotationMatrix2D((cx, cy), angle, scale), np.float64)
        M[:, 2] += (w / 2 - cx, h / 2 - cy)
        if self.flip and rng.random() < 0.5:
            M = np.array([[-1.0, 0.0, w - 1.0], [0.0, 1.0, 0.0]]) @ np.vstack([M, [0.0, 0.0, 1.0]])
        rgb = cv2.warpAffine(rgb, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mask = cv2.warpAffine(mask, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        # 2. photometry: hue, brightness, contrast, saturation, gamma, a soft shadow, blur, sensor noise
        if rng.random() < self.hue_probability:
            rgb = rotate_hue(rgb, float(rng.uniform(0.0, 360.0)))
        img = rgb.astype(np.float32) / 255.0
        img = img * float(rng.uniform(1 - self.brightness, 1 + self.brightness))
        mean = img.mean()
        img = (img - mean) * float(rng.uniform(1 - self.contrast, 1 + self.contrast)) + mean
        grey = img.mean(axis=2, keepdims=True)
        img = grey + (img - grey) * float(rng.uniform(1 - self.saturation, 1 + self.saturation))
        img = np.clip(img, 0.0, 1.0) ** float(math.exp(rng.uniform(-self.gamma, self.gamma)))
        if rng.random() < self.shadow_probability:
            img = img * _shadow(h, w, rng)[:, :, None]
        if rng.random() < self.blur_probability:
            img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.5, 1.5)))
        img = img * 255.0 + rng.normal(0.0, self.noise * float(rng.random()), img.shape).astype(np.float32)
        return np.clip(img, 0, 255).astype(np.uint8), np.clip(mask, 0.0, 1.0)


def rotate_hue(rgb: np.ndarray, degrees: float) -> np.ndarray:
    """An RGB image (uint8) with every hue turned by ``degrees``: paint of any colour is still paint."""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    shift = round(degrees / 2.0) % 180  # OpenCV's 8-bit hue runs over [0, 180)
    hsv[:, :, 0] = ((hsv[:, :, 0].astype(np.int32) + shift) % 180).astype(np.uint8)
    return np.asarray(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), np.uint8)


def salient_crop(
    rgb: np.ndarray, mask: np.ndarray, crop: int, on_marking: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A ``crop x crop`` window of an image and its mask at full resolution.

    With probability ``on_marking`` (when the mask has salient pixels) the window holds a random
    salient pixel at a random place inside it, else it lies anywhere.
    """
    h, w = mask.shape
    if crop > h or crop > w:
        raise ValueError(f"a crop of {crop} px does not fit a {h}x{w} image")
    ys, xs = np.nonzero(mask > 0.5)
    if len(ys) and rng.random() < on_marking:
        k = int(rng.integers(len(ys)))
        y0 = int(np.clip(ys[k] - rng.integers(crop), 0, h - crop))
        x0 = int(np.clip(xs[k] - rng.integers(crop), 0, w - crop))
    else:
        y0, x0 = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
    return rgb[y0 : y0 + crop, x0 : x0 + crop], mask[y0 : y0 + crop, x0 : x0 + crop]


def _shadow(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A soft-edged half-plane darkening (a building's or the robot's shadow)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    theta = rng.uniform(0, 2 * np.pi)
    offset = rng.uniform(-0.3, 0.3) * max(h, w)
    d = (xx - w / 2) * math.cos(theta) + (yy - h / 2) * math.sin(theta) - offset
    edge = max(1.0, float(rng.uniform(2, 0.1 * max(h, w))))
    darkness = float(rng.uniform(0.3, 0.7))
    return (1 - darkness * 0.5 * (1 + np.tanh(d / (2 * edge)))).astype(np.float32)  # a logistic step, no overflow
