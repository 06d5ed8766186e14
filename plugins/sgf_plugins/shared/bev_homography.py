"""The homography from the ground and a BEV grid to the image (eq. 1-4 inverted), and the BEV pixels it sees.

Conventions (those of :mod:`sgf_pipeline.types`): the robot base frame has x forward, y left,
z up, with its origin on the ground; the camera frame is the optical frame (x right, y down,
z forward). Image coordinates ``(u, v)`` put pixel centres on integers (OpenCV's convention),
and so do the index coordinates of a :class:`~sgf_pipeline.types.BevGrid`.

For the ground plane, the inverse of eq. 1-2 (a camera pitched by ``theta`` and rolled by ``psi``)
is a homography of the image (:func:`ground_to_image_homography`); with eq. 3-4 (the BEV grid's
metric pixels) it maps BEV pixels to image pixels (:func:`bev_to_image_homography`), the warp the
stages resample the ground with. :func:`visible_mask` says which BEV pixels land inside the image.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.types import BevGrid

RollAxis = Literal["optical", "base"]

#: Ground points closer to the camera plane than this (m, along the optical axis) are not imaged.
MIN_DEPTH = 1e-3


def _rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def compensated_camera_to_base(
    calibration: Calibration, psi: float = 0.0, theta: float = 0.0, roll_axis: RollAxis = "optical"
) -> np.ndarray:
    """Rotation of the camera in the base frame once pitched by ``theta`` and rolled by ``psi`` (eq. 1-2).

    ``optical`` (eq. 1 as printed): ``Ry(theta) R_cb Rz_optical(-psi)``, the image rotated about the
    principal point, then the camera pitched about the robot's lateral axis (``alpha + theta``).
    ``base``: ``Ry(theta) Rx(-psi) R_cb``, the roll taken about the robot's forward axis, exact for a
    tilted camera. Both rotate about the camera centre (``h_c`` is kept, as in eq. 2); they coincide
    when the optical axis is horizontal.
    """
    r_cb = calibration.camera_to_base_matrix[:3, :3]
    if roll_axis == "optical":
        return _rot_y(theta) @ r_cb @ _rot_z(-psi)
    return _rot_y(theta) @ _rot_x(-psi) @ r_cb


def ground_to_image_homography(
    calibration: Calibration, psi: float = 0.0, theta: float = 0.0, roll_axis: RollAxis = "optical"
) -> np.ndarray:
    """3x3 homography from base-frame ground ``(x, y, 1)`` to image pixels: the inverse of eq. 1-2."""
    rotation = compensated_camera_to_base(calibration, psi, theta, roll_axis)
    position = calibration.camera_to_base_matrix[:3, 3]
    world_to_camera = rotation.T
    plane = np.column_stack([world_to_camera[:, 0], world_to_camera[:, 1], -world_to_camera @ position])
    return calibration.intrinsics.matrix @ plane


def bev_to_image_homography(
    calibration: Calibration, grid: BevGrid, psi: float = 0.0, theta: float = 0.0, roll_axis: RollAxis = "optical"
) -> np.ndarray:
    """3x3 homography from BEV index coordinates to image pixels (eq. 3-4 inverted, then eq. 1-2 inverted)."""
    return ground_to_image_homography(calibration, psi, theta, roll_axis) @ np.linalg.inv(grid.ground_to_pixel_matrix)


def visible_mask(homography: np.ndarray, grid: BevGrid, image_width: int, image_height: int) -> np.ndarray:
    """BEV pixels whose centre maps in front of the camera and inside ``[0, W-1] x [0, H-1]`` of the image.

    Every condition is linear in the BEV column ``u`` for a fixed row ``v`` (``a u + b(v) >= 0``), so
    each row's visible pixels are one interval: the mask costs a few vector operations per row,
    not a projection per pixel.
    """
    h = np.asarray(homography, dtype=np.float64)
    w1, h1 = image_width - 1.0, image_height - 1.0
    # Rows of h applied to (u, v, 1): s (image x times depth), t (image y times depth), w (depth).
    # Conditions: w - MIN_DEPTH >= 0, s >= 0, (W-1) w - s >= 0, t >= 0, (H-1) w - t >= 0.
    forms = np.array([h[2], h[0], w1 * h[2] - h[0], h[1], h1 * h[2] - h[1]])
    forms[0, 2] -= MIN_DEPTH
    a = forms[:, 0]
    rows = np.arange(grid.height, dtype=np.float64)
    b = forms[:, 1:2] * rows + forms[:, 2:3]  # (5, rows)
    lo = np.zeros(grid.height)
    hi = np.full(grid.height, grid.width - 1.0)
    for k in range(5):
        if a[k] > 0.0:
            lo = np.maximum(lo, -b[k] / a[k])
        elif a[k] < 0.0:
            hi = np.minimum(hi, -b[k] / a[k])
        else:
            hi = np.where(b[k] < 0.0, -1.0, hi)
    first = np.ceil(lo - 1e-9)
    last = np.floor(hi + 1e-9)
    cols = np.arange(grid.width, dtype=np.float64)
    return (cols >= first[:, None]) & (cols <= last[:, None])
