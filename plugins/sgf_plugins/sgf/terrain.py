"""Lifting SGF pixels onto the ground the robot drove over (an extension of eq. 9 for uneven ground).

The BEV puts every pixel on one plane: the plane the IPM variant assumed when the view was taken
(the robot's base plane for plain IPM, the reference attitude's plane for MC-IPM). Where the grade
ahead differs from that plane (a slope starting or ending under the marking), a point seen d
metres ahead by a camera h metres high moves by about d^2 / h times the grade difference: 0.56 m
at 4.4 m ahead for 1 degree with the world's 0.6 m camera. By the time a feature has left the
view the robot has driven up to it, so its odometry (3-D: heights and attitude from the IMU) has
measured that ground. Each pixel's camera ray (through the view's homography to the image and the
camera's pose in the odometry frame) is intersected with the driven ground: a surface made of
the base poses since the view, each the local tangent plane of the ground under the wheels,
extended ahead of the newest pose at its grade.
"""

from __future__ import annotations

import numpy as np

from sgf_pipeline.calibration import Calibration

#: Ray-ground iterations: each picks every ray's nearest ground sample, then meets its tangent plane.
ITERATIONS = 5
#: Smallest cosine between a ray and a ground normal (a ray grazing the ground gives no point).
_MIN_INCIDENCE = 1e-3


def driven_ground(poses: np.ndarray, ahead: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground samples (K, 3) and their unit normals (K, 3) from base poses (N, 4, 4), in the poses' frame.

    Each pose's base origin is a point of the ground and its z axis the ground's normal there;
    the newest pose's tangent plane is sampled every ``step`` metres up to ``ahead`` metres on.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise ValueError(f"expected base poses of shape (N, 4, 4), got {poses.shape}")
    points = poses[:, :3, 3]
    normals = poses[:, :3, 2]
    last = poses[-1]
    if ahead > 0.0 and step > 0.0:
        offsets = np.arange(step, ahead + 0.5 * step, step)
        points = np.vstack([points, last[:3, 3] + offsets[:, None] * last[:3, 0]])
        normals = np.vstack([normals, np.repeat(last[None, :3, 2], len(offsets), axis=0)])
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def pixel_rays(pixels: np.ndarray, homography: np.ndarray, calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """The camera ray of each BEV pixel ``(u, v)``: origin (3,) and unit directions (M, 3) in the base frame."""
    uv1 = np.column_stack([np.asarray(pixels, dtype=np.float64).reshape(-1, 2), np.ones(len(pixels))])
    image = uv1 @ np.asarray(homography, dtype=np.float64).T  # BEV index -> image pixel (homogeneous)
    rays = image @ np.linalg.inv(calibration.intrinsics.matrix).T  # optical frame, z forward
    camera = calibration.camera_to_base_matrix
    directions = rays @ camera[:3, :3].T
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return camera[:3, 3].copy(), directions


def intersect_ground(
    origin: np.ndarray, directions: np.ndarray, points: np.ndarray, normals: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where each ray meets the driven ground: (M, 3) points and whether a ground sample lay within ``radius``.

    Rays start on the first sample's tangent plane; each iteration moves every ray to its nearest
    sample (horizontally) and intersects that sample's plane. A ray whose nearest sample stays
    farther than ``radius`` (m) is not covered by the driven ground: its point is not trusted.
    """
    hit = np.empty((len(directions), 3))
    covered = np.zeros(len(directions), dtype=bool)
    nearest = np.zeros(len(directions), dtype=np.int64)
    for _ in range(ITERATIONS):
        n = normals[nearest]
        cos = np.einsum("ij,ij->i", directions, n)
        ok = cos < -_MIN_INCIDENCE  # the ray goes down through the plane
        t = np.where(ok, np.einsum("ij,ij->i", points[nearest] - origin, n) / np.where(ok, cos, -1.0), np.nan)
        ok &= t > 0.0
        hit = origin + np.where(ok, t, np.nan)[:, None] * directions
        d2 = (hit[:, None, 0] - points[None, :, 0]) ** 2 + (hit[:, None, 1] - points[None, :, 1]) ** 2
        d2 = np.where(ok[:, None], d2, np.inf)
        moved = np.argmin(d2, axis=1)
        covered = ok & (d2[np.arange(len(moved)), moved] <= radius * radius)
        if np.array_equal(moved, nearest):
            break
        nearest = moved
    return hit, covered
