"""Compensation strategies that measure the ground ahead (extensions of Sec. III-A): ``mc_plane``, ``mc_hindsight``.

Both keep ``ipm=mc_ahead``'s pose queue reference (:class:`~sgf_plugins.ipm.compensation.PoseQueueReference`)
running on every frame and read its :class:`~sgf_plugins.ipm.compensation.RelativeAttitude`: the
robot's own attitude for :class:`GroundPlaneCompensation`, the fallback for :class:`HindsightCompensation`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sgf_pipeline.imu import steadied
from sgf_pipeline.types import BevGrid, Frame
from sgf_plugins.ipm.compensation import PoseQueueReference
from sgf_plugins.ipm.ground_plane import GradeFilter, GroundPlaneTracker
from sgf_plugins.ipm.hindsight import AttitudeWindow, GroundAhead, ground_ahead, path_profile
from sgf_plugins.ipm.params import HindsightMotionCompensatedIpmParams, PlaneMotionCompensatedIpmParams
from sgf_plugins.shared.bev_homography import RollAxis


class GroundPlaneCompensation:
    """``ipm=mc_plane``: the robot's own attitude (IMU, against the reference) plus the ground ahead's, from two views.

    :class:`~sgf_plugins.ipm.ground_plane.GroundPlaneTracker` fits the plane that maps the current
    view onto one about ``plane_baseline`` metres back; a Kalman filter over distance
    (:class:`~sgf_plugins.ipm.ground_plane.GradeFilter`) smooths the fitted ``(psi, theta)`` minus
    the robot's own. Until the first fit, and without an image, it is the reference's compensation.
    ``max_abs_pitch_compensation`` counts the reference's ``theta``.
    """

    read_ahead = 0.0

    def __init__(self, params: PlaneMotionCompensatedIpmParams) -> None:
        self.params = params
        self.roll_axis: RollAxis = params.roll_axis
        self.reference = PoseQueueReference(params)
        self.tracker = GroundPlaneTracker(
            params.grid,
            baseline=params.plane_baseline,
            min_baseline=params.plane_min_baseline,
            scales=tuple(params.plane_scales),
            iterations=params.plane_iterations,
            rotation_prior=params.plane_rotation_prior,
            height_prior=params.plane_height_prior,
            roll_axis=params.roll_axis,
        )
        self.pitch_filter = GradeFilter(params.plane_rate_noise, params.plane_measurement_noise)
        self.roll_filter = GradeFilter(params.plane_rate_noise, params.plane_measurement_noise)
        self._recent_motion: list[tuple[float, float]] = []
        self._start: tuple[float, float] | None = None
        self.counts = {"plane_fits": 0, "plane_skipped_bumps": 0, "plane_no_fit": 0}

    def reset(self) -> None:
        """Forget the reference, the views, the filters and the counts of the previous sequence."""
        self.reference.reset()
        self.tracker.reset()
        self.pitch_filter.reset()
        self.roll_filter.reset()
        self._recent_motion = []
        self._start = None
        self.counts = dict.fromkeys(self.counts, 0)

    def compensate(self, frame: Frame, image: np.ndarray | None, grid: BevGrid) -> tuple[float, float]:
        """``(psi, theta)``: the robot's own attitude (IMU) plus the ground ahead's (fitted, filtered)."""
        ahead = self.reference.relative(frame)
        self.reference.record(ahead.theta)
        psi_motion, theta_motion = ahead.motion
        self.pitch_filter.predict(ahead.step)
        self.roll_filter.predict(ahead.step)
        threshold = self.params.plane_bump_threshold
        window = self.params.plane_baseline + 0.4
        travelled = ahead.travelled
        self._recent_motion = [(d, m) for d, m in self._recent_motion if travelled - d <= window]
        bumpy = abs(theta_motion) > threshold or any(m > threshold for _, m in self._recent_motion)
        self._recent_motion.append((travelled, abs(theta_motion)))
        if image is not None:
            self.tracker.grid = grid
            start = self._start if self._start is not None else (ahead.psi, ahead.theta)
            fit = self.tracker.measure(image, frame.odometry, frame.calibration, *start)
            if fit is None:
                self.counts["plane_no_fit"] += 1
                self._start = None
            elif bumpy:
                self.counts["plane_skipped_bumps"] += 1
                self._start = (fit.psi, fit.theta)
            else:
                self.counts["plane_fits"] += 1
                self.pitch_filter.update(fit.theta - theta_motion)
                self.roll_filter.update(fit.psi - psi_motion)
                self._start = (fit.psi, fit.theta)
        pitch_ahead, roll_ahead = self.pitch_filter.value, self.roll_filter.value
        if pitch_ahead is None or roll_ahead is None:
            return ahead.psi, ahead.theta
        psi = psi_motion + roll_ahead if self.params.compensate_roll else 0.0
        theta = theta_motion + pitch_ahead if self.params.compensate_pitch else 0.0
        return psi, theta

    def metrics(self) -> dict[str, Any]:
        """The reference's counts, and how many frames had a plane fit, were skipped in a bump, or had none."""
        return {**self.reference.metrics(), **self.counts}


class HindsightCompensation:
    """``ipm=mc_hindsight``: the robot's attitude against the plane of the path it drove next.

    :func:`~sgf_plugins.ipm.hindsight.ground_ahead` fits the plane of the ground within the BEV's
    reach to ``Frame.path_ahead``; the robot's own attitude is the median IMU attitude around the
    frame plus the frame's shrunk deviation (:class:`~sgf_plugins.ipm.hindsight.AttitudeWindow`).
    ``theta`` (eq. 2) is the robot's pitch against that plane, ``psi`` (eq. 1) its roll against
    the ground's roll there. Without a path it is the reference's compensation.
    """

    def __init__(self, params: HindsightMotionCompensatedIpmParams) -> None:
        self.params = params
        self.roll_axis: RollAxis = params.roll_axis
        self.reference = PoseQueueReference(params)
        self.window = AttitudeWindow(params.attitude_window)
        self.last_ground: GroundAhead | None = None
        self.counts = {"hindsight_planes": 0, "hindsight_fallbacks": 0}

    @property
    def read_ahead(self) -> float:
        """``hindsight``: the metres of path the runner reads ahead of each frame."""
        return self.params.hindsight

    def reset(self) -> None:
        """Forget the reference, the attitudes and the counts of the previous sequence."""
        self.reference.reset()
        self.window.reset()
        self.last_ground = None
        self.counts = dict.fromkeys(self.counts, 0)

    def compensate(self, frame: Frame, image: np.ndarray | None, grid: BevGrid) -> tuple[float, float]:
        """``(psi, theta)`` against the plane of the path ahead; the reference's without one."""
        fallback = self.reference.relative(frame)  # keeps the queue and its counts going
        travelled = fallback.travelled
        roll, pitch = self.reference.attitude(frame)
        path = frame.path_ahead
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        ground = None
        if path is not None and math.isfinite(roll) and math.isfinite(pitch):
            profile = path_profile(odometry, path)
            ground = ground_ahead(
                odometry, path, grid.x_min, grid.x_max, self.params.hindsight_min_reach, profile=profile
            )
            self.window.add(travelled, roll, pitch)
            for distance, (r, p) in zip(profile[0], path.imu_roll_pitch, strict=True):
                self.window.add(travelled + float(distance), float(r), float(p))
        self.last_ground = ground
        smooth = self.window.median(travelled) if ground is not None else None
        if ground is None or smooth is None:
            self.counts["hindsight_fallbacks"] += 1
            self.reference.record(fallback.theta)
            return fallback.psi, fallback.theta
        self.counts["hindsight_planes"] += 1
        noise = self.params.attitude_noise
        body_roll = steadied(roll, smooth[0], noise)
        body_pitch = steadied(pitch, smooth[1], noise)
        ground_roll = body_roll if ground.roll is None else ground.roll
        psi = -(body_roll - ground_roll) if self.params.compensate_roll else 0.0
        theta = body_pitch - ground.pitch if self.params.compensate_pitch else 0.0
        self.reference.record(theta)  # this pitch, not the fallback's
        return psi, theta

    def metrics(self) -> dict[str, Any]:
        """The reference's counts, and how many frames had a plane from the path ahead or fell back to it."""
        return {**self.reference.metrics(), **self.counts}
