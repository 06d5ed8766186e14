"""Seeded, tile-seamless randomness of the synthetic world: integer hashing and lattice value noise."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

_M1 = np.uint32(0x85EBCA6B)
_M2 = np.uint32(0xC2B2AE35)
_PRIMES = (np.uint32(0x9E3779B1), np.uint32(0x85EBCA77), np.uint32(0xC2B2AE3D), np.uint32(0x27D4EB2F))


def _zigzag(value: int) -> int:
    """Map a signed integer to a non-negative one (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...)."""
    return 2 * value if value >= 0 else -2 * value - 1


def rng_for(seed: int, *keys: int) -> np.random.Generator:
    """A numpy generator determined by the world seed and integer keys (tile or cell indices, ids)."""
    return np.random.default_rng([_zigzag(int(seed)), *(_zigzag(int(k)) for k in keys)])


def hash_u32(seed: int, *coords: np.ndarray) -> np.ndarray:
    """A well-mixed uint32 hash of integer coordinate arrays (broadcast together) and a seed."""
    with np.errstate(over="ignore"):
        h = np.full(np.broadcast_shapes(*(np.shape(c) for c in coords)), np.uint32(seed & 0xFFFFFFFF), np.uint32)
        for i, c in enumerate(coords):
            h = h ^ (np.asarray(c).astype(np.int64).astype(np.uint32) * _PRIMES[i % 4])
            h = (h << np.uint32(13)) | (h >> np.uint32(19))
            h = h * np.uint32(5) + np.uint32(0xE6546B64)
        h ^= h >> np.uint32(16)
        h *= _M1
        h ^= h >> np.uint32(13)
        h *= _M2
        h ^= h >> np.uint32(16)
    return h


def hash_uniform(seed: int, *coords: np.ndarray) -> np.ndarray:
    """Uniform values in [0, 1) hashed from integer coordinates (float32)."""
    return (hash_u32(seed, *coords) >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def lattice_noise(seed: int, x0: float, y_top: float, nx: int, ny: int, res: float, spacing: float) -> np.ndarray:
    """Smooth value noise in about [-1, 1] on a texel grid, continuous across tiles and resolutions.

    Texel ``(row, col)`` has its centre at world ``(x0 + (col + 0.5) res, y_top - (row + 0.5) res)``.
    Lattice point ``(m, n)`` sits at world ``((m + 0.5) spacing, (n + 0.5) spacing)`` and holds a
    hashed uniform value; texels interpolate it bicubically. When ``spacing / res`` and
    ``x0 / res`` are integers the interpolation is one ``cv2.resize`` (tiles use this); otherwise a
    ``cv2.remap`` gives the same field. Lattices finer than two texels average out to 0.
    """
    if spacing < 2.0 * res:
        return np.zeros((ny, nx), np.float32)
    # Lattice coordinates of the first and last texel centres (x grows with col, y falls with row).
    gx0 = (x0 + 0.5 * res) / spacing - 0.5
    gx1 = (x0 + (nx - 0.5) * res) / spacing - 0.5
    gy_top = (y_top - 0.5 * res) / spacing - 0.5
    gy_bot = (y_top - (ny - 0.5) * res) / spacing - 0.5
    mx0, mx1 = math.floor(gx0) - 1, math.floor(gx1) + 3
    ny0, ny1 = math.floor(gy_bot) - 1, math.floor(gy_top) + 3
    m = np.arange(mx0, mx1)
    n = np.arange(ny1 - 1, ny0 - 1, -1)  # rows of the patch go from north (high y) to south
    patch = hash_uniform(seed, n[:, None], m[None, :]) * np.float32(2.0) - np.float32(1.0)
    k = spacing / res
    kx = x0 / res
    ky = y_top / res
    aligned = abs(k - round(k)) < 1e-9 and abs(kx - round(kx)) < 1e-6 and abs(ky - round(ky)) < 1e-6
    if aligned and round(k) <= 16:
        k_i = round(k)
        big = cv2.resize(patch, (patch.shape[1] * k_i, patch.shape[0] * k_i), interpolation=cv2.INTER_CUBIC)
        # dst column q samples patch column (q + 0.5) / k - 0.5; texel col j needs gx0 + j / k - mx0.
        c0 = round((gx0 - mx0 + 0.5) * k - 0.5)
        # Patch row p holds lattice n = ny1 - 1 - p; texel row i needs gy_top - i / k.
        r0 = round((ny1 - 1 - gy_top + 0.5) * k - 0.5)
        return np.ascontiguousarray(big[r0 : r0 + ny, c0 : c0 + nx])
    # Separable bicubic interpolation as two small matrix products (exact, any alignment).
    cols = gx0 - mx0 + np.arange(nx, dtype=np.float64) * (res / spacing)
    rows = ny1 - 1 - gy_top + np.arange(ny, dtype=np.float64) * (res / spacing)
    wx = _cubic_weights(cols, patch.shape[1])
    wy = _cubic_weights(rows, patch.shape[0])
    return (wy @ patch @ wx.T).astype(np.float32)


def _cubic_weights(pos: np.ndarray, size: int) -> np.ndarray:
    """Interpolation matrix (len(pos), size) of the bicubic kernel OpenCV uses (a = -0.75)."""
    a = -0.75
    i = np.floor(pos).astype(np.int64)
    f = pos - i
    out = np.zeros((len(pos), size), np.float32)
    for k in range(-1, 3):
        x = np.abs(f - k)
        w = np.where(x <= 1.0, ((a + 2) * x - (a + 3)) * x * x + 1, ((a * x - 5 * a) * x + 8 * a) * x - 4 * a)
        w = np.where(x < 2.0, w, 0.0)
        idx = np.clip(i + k, 0, size - 1)
        np.add.at(out, (np.arange(len(pos)), idx), w.astype(np.float32))
    return out


def fbm(
    seed: int,
    x0: float,
    y_top: float,
    nx: int,
    ny: int,
    res: float,
    spacings: Sequence[float],
    gains: Sequence[float] | None = None,
) -> np.ndarray:
    """Sum of lattice-noise octaves (fractal noise); ``gains`` default to the spacing ratio."""
    out = np.zeros((ny, nx), np.float32)
    total = 0.0
    for i, spacing in enumerate(spacings):
        gain = gains[i] if gains is not None else spacing / spacings[0]
        total += gain
        out += np.float32(gain) * lattice_noise(seed * 31 + i + 1, x0, y_top, nx, ny, res, spacing)
    return out / np.float32(max(total, 1e-9))


def point_noise(seed: int, x: np.ndarray, y: np.ndarray, spacing: float) -> np.ndarray:
    """Bilinear lattice value noise at arbitrary world points (for scattered queries, not tiles)."""
    gx = np.asarray(x, np.float64) / spacing - 0.5
    gy = np.asarray(y, np.float64) / spacing - 0.5
    ix = np.floor(gx).astype(np.int64)
    iy = np.floor(gy).astype(np.int64)
    fx = (gx - ix).astype(np.float32)
    fy = (gy - iy).astype(np.float32)
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    v00 = hash_uniform(seed, iy, ix)
    v01 = hash_uniform(seed, iy, ix + 1)
    v10 = hash_uniform(seed, iy + 1, ix)
    v11 = hash_uniform(seed, iy + 1, ix + 1)
    top = v00 + (v01 - v00) * fx
    bot = v10 + (v11 - v10) * fx
    return (top + (bot - top) * fy) * 2.0 - 1.0
