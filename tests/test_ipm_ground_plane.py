"""The ground plane measured from two views (``ipm=mc_plane``): the fit on an exact scene, the filter."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from ipm_scene import scene_calibration
from sgf_plugins.ipm import IpmParams
from sgf_plugins.ipm.ground_plane import GradeFilter, GroundPlaneTracker
from sgf_plugins.shared.bev_homography import compensated_camera_to_base, ground_to_image_homography

from sgf_pipeline.geometry import rotation_rpy

STEP = 0.01  # m per texture pixel
ORIGIN = (-2.0, -6.0)  # ground (x, y) of texture pixel (0, 0)


def _texture(seed: int = 0) -> np.ndarray:
    """Paving-like grain: smoothed noise at two scales, 12 m x 12 m at 1 cm."""
    rng = np.random.default_rng(seed)
    fine = cv2.GaussianBlur(rng.uniform(0, 255, (1200, 1200)).astype(np.float32), (0, 0), 1.5)
    coarse = cv2.GaussianBlur(rng.uniform(0, 255, (1200, 1200)).astype(np.float32), (0, 0), 8.0)
    return np.clip(110 + 1.5 * (fine - fine.mean()) + 3.0 * (coarse - coarse.mean()), 0, 255).astype(np.uint8)


def _view(texture: np.ndarray, calibration, x: float, psi: float, theta: float) -> tuple[np.ndarray, np.ndarray]:
    """The image of the flat ground from a camera at ``x`` pitched ``theta`` and rolled ``psi``, and its true odometry."""
    shift = np.array([[1.0, 0.0, -x], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # world ground -> this base's ground
    to_texture = np.array([[1 / STEP, 0.0, -ORIGIN[0] / STEP], [0.0, 1 / STEP, -ORIGIN[1] / STEP], [0.0, 0.0, 1.0]])
    h = ground_to_image_homography(calibration, psi, theta) @ shift @ np.linalg.inv(to_texture)
    intr = calibration.intrinsics
    image = cv2.warpPerspective(texture, h, (intr.width, intr.height), flags=cv2.INTER_LINEAR)
    camera_to_base = calibration.camera_to_base_matrix
    rotation = compensated_camera_to_base(calibration, psi, theta) @ camera_to_base[:3, :3].T
    centre = np.array([x, 0.0, 0.0]) + camera_to_base[:3, 3]  # compensation turns about the camera centre
    odometry = np.eye(4)
    odometry[:3, :3] = rotation
    odometry[:3, 3] = centre - rotation @ camera_to_base[:3, 3]
    return image, odometry


@pytest.fixture(scope="module")
def scene() -> tuple:
    return scene_calibration(), _texture()


def test_two_views_of_a_plane_give_its_pitch_and_roll(scene) -> None:
    calibration, texture = scene
    tracker = GroundPlaneTracker(IpmParams().grid, baseline=1.0)
    earlier, odometry_s = _view(texture, calibration, 0.0, 0.0, 0.005)
    assert tracker.measure(earlier, odometry_s, calibration, 0.0, 0.0) is None  # nothing to pair it with yet
    current, odometry_t = _view(texture, calibration, 1.0, -0.01, 0.02)
    # the odometry's attitude is off by 3 mrad of pitch and 2 of roll (the IMU's noise): the fit corrects it
    odometry_t[:3, :3] = odometry_t[:3, :3] @ rotation_rpy(0.002, 0.003, 0.0)
    fit = tracker.measure(current, odometry_t, calibration, 0.0, 0.0)
    assert fit is not None
    assert fit.theta == pytest.approx(0.02, abs=1e-3)
    assert fit.psi == pytest.approx(-0.01, abs=1.5e-3)
    assert fit.baseline == pytest.approx(1.0, abs=0.02)  # by the base origins, which the pitch moves a little
    assert fit.samples > 1000


def test_no_fit_without_texture_or_without_baseline(scene) -> None:
    calibration, texture = scene
    tracker = GroundPlaneTracker(IpmParams().grid, baseline=1.0, min_baseline=0.5)
    blank = np.full((calibration.intrinsics.height, calibration.intrinsics.width), 120, np.uint8)
    _, odometry_s = _view(texture, calibration, 0.0, 0.0, 0.0)
    _, odometry_t = _view(texture, calibration, 1.0, 0.0, 0.0)
    tracker.measure(blank, odometry_s, calibration, 0.0, 0.0)
    assert tracker.measure(blank, odometry_t, calibration, 0.0, 0.0) is None  # a blank ground says nothing
    close = GroundPlaneTracker(IpmParams().grid, baseline=1.0, min_baseline=0.5)
    image, odometry = _view(texture, calibration, 0.0, 0.0, 0.0)
    close.measure(image, odometry, calibration, 0.0, 0.0)
    image, odometry = _view(texture, calibration, 0.3, 0.0, 0.0)
    assert close.measure(image, odometry, calibration, 0.0, 0.0) is None  # 0.3 m apart: below min_baseline
    with pytest.raises(ValueError, match="min_baseline"):
        GroundPlaneTracker(IpmParams().grid, baseline=0.4, min_baseline=0.5)


def test_the_grade_filter_follows_a_ramp_and_shrugs_off_an_outlier() -> None:
    rng = np.random.default_rng(1)
    grade = GradeFilter(rate_noise=0.01, measurement_noise=0.003)
    assert grade.value is None
    step = 0.25
    truth = [0.0 if k < 40 else min(0.02 * step * (k - 40), 0.06) for k in range(120)]
    errors = []
    for k, angle in enumerate(truth):
        grade.predict(step)
        measured = angle + rng.normal(0.0, 0.003) + (0.1 if k == 100 else 0.0)  # one bad fit at k = 100
        grade.update(measured)
        value = grade.value
        assert value is not None
        errors.append(abs(value - angle))
    assert np.mean(errors[:40]) < 0.002  # flat: below one fit's mean error (0.0024 for a noise of 0.003)
    assert max(errors[60:]) < 0.01  # on and after the ramp, and at the outlier
    assert errors[100] < 0.01
    # no measurements for 20 m: the rate decays, the angle stays near its last value
    before = grade.value
    assert grade.state is not None and before is not None
    rate = float(grade.state[1])
    for _ in range(80):
        grade.predict(step)
    assert grade.value is not None
    # it moves on by about the rate times its memory (3 m), not the rate times 20 m
    assert abs(grade.value - before) <= abs(rate) * (grade.rate_memory + step)
    assert abs(grade.value - before) < 0.01
    assert math.isfinite(grade.covariance[0, 0])
