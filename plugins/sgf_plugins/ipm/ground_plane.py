"""The ground plane ahead measured from two views: the attitude MC-IPM needs, taken from the image (extension).

MC-IPM (paper Sec. III-A) compensates the robot's roll and pitch against a reference attitude from
past poses. Where the grade of the ground *ahead* changes (the foot of a hill, its crest), no past
pose knows it (docs/results.md, Table 4). The camera sees it: the ground
seen from two places along the drive is related by the homography its plane induces,

    x_s ~ K (R_st - t_st n^T / h) K^-1 x_t,                 (plane n . X = -h in camera t)

where ``(R_st, t_st)`` is camera t's pose in camera s (from the odometry, about 0.6 m back),
``n`` the plane's upward normal and ``h`` the camera's height above it. The plane is
parameterised by the ``(psi, theta)`` of eq. 1-2 (the compensated camera's up axis is ``n``), so
the estimate goes straight into the IPM's homography. :class:`GroundPlaneTracker` finds ``(psi,
theta)`` with a small correction of the relative rotation (the IMU's noise) and of the height
(the odometry's scale error) by Gauss-Newton on the photometric difference of the two views,
coarse to fine, with Huber weights (occluders, shadows that moved) and weak priors on the
corrections.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.types import BevGrid
from sgf_plugins.shared.bev_homography import RollAxis, bev_to_image_homography, compensated_camera_to_base

#: Parameters: psi, theta (rad, eq. 1-2), log of the height scale, relative rotation correction (rad, 3).
NUM_PARAMS = 6
_STEP = 1e-4  # finite-difference step of every parameter


@dataclass(frozen=True)
class PlaneMeasurement:
    """``(psi, theta)`` of the ground plane seen from two views, with its standard deviation and support."""

    psi: float
    theta: float
    theta_std: float
    baseline: float
    samples: int
    residual: float


@dataclass
class _View:
    levels: list[tuple[np.ndarray, np.ndarray, np.ndarray]]  # per level: image, d/du, d/dv (float32)
    camera: np.ndarray  # camera pose (4x4) in the odometry frame
    travelled: float  # metres along the drive, by odometry


def _rotation_vector(omega: np.ndarray) -> np.ndarray:
    rotation, _ = cv2.Rodrigues(np.asarray(omega, dtype=np.float64).reshape(3, 1))
    return rotation


class GroundPlaneTracker:
    """Measures the camera's roll and pitch against the ground ahead from the current and an earlier view.

    ``baseline``: metres driven between the two views (the earliest kept view at least this far back
    is used; none closer than ``min_baseline``: no measurement). ``scales``: image downsampling per
    pyramid level, coarse to fine. ``rotation_prior`` (rad) and ``height_prior`` (relative): the
    standard deviations of the odometry's relative rotation and scale the fit may correct.
    """

    def __init__(
        self,
        grid: BevGrid,
        baseline: float = 0.6,
        min_baseline: float = 0.4,
        scales: tuple[int, ...] = (4, 2),
        iterations: int = 8,
        sample_step: int = 4,
        rotation_prior: float = 0.003,
        height_prior: float = 0.005,
        roll_axis: RollAxis = "optical",
        history: int = 64,
    ) -> None:
        if min_baseline <= 0.0 or baseline < min_baseline:
            raise ValueError(f"need 0 < min_baseline ({min_baseline}) <= baseline ({baseline})")
        self.grid = grid
        self.baseline = baseline
        self.min_baseline = min_baseline
        self.scales = tuple(sorted(set(scales), reverse=True))
        self.iterations = iterations
        self.rotation_prior = rotation_prior
        self.height_prior = height_prior
        self.roll_axis = roll_axis
        v, u = np.mgrid[sample_step // 2 : grid.height : sample_step, sample_step // 2 : grid.width : sample_step]
        self._bev_samples = np.stack([u.ravel(), v.ravel(), np.ones(u.size)]).astype(np.float64)
        self._views: deque[_View] = deque(maxlen=history)
        self._travelled = 0.0
        self._last_position: np.ndarray | None = None

    def reset(self) -> None:
        """Forget the views of the previous sequence."""
        self._views.clear()
        self._travelled = 0.0
        self._last_position = None

    def _prepare(self, image: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        gray = gray.astype(np.float32)
        height, width = gray.shape
        levels = []
        for scale in self.scales:
            small = (
                gray
                if scale == 1
                else cv2.resize(gray, (width // scale, height // scale), interpolation=cv2.INTER_AREA)
            )
            small = cv2.GaussianBlur(small, (0, 0), 1.0)
            gu = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
            gv = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
            levels.append((small, gu, gv))
        return levels

    def measure(
        self,
        image: np.ndarray,
        odometry: np.ndarray,
        calibration: Calibration,
        psi: float,
        theta: float,
    ) -> PlaneMeasurement | None:
        """Add the view and measure the plane from it and an earlier one; ``(psi, theta)`` is the start.

        None when no earlier view is between ``min_baseline`` and twice ``baseline`` back, or too little
        of the ground is seen in both.
        """
        odometry = np.asarray(odometry, dtype=np.float64)
        if odometry.shape != (4, 4) or not np.all(np.isfinite(odometry)):
            return None
        position = odometry[:3, 3]
        if self._last_position is not None:
            self._travelled += float(np.linalg.norm(position - self._last_position))
        self._last_position = position.copy()
        view = _View(self._prepare(image), odometry @ calibration.camera_to_base_matrix, self._travelled)
        earlier = None
        for candidate in reversed(self._views):
            if view.travelled - candidate.travelled >= self.baseline:
                earlier = candidate
                break
        if earlier is None and self._views and view.travelled - self._views[0].travelled >= self.min_baseline:
            earlier = self._views[0]
        self._views.append(view)
        while len(self._views) > 1 and view.travelled - self._views[1].travelled >= self.baseline:
            self._views.popleft()  # the second oldest is already far enough back for every later view
        if earlier is None or view.travelled - earlier.travelled > 2.0 * self.baseline:
            return None  # nothing far enough back, or only views of ground long passed (frames were skipped)
        return self._fit(view, earlier, calibration, psi, theta)

    def _fit(
        self, current: _View, earlier: _View, calibration: Calibration, psi: float, theta: float
    ) -> PlaneMeasurement | None:
        relative = np.linalg.inv(earlier.camera) @ current.camera  # camera t in camera s
        r_st, t_st = relative[:3, :3], relative[:3, 3]
        intr = calibration.intrinsics
        h_bev = bev_to_image_homography(calibration, self.grid, psi, theta, self.roll_axis)
        q = h_bev @ self._bev_samples
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = q[0] / q[2], q[1] / q[2]
        inside = (q[2] > 0) & (u >= 2) & (u <= intr.width - 3) & (v >= 2) & (v <= intr.height - 3)
        if inside.sum() < 200:
            return None
        u, v = u[inside], v[inside]
        params = np.array([psi, theta, 0.0, 0.0, 0.0, 0.0])
        prior_std = np.array([np.inf, np.inf, self.height_prior, *(3 * [self.rotation_prior])])
        precision = np.where(np.isfinite(prior_std), 1.0 / np.square(prior_std), 0.0)
        covariance = None
        samples = 0
        sigma = math.nan
        for level, scale in enumerate(self.scales):
            image_t, _, _ = current.levels[level]
            image_s, grad_u, grad_v = earlier.levels[level]
            height, width = image_s.shape
            k = intr.matrix.copy()
            k[:2] /= scale
            k[0, 2] = (intr.cx + 0.5) / scale - 0.5
            k[1, 2] = (intr.cy + 0.5) / scale - 0.5
            k_inv = np.linalg.inv(k)
            ut = ((u + 0.5) / scale - 0.5).astype(np.float32)
            vt = ((v + 0.5) / scale - 0.5).astype(np.float32)
            rays = k_inv @ np.stack([ut, vt, np.ones_like(ut)]).astype(np.float64)
            values_t = cv2.remap(image_t, ut[None], vt[None], cv2.INTER_LINEAR)[0].astype(np.float64)

            def warp(p: np.ndarray, rays: np.ndarray = rays, k: np.ndarray = k) -> tuple[np.ndarray, np.ndarray]:
                rotation = compensated_camera_to_base(calibration, p[0], p[1], self.roll_axis)
                normal = rotation[2]  # the base's up axis in camera coordinates
                h = calibration.height * math.exp(p[2])
                plane = _rotation_vector(p[3:6]) @ r_st - np.outer(t_st, normal) / h
                x = k @ (plane @ rays)
                with np.errstate(divide="ignore", invalid="ignore"):
                    return x[0] / x[2], x[1] / x[2]

            for _ in range(self.iterations):
                us, vs = warp(params)
                valid = np.isfinite(us) & (us >= 1) & (us <= width - 2) & (vs >= 1) & (vs <= height - 2)
                if valid.sum() < 100:
                    return None
                mu, mv = us[valid].astype(np.float32)[None], vs[valid].astype(np.float32)[None]
                values_s = cv2.remap(image_s, mu, mv, cv2.INTER_LINEAR)[0].astype(np.float64)
                gu = cv2.remap(grad_u, mu, mv, cv2.INTER_LINEAR)[0].astype(np.float64)
                gv = cv2.remap(grad_v, mu, mv, cv2.INTER_LINEAR)[0].astype(np.float64)
                a = values_t[valid]
                a = a - a.mean()
                b = values_s - values_s.mean()
                gain = float(a.std() / max(b.std(), 1e-6))
                residual = gain * b - a
                derivatives = np.empty((valid.sum(), NUM_PARAMS))
                for j in range(NUM_PARAMS):
                    step = np.zeros(NUM_PARAMS)
                    step[j] = _STEP
                    up, vp = warp(params + step)
                    derivatives[:, j] = gain * (gu * (up[valid] - us[valid]) + gv * (vp[valid] - vs[valid])) / _STEP
                sigma = 1.4826 * float(np.median(np.abs(residual))) + 1e-6
                huber = 1.345 * sigma
                weights = np.minimum(1.0, huber / np.maximum(np.abs(residual), 1e-12))
                jw = derivatives * weights[:, None]
                normal_matrix = jw.T @ derivatives / sigma**2 + np.diag(precision)
                gradient = jw.T @ residual / sigma**2 + precision * params  # no prior on psi, theta
                try:
                    delta = -np.linalg.solve(normal_matrix, gradient)
                except np.linalg.LinAlgError:
                    return None
                params = params + delta
                samples = int(valid.sum())
                covariance = normal_matrix
                if np.abs(delta[:2]).max() < 2e-5:
                    break
        if covariance is None or not np.all(np.isfinite(params)):
            return None
        try:
            theta_var = float(np.linalg.inv(covariance)[1, 1])
        except np.linalg.LinAlgError:
            return None
        return PlaneMeasurement(
            psi=float(params[0]),
            theta=float(params[1]),
            theta_std=math.sqrt(max(theta_var, 0.0)),
            baseline=current.travelled - earlier.travelled,
            samples=samples,
            residual=sigma,
        )


class GradeFilter:
    """A Kalman filter over distance for one angle that changes smoothly along the drive: angle and its rate.

    The rate decays over ``rate_memory`` metres, so a stretch without measurements is not extrapolated far.

    ``rate_noise`` (rad per metre per sqrt(metre)): how fast the rate may change, e.g. at the foot of a
    hill; ``measurement_noise`` (rad): one measurement's standard deviation. An innovation beyond
    ``gate`` standard deviations is down-weighted (Huber), so a bad fit does not throw the estimate.
    """

    def __init__(
        self, rate_noise: float = 0.01, measurement_noise: float = 0.003, gate: float = 3.0, rate_memory: float = 3.0
    ) -> None:
        self.rate_noise = rate_noise
        self.rate_memory = rate_memory
        self.measurement_noise = measurement_noise
        self.gate = gate
        self.state: np.ndarray | None = None
        self.covariance = np.zeros((2, 2))

    def reset(self) -> None:
        """Forget the estimate."""
        self.state = None

    @property
    def value(self) -> float | None:
        """The current angle estimate (None before the first measurement)."""
        return None if self.state is None else float(self.state[0])

    def predict(self, distance: float) -> None:
        """Move ``distance`` metres on: the angle follows its rate, the rate's uncertainty grows."""
        if self.state is None or distance <= 0.0:
            return
        decay = math.exp(-distance / self.rate_memory)  # a grade's change does not go on for ever
        f = np.array([[1.0, distance], [0.0, decay]])
        self.state = f @ self.state
        q = self.rate_noise**2 * distance
        process = q * np.array([[distance**2 / 3.0, distance / 2.0], [distance / 2.0, 1.0]])
        self.covariance = f @ self.covariance @ f.T + process

    def update(self, measurement: float) -> None:
        """Fold in one measurement of the angle."""
        r = self.measurement_noise**2
        if self.state is None:
            self.state = np.array([measurement, 0.0])
            self.covariance = np.diag([r, (5.0 * self.rate_noise) ** 2])
            return
        innovation = measurement - self.state[0]
        s = self.covariance[0, 0] + r
        if innovation * innovation > self.gate**2 * s:
            r *= innovation * innovation / (self.gate**2 * s)  # Huber: beyond the gate, the weight falls as 1/|e|
            s = self.covariance[0, 0] + r
        gain = self.covariance[:, 0] / s
        self.state = self.state + gain * innovation
        self.covariance = self.covariance - np.outer(gain, self.covariance[0])
