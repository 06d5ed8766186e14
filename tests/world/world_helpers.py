"""Geometry helpers of the world tests, independent of the renderer (OpenCV projection, exact ray march)."""

from __future__ import annotations

import numpy as np
from sgf_plugins.world import CampusWorld


def project(world: CampusWorld, pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of world points (N, 3) with OpenCV's own pinhole projection."""
    import cv2

    cam = pose @ world.calibration.camera_to_base_matrix
    world_to_cam = np.linalg.inv(cam)
    rvec, _ = cv2.Rodrigues(world_to_cam[:3, :3])
    uv, _ = cv2.projectPoints(
        points.reshape(-1, 1, 3), rvec, world_to_cam[:3, 3], world.calibration.intrinsics.matrix, None
    )
    return uv.reshape(-1, 2)


def exact_ground(world: CampusWorld, pose: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """World points (N, 3) where the rays of pixels ``uv`` first meet the terrain (fine march + bisection)."""
    intr = world.calibration.intrinsics
    cam = pose @ world.calibration.camera_to_base_matrix
    rays = np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))], axis=1)
    d = rays @ cam[:3, :3].T
    c = cam[:3, 3]
    ts = np.arange(0.05, 40.0, 0.01)
    out = np.full((len(uv), 3), np.nan)
    for i, di in enumerate(d):
        p = c + ts[:, None] * di
        f = p[:, 2] - world.terrain.height(p[:, 0], p[:, 1])
        below = np.flatnonzero(f <= 0)
        if below.size == 0:
            continue
        k = below[0]
        a, b = ts[max(k - 1, 0)], ts[k]
        for _ in range(40):
            m = 0.5 * (a + b)
            q = c + m * di
            if q[2] - world.terrain.height(np.array([q[0]]), np.array([q[1]]))[0] > 0:
                a = m
            else:
                b = m
        out[i] = c + 0.5 * (a + b) * di
    return out
