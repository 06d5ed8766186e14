"""Hu moment invariants of binary SGF regions (paper eq. 5-7) and their shape distance (eq. 8)."""

from __future__ import annotations

from typing import Literal

import numpy as np

HuScale = Literal["raw", "log"]

#: Magnitudes below this are treated as zero by the ``log`` scale (an exactly symmetric shape has
#: h3..h7 = 0, whose logarithm would otherwise dominate every distance).
LOG_FLOOR = 1e-12


def hu_moments(pixels: np.ndarray) -> np.ndarray:
    """The seven Hu invariants (eq. 7) of a binary region given by its (N, 2) pixel coordinates (u, v)."""
    pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(7)
    u = pts[:, 0] - pts[:, 0].mean()
    v = pts[:, 1] - pts[:, 1].mean()
    m00 = float(len(pts))  # mu_00 of a binary image, I(u, v) = 1 on the region

    def eta(p: int, q: int) -> float:
        """Normalised central moment (eq. 5-6)."""
        mu = float(np.sum(u**p * v**q))
        return mu / m00 ** (1.0 + (p + q) / 2.0)

    n20, n02, n11 = eta(2, 0), eta(0, 2), eta(1, 1)
    n30, n03, n21, n12 = eta(3, 0), eta(0, 3), eta(2, 1), eta(1, 2)
    h = np.empty(7)
    h[0] = n20 + n02
    h[1] = (n20 - n02) ** 2 + 4.0 * n11**2
    h[2] = (n30 - 3.0 * n12) ** 2 + (3.0 * n21 - n03) ** 2
    h[3] = (n30 + n12) ** 2 + (n21 + n03) ** 2
    a, b = n30 + n12, n21 + n03
    h[4] = (n30 - 3.0 * n12) * a * (a**2 - 3.0 * b**2) + (3.0 * n21 - n03) * b * (3.0 * a**2 - b**2)
    h[5] = (n20 - n02) * (a**2 - b**2) + 4.0 * n11 * a * b
    h[6] = (3.0 * n21 - n03) * a * (a**2 - 3.0 * b**2) - (n30 - 3.0 * n12) * b * (3.0 * a**2 - b**2)
    return h


def scale_hu(hu: np.ndarray, scale: HuScale) -> np.ndarray:
    """Hu invariants as compared by eq. 8: ``raw``, or ``log`` = sign(h) log10|h| (OpenCV's matchShapes)."""
    h = np.asarray(hu, dtype=np.float64)
    if scale == "raw":
        return h
    if scale == "log":
        mag = np.abs(h)
        return np.where(mag < LOG_FLOOR, 0.0, np.sign(h) * np.log10(np.maximum(mag, LOG_FLOOR)))
    raise ValueError(f"unknown Hu scale {scale!r}; expected 'raw' or 'log'")


def hu_distance(hu_a: np.ndarray, hu_b: np.ndarray, scale: HuScale = "raw") -> float:
    """Shape distance of eq. 8: the sum of absolute differences of the (scaled) Hu invariants."""
    return float(np.sum(np.abs(scale_hu(hu_a, scale) - scale_hu(hu_b, scale))))
