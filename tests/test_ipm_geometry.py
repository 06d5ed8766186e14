"""Eq. 1-2 as pixel -> ground functions, their homography (the fast path), and the visibility mask."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ipm_scene import camera_pose, scene_calibration
from sgf_plugins.ipm import (
    compensated_ground_point,
    mc_pixel_to_ground,
    metric_image_coordinates,
    roll_compensation,
)
from sgf_plugins.shared.bev_homography import (
    bev_to_image_homography,
    compensated_camera_to_base,
    ground_to_image_homography,
    visible_mask,
)

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.types import BevGrid

GRID = BevGrid(0.02, 0.5, 5.62, -2.56, 2.56)


def _ray_plane(u, v, calibration: Calibration, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground point of pixel rays for a camera with ``rotation`` in the base frame (independent of eq. 2)."""
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(calibration.intrinsics.matrix).T @ rotation.T
    position = calibration.camera_to_base_matrix[:3, 3]
    t = -position[2] / rays[..., 2]
    return position[0] + t * rays[..., 0], position[1] + t * rays[..., 1]


def test_eq1_rotates_the_metric_image_coordinates_by_minus_psi() -> None:
    c, r = np.array([1.0, 0.0, -0.3]), np.array([0.0, 1.0, 0.4])
    c_psi, r_psi = roll_compensation(c, r, 0.3)
    assert np.allclose(np.hypot(c_psi, r_psi), np.hypot(c, r))
    assert np.allclose(np.arctan2(r_psi, c_psi) - np.arctan2(r, c), -0.3)
    assert np.allclose(roll_compensation(c, r, 0.0), (c, r))


def test_metric_image_coordinates_are_centred_on_the_principal_point() -> None:
    calibration = scene_calibration()
    k = calibration.intrinsics
    c, r = metric_image_coordinates(np.array([k.cx, k.cx + k.fx]), np.array([k.cy, k.cy - 2 * k.fy]), calibration)
    assert np.allclose(c, [0.0, 1.0]) and np.allclose(r, [0.0, -2.0])


def test_eq2_is_the_ray_plane_intersection_of_the_pitched_camera() -> None:
    calibration = scene_calibration()
    v, u = np.mgrid[200:480:20, 0:640:40].astype(np.float64)
    for theta in (0.0, 0.05, -0.04):
        x, y, hits = mc_pixel_to_ground(u, v, calibration, 0.0, theta)
        rotation = compensated_camera_to_base(calibration, 0.0, theta)
        x_ref, y_ref = _ray_plane(u, v, calibration, rotation)
        assert hits.all()
        assert np.allclose(x, x_ref, atol=1e-9) and np.allclose(y, y_ref, atol=1e-9)


def test_eq2_as_printed_differs_laterally_once_pitched() -> None:
    """The printed lateral term cos(Phi + theta) is off by up to cm at theta = 0.05 (why the exact form is used)."""
    calibration = scene_calibration()
    v, u = np.mgrid[200:480:20, 0:640:40].astype(np.float64)
    c, r = metric_image_coordinates(u, v, calibration)
    theta = 0.05
    x_c, y_c, _ = compensated_ground_point(c, r, calibration.height, calibration.tilt, theta)
    phi = np.arctan(r)
    y_printed = -x_c * c * np.cos(phi + theta) / np.cos(calibration.tilt + phi + theta)
    deviation = np.abs(y_printed - y_c)
    print(f"printed eq. 2 lateral deviation at theta = 0.05: up to {deviation.max() * 100:.1f} cm")
    assert deviation.max() > 0.01


def test_rays_above_the_horizon_do_not_hit_the_ground() -> None:
    calibration = scene_calibration()
    x, _, hits = mc_pixel_to_ground(np.array([320.0, 320.0]), np.array([0.0, 479.0]), calibration)
    assert hits.tolist() == [False, True]
    assert np.isnan(x[0]) and np.isfinite(x[1]) and x[1] > 0.25


@pytest.mark.parametrize("psi,theta", [(0.0, 0.0), (0.04, -0.03), (-0.05, 0.06), (0.02, 0.1)])
def test_the_homography_inverts_eq1_eq2_exactly(psi: float, theta: float) -> None:
    """The fast path (a homography) and the literal eq. 1-2 map every BEV pixel to the same ground point."""
    calibration = scene_calibration()
    h = bev_to_image_homography(calibration, GRID, psi, theta)
    v, u = np.mgrid[0 : GRID.height : 5, 0 : GRID.width : 5].astype(np.float64)
    image = np.stack([u, v, np.ones_like(u)], axis=-1) @ h.T
    x, y, hits = mc_pixel_to_ground(
        image[..., 0] / image[..., 2], image[..., 1] / image[..., 2], calibration, psi, theta
    )
    x_bev, y_bev = GRID.pixel_to_ground(u, v)
    assert hits.all()
    assert np.max(np.hypot(x - x_bev, y - y_bev)) < 1e-9


def test_plain_homography_is_the_calibrated_projection() -> None:
    calibration = scene_calibration()
    points = np.array([[1.0, 0.0], [3.0, 1.5], [5.0, -2.0]])
    rotation, position = camera_pose(calibration, 0.0, 0.0, 0.0)
    camera = (np.column_stack([points, np.zeros(3)]) - position) @ rotation
    expected = camera @ calibration.intrinsics.matrix.T
    mapped = np.column_stack([points, np.ones(3)]) @ ground_to_image_homography(calibration).T
    assert np.allclose(mapped[:, :2] / mapped[:, 2:], expected[:, :2] / expected[:, 2:], atol=1e-9)


def test_roll_about_the_base_axis_is_the_robot_roll() -> None:
    """roll_axis=base reproduces a camera on a robot rolled by phi (psi = -phi); optical matches only a level camera."""
    calibration = scene_calibration()
    phi = 0.04
    true_rotation, _ = camera_pose(calibration, 0.0, phi, 0.0)
    assert np.allclose(compensated_camera_to_base(calibration, -phi, 0.0, "base"), true_rotation)
    assert not np.allclose(compensated_camera_to_base(calibration, -phi, 0.0, "optical"), true_rotation, atol=1e-3)
    level = Calibration.from_mounting(calibration.intrinsics, 0.8, 0.0)
    level_true, _ = camera_pose(level, 0.0, phi, 0.0)
    assert np.allclose(compensated_camera_to_base(level, -phi, 0.0, "optical"), level_true)


def test_visible_mask_is_the_per_pixel_rule() -> None:
    """Centre in front of the camera and inside [0, W-1] x [0, H-1]: interval rows equal the brute force."""
    calibration = scene_calibration()
    for psi, theta in ((0.0, 0.0), (0.05, -0.08), (-0.1, 0.2)):
        h = bev_to_image_homography(calibration, GRID, psi, theta)
        v, u = np.mgrid[0 : GRID.height, 0 : GRID.width].astype(np.float64)
        p = np.stack([u, v, np.ones_like(u)], axis=-1) @ h.T
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
        brute = (p[..., 2] > 1e-3) & (x >= 0) & (x <= 639) & (y >= 0) & (y <= 479)
        mask = visible_mask(h, GRID, 640, 480)
        assert (mask != brute).sum() == 0
        assert 0 < mask.sum() < mask.size


def test_visible_mask_excludes_ground_behind_the_camera() -> None:
    """A downward camera with a BEV reaching behind it: the half-plane of negative depth is not visible."""
    intrinsics = Intrinsics(fx=300.0, fy=300.0, cx=319.5, cy=239.5, width=640, height=480)
    calibration = Calibration.from_mounting(intrinsics, height=2.0, tilt=math.radians(80.0))
    grid = BevGrid(0.05, -6.0, 6.0, -3.0, 3.0)
    h = bev_to_image_homography(calibration, grid)
    mask = visible_mask(h, grid, 640, 480)
    x, _ = grid.pixel_to_ground(np.zeros(grid.height), np.arange(grid.height, dtype=np.float64))
    depth = (np.stack([np.zeros(grid.height), np.arange(grid.height), np.ones(grid.height)], axis=1) @ h.T)[:, 2]
    assert not mask[depth <= 0].any()
    assert mask[np.argmin(np.abs(x))].any()  # the ground under the camera is seen
