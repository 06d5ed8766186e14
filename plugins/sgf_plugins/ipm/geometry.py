"""Eq. 1-2 of plain and motion-compensated IPM (paper Sec. III-A) as pixel -> ground functions.

Conventions (those of :mod:`sgf_pipeline.types`): the robot base frame has x forward, y left,
z up, with its origin on the ground; the camera frame is the optical frame (x right, y down,
z forward). Image coordinates ``(u, v)`` put pixel centres on integers (OpenCV's convention).

Eq. 1-2 are implemented literally (:func:`roll_compensation`, :func:`compensated_ground_point`,
:func:`mc_pixel_to_ground`). For a plane, their inverse is a homography of the image
(:func:`sgf_plugins.shared.bev_homography.ground_to_image_homography`); the stages warp with it,
and the tests check that both agree to numerical precision. Two points where the paper is terse:

* Eq. 2's lateral term is used in its exact form ``y_c = -x_c (c/f_m) cos(Phi) / cos(alpha + Phi +
  theta)``. The printed ``cos(Phi + theta)`` in the numerator equals this only for ``theta = 0``:
  ray-plane intersection of a camera pitched by ``alpha + theta`` gives ``cos(Phi)`` (the ray's
  forward/lateral ratio does not depend on the pitch), and only the exact form is a homography.
* ``psi`` of eq. 1 rotates the image coordinates ``(c, r)`` (c right, r down) by ``-psi``: it undoes
  a camera roll about the optical axis. A robot roll ``phi`` (right-handed about the forward axis,
  left side up) is that roll with ``psi = -phi`` when the optical axis is horizontal; for a tilted
  camera the robot's roll axis differs from the optical axis by ``alpha``, which ``roll_axis="base"``
  models exactly (see :func:`sgf_plugins.shared.bev_homography.compensated_camera_to_base`).
"""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.calibration import Calibration


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
