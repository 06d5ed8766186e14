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


# -- the ground the camera sees ----------------------------------------------------------------------

#: How far out (m) the nearest visible ground is looked for.
MAX_GROUND_RANGE = 200.0


def ground_visible(calibration: Calibration, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Which base-frame ground points ``(x, y, 0)`` the camera images (in front of it, inside the image)."""
    pose = calibration.camera_to_base_matrix
    points = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64), np.zeros(np.shape(x))], axis=-1)
    camera = (points - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t), row-wise
    k = calibration.intrinsics
    depth = camera[..., 2]
    ahead = depth > MIN_DEPTH
    safe = np.where(ahead, depth, 1.0)
    u = k.fx * camera[..., 0] / safe + k.cx
    v = k.fy * camera[..., 1] / safe + k.cy
    return ahead & (u >= 0.0) & (u <= k.width - 1.0) & (v >= 0.0) & (v <= k.height - 1.0)


def seen_fraction(calibration: Calibration, grid: BevGrid) -> float:
    """The share of a BEV grid's pixels the camera sees."""
    k = calibration.intrinsics
    return float(visible_mask(bev_to_image_homography(calibration, grid), grid, k.width, k.height).mean())


def view_direction(calibration: Calibration) -> tuple[float, float]:
    """``(yaw, depression)`` of the optical axis in rad: from the base's x axis (left +), below the horizon.

    A camera looking straight down takes the image's up direction for its yaw.
    """
    rotation = calibration.camera_to_base_matrix[:3, :3]
    axis = rotation[:, 2]
    horizontal = axis[:2] if float(np.hypot(*axis[:2])) > 1e-6 else -rotation[:2, 1]
    depression = math.asin(max(-1.0, min(1.0, -float(axis[2]))))
    return math.atan2(float(horizontal[1]), float(horizontal[0])), depression


def _direction_word(yaw: float) -> str:
    degrees = math.degrees(yaw)
    if abs(degrees) <= 45.0:
        return "ahead"
    if abs(degrees) >= 135.0:
        return "behind"
    return "to the left" if degrees > 0 else "to the right"


def nearest_region(calibration: Calibration, grid: BevGrid) -> BevGrid | None:
    """A grid of ``grid``'s size and resolution on the nearest ground the camera sees, or None when it sees none.

    The camera's viewing direction (its optical axis on the ground) picks the side: ahead, behind,
    left or right of the robot. The region's near edge is the nearest ground seen along the line
    through its middle, on ``grid``'s pixel lattice; across that line it keeps ``grid``'s span
    (ahead or behind) or is centred on the camera (left or right).
    """
    yaw, _ = view_direction(calibration)
    side = _direction_word(yaw)
    r = grid.resolution
    depth_x, depth_y = grid.x_max - grid.x_min, grid.y_max - grid.y_min
    foot = calibration.camera_to_base_matrix[:2, 3]
    along_x = side in ("ahead", "behind")
    sign = 1.0 if side in ("ahead", "to the left") else -1.0
    origin, start = (grid.x_min, float(foot[0])) if along_x else (grid.y_min, float(foot[1]))
    extent = depth_x if along_x else depth_y
    # candidate near edges on the lattice origin + k r, from the camera's foot outwards
    steps = np.arange(0, round(MAX_GROUND_RANGE / r) + 1)
    if sign > 0:
        near = origin + (math.ceil((start - origin) / r - 1e-9) + steps) * r
        mid = near + 0.5 * r
    else:
        far = origin + extent + (math.floor((start - origin - extent) / r + 1e-9) - steps) * r
        near, mid = far - extent, far - 0.5 * r
    if along_x:
        centre = np.full(mid.shape, 0.5 * (grid.y_min + grid.y_max))
        seen = ground_visible(calibration, mid, centre)
    else:
        x_min = grid.x_min + round((float(foot[0]) - 0.5 * depth_x - grid.x_min) / r) * r
        seen = ground_visible(calibration, np.full(mid.shape, x_min + 0.5 * depth_x), mid)
    if not seen.any():
        return None
    low = float(near[int(np.argmax(seen))])
    if along_x:
        return BevGrid(r, round(low, 9), round(low + depth_x, 9), grid.y_min, grid.y_max)
    return BevGrid(r, round(x_min, 9), round(x_min + depth_x, 9), round(low, 9), round(low + depth_y, 9))


def describe_view(calibration: Calibration) -> str:
    """Where the camera looks and the nearest ground it sees, for messages."""
    yaw, depression = view_direction(calibration)
    side = _direction_word(yaw)
    tilt = round(math.degrees(depression), 1) + 0.0  # no "-0.0"
    level = f"{abs(tilt):.1f} deg {'below' if tilt >= 0 else 'above'} the horizon"
    words = f"{calibration.height:.2f} m high, optical axis {level}"
    if side != "ahead" or abs(yaw) > math.radians(1.0):
        words += f", turned {math.degrees(yaw):.0f} deg from the robot's forward axis (looking {side})"
    probe = nearest_region(calibration, BevGrid(0.01, -0.005, 0.005, -0.005, 0.005))
    if probe is None:
        return words + "; it sees no ground (the ground lies outside its image)"
    x, y = 0.5 * (probe.x_min + probe.x_max), 0.5 * (probe.y_min + probe.y_max)
    return words + f"; the nearest ground it sees {side} is about {math.hypot(x, y):.2f} m from the base origin"
