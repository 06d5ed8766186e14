"""The odometry's drift model: how far a pose predicted across a drive may be off, and its heading bias.

A relative pose predicted by dead reckoning across ``d`` metres since a loop last anchored its two
ends is off by a translation random walk (``sigma_xy^2 d``), a heading random walk whose lateral
effect grows as ``d^1.5`` (``sigma_yaw^2 d^3 / 3``), a scale error (``scale_error d``) and the
heading bias ``b`` (rad/m) that bends the drive (``b d^2 / 2`` of position, ``b d`` of heading),
over floors that hold right after an anchor (:func:`drift_covariance`, the loop gate). The
association's spatial gate is the same drift as a radius, ``floor + rate d + q d^2`` with ``q`` a
share of the bias's ``b / 2`` (:func:`drift_radius`, :func:`bias_growth`). Both gates read the
heading bias from the back-end's model (``PoseEstimate.yaw_bias``) when it publishes one, and the
loop gate its random walks and scale error as the camera measured them (``PoseEstimate.drift``,
:func:`measured_sigmas`), its priors until then.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from sgf_pipeline.geometry import invert, wrap_angle, xy_yaw
from sgf_pipeline.types import PoseEstimate

#: The bias wheel odometry is expected to have (rad per metre): it chooses between readings of the loops'
#: turns that the loops cannot tell apart, and the gates count it until the back-end knows better
#: (:func:`uncorrected_yaw_bias`). Wheel odometry drifts by up to a few tenths of a degree per metre.
EXPECTED_YAW_BIAS = math.radians(0.1)


class DriftSigmas(Protocol):
    """The drift model's sigmas (``loop.gate`` holds them)."""

    @property
    def floor_xy(self) -> float:
        """m, position sigma right after an anchor."""

    @property
    def floor_yaw_deg(self) -> float:
        """deg, heading sigma right after an anchor."""

    @property
    def sigma_xy(self) -> float:
        """m/sqrt(m), translation random walk."""

    @property
    def sigma_yaw_deg(self) -> float:
        """deg/sqrt(m), heading random walk."""

    @property
    def scale_error(self) -> float:
        """Odometry scale error, a fraction of the distance."""


@dataclass(frozen=True)
class Sigmas:
    """Drift sigmas (:class:`DriftSigmas`) as values."""

    floor_xy: float
    floor_yaw_deg: float
    sigma_xy: float
    sigma_yaw_deg: float
    scale_error: float


def measured_sigmas(prior: DriftSigmas, estimate: PoseEstimate | None) -> DriftSigmas:
    """The drift sigmas with the odometry's errors as measured (``PoseEstimate.drift``), the priors elsewhere."""
    drift = None if estimate is None else estimate.drift
    if drift is None:
        return prior
    return Sigmas(
        prior.floor_xy,
        prior.floor_yaw_deg,
        prior.sigma_xy if drift.sigma_xy is None else drift.sigma_xy,
        prior.sigma_yaw_deg if drift.sigma_yaw is None else math.degrees(drift.sigma_yaw),
        prior.scale_error if drift.scale_error is None else drift.scale_error,
    )


def drift_covariance(distance: float, p: DriftSigmas, yaw_bias: float = EXPECTED_YAW_BIAS) -> np.ndarray:
    """Covariance (x, y, yaw) of a relative pose predicted across ``distance`` metres since the last anchor.

    ``yaw_bias`` (rad/m): the heading bias in the estimate's odometry (root mean square).
    """
    d = max(distance, 0.0)
    s_yaw = math.radians(p.sigma_yaw_deg)
    bias = abs(yaw_bias)
    var_xy = (
        p.floor_xy**2 + (p.scale_error * d) ** 2 + p.sigma_xy**2 * d + s_yaw**2 * d**3 / 3.0 + (0.5 * bias * d**2) ** 2
    )
    var_yaw = math.radians(p.floor_yaw_deg) ** 2 + s_yaw**2 * d + (bias * d) ** 2
    return np.diag([var_xy, var_xy, var_yaw])


def pose_error(predicted: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """``(x, y, yaw)`` of ``measured`` seen from ``predicted``."""
    x, y, yaw = xy_yaw(invert(predicted) @ measured)
    return np.array([x, y, wrap_angle(yaw)])


def mahalanobis2(error: np.ndarray, covariance: np.ndarray) -> float:
    """Squared Mahalanobis distance of an error under a covariance."""
    return float(error @ np.linalg.solve(covariance, error))


def uncorrected_yaw_bias(estimate: PoseEstimate | None) -> float:
    """The heading bias (rad/m, root mean square) a gate counts on odometry nothing was taken off.

    The back-end's model (``PoseEstimate.yaw_bias``) when it publishes one, else ``EXPECTED_YAW_BIAS``.
    """
    correction = None if estimate is None else estimate.yaw_bias
    return EXPECTED_YAW_BIAS if correction is None else correction.uncorrected


def corrected_yaw_bias(estimate: PoseEstimate | None) -> tuple[int, float] | None:
    """The frame after which the back-end takes the heading bias off, and the bias a gate counts there (rad/m).

    The uncertainty of the bias left, never more than the bias on odometry nothing was taken off;
    None where nothing is taken off.
    """
    correction = None if estimate is None else estimate.yaw_bias
    if correction is None or correction.since is None:
        return None
    return correction.since, min(correction.sigma, correction.uncorrected)


def bias_growth(bias: float, share: float) -> float:
    """Growth per squared metre (1/m) of a position envelope for a heading bias (rad/m).

    ``share`` of the lateral offset ``0.5 b d^2`` that bias gives a straight drive of ``d`` metres.
    """
    return share * 0.5 * abs(bias)


def drift_radius(travelled: np.ndarray, floor: float, rate: float, quadratic: np.ndarray | float) -> np.ndarray:
    """A position envelope (m) across ``travelled`` metres: ``floor + rate d + quadratic d^2``."""
    return floor + rate * travelled + quadratic * travelled**2
