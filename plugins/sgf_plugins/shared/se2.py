"""Planar rigid transforms as 3x3 homogeneous matrices ``T``: ``q = R p + t``."""

from __future__ import annotations

import math

import numpy as np


def se2(x: float, y: float, yaw: float) -> np.ndarray:
    """3x3 homogeneous matrix of a planar rigid transform."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_params(transform: np.ndarray) -> tuple[float, float, float]:
    """``(x, y, yaw)`` of a 3x3 planar transform."""
    return float(transform[0, 2]), float(transform[1, 2]), math.atan2(float(transform[1, 0]), float(transform[0, 0]))


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Transform (N, 2) points."""
    return points @ transform[:2, :2].T + transform[:2, 2]
