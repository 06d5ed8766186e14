"""The IPM stages' compensation strategies: the ``(psi, theta)`` of eq. 1-2 each frame is warped with.

An IPM stage resamples the image into the BEV; its strategy decides the compensation:
:class:`NoCompensation` (plain IPM) or :class:`ReferenceCompensation` (MC-IPM, paper Sec. III-A:
the robot's attitude against the reference attitude of a pose queue, :class:`PoseQueueReference`).
The strategies that also measure the ground ahead are in :mod:`sgf_plugins.ipm.ahead`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from sgf_pipeline import DataError
from sgf_pipeline.geometry import rpy_from_rotation
from sgf_pipeline.imu import shrink_noise
from sgf_pipeline.types import BevGrid, Frame
from sgf_plugins.ipm.params import MotionCompensatedIpmParams
from sgf_plugins.ipm.reference import PoseQueue, ReferenceAttitude
from sgf_plugins.shared.bev_homography import RollAxis

_LOGGED_DROPOUTS = 5
log = logging.getLogger("sgf_pipeline.ipm")


class Compensation(Protocol):
    """A compensation strategy: the ``(psi, theta)`` of eq. 1-2 per frame, and what it counted."""

    @property
    def roll_axis(self) -> RollAxis:
        """The axis eq. 1's roll turns about (``bev_to_image_homography``)."""
        ...

    @property
    def read_ahead(self) -> float:
        """Metres of path after a frame the strategy reads (``Frame.path_ahead``)."""
        ...

    def reset(self) -> None:
        """Forget the previous sequence."""
        ...

    def compensate(self, frame: Frame, image: np.ndarray | None, grid: BevGrid) -> tuple[float, float]:
        """``(psi, theta)`` for the frame (``image``: the pixels the IPM warps into ``grid``)."""
        ...

    def metrics(self) -> dict[str, Any]:
        """What the stage writes to metrics.json under ``ipm`` (nothing: an empty dict)."""
        ...


class NoCompensation:
    """Plain IPM: every frame is warped as if the robot stood level on a flat ground."""

    roll_axis: RollAxis = "optical"
    read_ahead = 0.0

    def reset(self) -> None:
        """Nothing to forget."""

    def compensate(self, frame: Frame, image: np.ndarray | None, grid: BevGrid) -> tuple[float, float]:
        """No compensation: ``(0, 0)``."""
        return 0.0, 0.0

    def metrics(self) -> dict[str, Any]:
        """Nothing counted."""
        return {}


def _odometry_attitude(frame: Frame) -> tuple[float, float]:
    """Roll and pitch (rad) of the frame's odometry pose; NaN when the pose is not a finite 4x4 matrix."""
    odometry = np.asarray(frame.odometry, dtype=np.float64)
    if odometry.shape != (4, 4) or not np.all(np.isfinite(odometry)):
        return math.nan, math.nan
    roll, pitch, _ = rpy_from_rotation(odometry[:3, :3])
    return roll, pitch


@dataclass(frozen=True)
class RelativeAttitude:
    """One frame's attitude against the pose queue's reference attitude (eq. 1-2).

    ``psi`` and ``theta``: the compensation of eq. 1-2 (the ground ahead's pitch included, either
    zero when ``compensate_roll``/``compensate_pitch`` is off); ``motion``: the robot's own
    ``(psi, theta)`` against its ground, noise shrunk out; ``step``: metres driven since the
    previous queued frame; ``travelled``: metres the pose queue has seen driven.
    """

    psi: float
    theta: float
    motion: tuple[float, float]
    step: float
    travelled: float


class PoseQueueReference:
    """MC-IPM's reference attitude: the robot's roll and pitch against the robust average of a pose queue.

    Per frame: read the attitude (IMU roll/pitch, or the odometry pose's), push it into the pose
    queue, take the queue's robust average as the reference (:class:`PoseQueue`: median-centred,
    poses with a pitch further than ``pitch_threshold`` from it left out), and compensate the
    difference: ``theta = pitch - pitch_ref`` in eq. 2 (positive nose down, like ``alpha``) and
    ``psi = -(roll - roll_ref)`` in eq. 1 (eq. 1's rotation sense in image coordinates). A speed
    bump is compensated by its own pitch; a slope becomes the reference after half a queue.

    A frame whose attitude is not finite (an IMU dropout) keeps the run going: with
    ``attitude=auto`` the odometry pose's attitude stands in (``attitude_from_odometry``), else the
    frame gets no compensation and is not queued (``attitude_dropouts``). :meth:`metrics` adds
    ``outlier_frames`` (frames whose own pitch lay beyond ``pitch_threshold`` of the reference pitch)
    and ``reference_without_inliers`` (frames whose queue had no pose within the threshold of its
    centre), and ``max_abs_pitch_compensation``, the largest ``theta`` given to :meth:`record`.
    """

    def __init__(self, params: MotionCompensatedIpmParams) -> None:
        self.params = params
        self.queue = PoseQueue(
            params.queue_size,
            params.pitch_threshold,
            params.reference_center,
            params.roll_threshold,
            params.settle,
            params.reference_fit,
            params.lookahead,
        )
        self._last_position: np.ndarray | None = None
        self.last_reference: ReferenceAttitude | None = None
        self.counts: dict[str, int] = {}
        self.largest_theta = 0.0
        self.reset()

    def reset(self) -> None:
        """Empty the pose queue: a new sequence starts with no reference."""
        self.queue.reset()
        self._last_position = None
        self.last_reference = None
        self.counts = {
            "frames": 0,
            "attitude_from_odometry": 0,
            "attitude_dropouts": 0,
            "outlier_frames": 0,
            "reference_without_inliers": 0,
        }
        self.largest_theta = 0.0

    def attitude(self, frame: Frame) -> tuple[float, float]:
        """The frame's ``(roll, pitch)`` in rad from the configured source."""
        source = self.params.attitude
        if source == "imu" or (source == "auto" and frame.imu_roll_pitch is not None):
            if frame.imu_roll_pitch is None:
                raise DataError(
                    f"frame {frame.index} has no IMU roll/pitch but ipm.attitude=imu; "
                    "use ipm.attitude=auto (odometry fallback) or ipm.attitude=odometry"
                )
            roll, pitch = frame.imu_roll_pitch
            return float(roll), float(pitch)
        return _odometry_attitude(frame)

    def relative(self, frame: Frame) -> RelativeAttitude:
        """Queue the frame's attitude and return it against the reference (zero when it has none)."""
        self.counts["frames"] += 1
        roll, pitch = self.attitude(frame)
        if not (math.isfinite(roll) and math.isfinite(pitch)) and self.params.attitude == "auto":
            roll, pitch = _odometry_attitude(frame)
            if math.isfinite(roll) and math.isfinite(pitch):
                self._count("attitude_from_odometry", frame, "the IMU roll/pitch is not finite; the odometry's is used")
        if not (math.isfinite(roll) and math.isfinite(pitch)):
            self._count("attitude_dropouts", frame, "no finite roll/pitch; warped at the reference attitude")
            # not queued: the next frame's step covers this one's
            return RelativeAttitude(0.0, 0.0, (0.0, 0.0), 0.0, self.queue.travelled)
        step = self._step(frame)
        self.queue.push(roll, pitch, step)
        reference = self.queue.reference()
        self.last_reference = reference
        if reference.inliers == 0:
            self.counts["reference_without_inliers"] += 1
        if abs(pitch - reference.pitch) > self.params.pitch_threshold:
            self.counts["outlier_frames"] += 1
        noise = self.params.attitude_noise
        # a deviation d from the reference is motion plus the IMU's noise: shrunk by d^2 / (d^2 + sigma^2),
        # it is kept whole when large (a bump) and mostly dropped when of the noise's size
        roll_motion = shrink_noise(roll - reference.roll, noise)
        pitch_motion = shrink_noise(pitch - reference.pitch, noise)
        psi = -roll_motion if self.params.compensate_roll else 0.0
        # the ground ahead's pitch against the ground under the robot: exactly 0.0 for the paper's mean
        ahead = reference.pitch - reference.target_pitch
        theta = pitch_motion + ahead if self.params.compensate_pitch else 0.0
        return RelativeAttitude(psi, theta, (-roll_motion, pitch_motion), step, self.queue.travelled)

    def record(self, theta: float) -> None:
        """Count ``theta`` towards ``max_abs_pitch_compensation``."""
        self.largest_theta = max(self.largest_theta, abs(theta))

    def metrics(self) -> dict[str, Any]:
        """The frame counts and the largest pitch compensation recorded."""
        entry: dict[str, Any] = dict(self.counts)
        entry["max_abs_pitch_compensation"] = round(self.largest_theta, 6)
        return entry

    def _step(self, frame: Frame) -> float:
        """Metres driven since the previous frame, from the odometry (0 when it is not finite)."""
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        if odometry.shape != (4, 4) or not np.all(np.isfinite(odometry[:3, 3])):
            return 0.0
        position = odometry[:3, 3].copy()
        previous, self._last_position = self._last_position, position
        return 0.0 if previous is None else float(np.linalg.norm(position - previous))

    def _count(self, key: str, frame: Frame, what: str) -> None:
        self.counts[key] += 1
        if self.counts[key] <= _LOGGED_DROPOUTS:
            log.warning("ipm=mc: frame %s: %s (%s so far)", frame.index, what, self.counts[key])


class MotionCompensation(Compensation, Protocol):
    """A strategy compensating the robot's motion: it has a pose queue reference (its own or its fallback)."""

    @property
    def reference(self) -> PoseQueueReference:
        """The pose queue and its reference attitude."""
        ...


class ReferenceCompensation:
    """MC-IPM (``ipm=mc``, and ``ipm=mc_ahead`` by its parameters): eq. 1-2 against the reference attitude."""

    read_ahead = 0.0

    def __init__(self, params: MotionCompensatedIpmParams) -> None:
        self.roll_axis: RollAxis = params.roll_axis
        self.reference = PoseQueueReference(params)

    def reset(self) -> None:
        """Empty the pose queue."""
        self.reference.reset()

    def compensate(self, frame: Frame, image: np.ndarray | None, grid: BevGrid) -> tuple[float, float]:
        """The frame's attitude against the pose queue's reference."""
        relative = self.reference.relative(frame)
        self.reference.record(relative.theta)
        return relative.psi, relative.theta

    def metrics(self) -> dict[str, Any]:
        """The reference's counts."""
        return self.reference.metrics()
