"""The geometry of plain and motion-compensated IPM (paper Sec. III-A, eq. 1-4).

Conventions (those of :mod:`sgf_pipeline.types`): the robot base frame has x forward, y left,
z up, with its origin on the ground; the camera frame is the optical frame (x right, y down,
z forward). Image coordinates ``(u, v)`` put pixel centres on integers (OpenCV's convention),
and so do the index coordinates of a :class:`~sgf_pipeline.types.BevGrid`.

Eq. 1-2 are implemented literally as pixel -> ground functions (:func:`roll_compensation`,
:func:`compensated_ground_point`, :func:`mc_pixel_to_ground`). For a plane, their inverse is a
homography of the image (:func:`ground_to_image_homography`); the stages warp with it, and the
tests check that both agree to numerical precision. Two points where the paper is terse:

* Eq. 2's lateral term is used in its exact form ``y_c = -x_c (c/f_m) cos(Phi) / cos(alpha + Phi +
  theta)``. The printed ``cos(Phi + theta)`` in the numerator equals this only for ``theta = 0``:
  ray-plane intersection of a camera pitched by ``alpha + theta`` gives ``cos(Phi)`` (the ray's
  forward/lateral ratio does not depend on the pitch), and only the exact form is a homography.
* ``psi`` of eq. 1 rotates the image coordinates ``(c, r)`` (c right, r down) by ``-psi``: it undoes
  a camera roll about the optical axis. A robot roll ``phi`` (right-handed about the forward axis,
  left side up) is that roll with ``psi = -phi`` when the optical axis is horizontal; for a tilted
  camera the robot's roll axis differs from the optical axis by ``alpha``, which ``roll_axis="base"``
  models exactly (see :func:`compensated_camera_to_base`).
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


def metric_image_coordinates(
    u: np.ndarray, v: np.ndarray, calibration: Calibration, f_m: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Metric image coordinates ``(c, r)`` of pixels on an image plane at focal length ``f_m`` (eq. 1)."""
    k = calibration.intrinsics
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    return (u - k.cx) * (f_m / k.fx), (v - k.cy) * (f_m / k.fy)


def roll_compensation(c: np.ndarray, r: np.ndarray, psi: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1: rotate the metric image coordinates by ``-psi``."""
    cos, sin = math.cos(-psi), math.sin(-psi)
    return cos * c - sin * r, sin * c + cos * r


def compensated_ground_point(
    c_psi: np.ndarray, r_psi: np.ndarray, height: float, tilt: float, theta: float, f_m: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 2: ground point ``(x_c, y_c)`` under the camera centre, and where the ray meets the ground."""
    phi = np.arctan(np.asarray(r_psi, dtype=np.float64) / f_m)  # Phi(r^psi) = arctan(r^psi / f_m)
    depression = tilt + phi + theta  # alpha + Phi(r^psi) + theta: the ray's angle below the horizon
    hits = (depression > 1e-9) & (depression < math.pi - 1e-9)
    safe = np.where(hits, depression, 0.5 * math.pi)
    x_c = height / np.tan(safe)  # h_c cot(alpha + Phi + theta)
    y_c = -x_c * (np.asarray(c_psi, dtype=np.float64) / f_m) * np.cos(phi) / np.cos(safe)
    return np.where(hits, x_c, np.nan), np.where(hits, y_c, np.nan), hits


def mc_pixel_to_ground(
    u: np.ndarray, v: np.ndarray, calibration: Calibration, psi: float = 0.0, theta: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Base-frame ground ``(x, y)`` seen at pixels ``(u, v)`` after roll ``psi`` and pitch ``theta`` (eq. 1-2).

    Valid for the forward mounting eq. 2 describes (no camera yaw or roll on the robot); the third
    array says which pixels look at the ground. ``(x_c, y_c)`` of eq. 2 are relative to the point
    under the camera centre, so the camera's position on the robot is added.
    """
    c, r = metric_image_coordinates(u, v, calibration)
    c_psi, r_psi = roll_compensation(c, r, psi)
    x_c, y_c, hits = compensated_ground_point(c_psi, r_psi, calibration.height, calibration.tilt, theta)
    position = calibration.camera_to_base_matrix[:3, 3]
    return x_c + position[0], y_c + position[1], hits


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
