"""The wheel odometry's scale error, measured from the camera (``odometry_scale=bev_motion``; extension).

Wheel odometry counts distance with a steady relative error (tyre radius, load, slip): the
campus robot's over-counts by about 1 %. Loop closures cannot see it: a lap drawn 1 % too large
still closes on itself, so eq. 11 keeps the error and a route 130 m across ends up to a metre off
everywhere (most of Table 2's remaining ATE without this stage; docs/method.md). The camera can: the ground in
a bird's-eye view is metric, so two views of it one metre apart are related by the robot's true
motion. :class:`BevMotionScale` resamples the near ground of every keyframe with the fixed
homography of plain IPM (eq. 3-4 without compensation, so MC-IPM's per-frame attitude noise stays
out), keeps its texture between the grain and 0.6 m (the log image less its local mean, so that
light moving with the robot, the lens's vignetting or a headlight, does not hold the fit at zero
motion), warps the view from about ``baseline`` metres back onto it with the odometry's motion,
and fits the small remaining shift by Gauss-Newton on the difference (Lucas-Kanade, Huber
weights). Besides the shift and a turn, the fit takes a change of the view's pitch and roll (a
ground point moves by ``(x, y) (a x + b y)`` under them), which would otherwise pass for a change
of scale. The shift along the motion, over the distance, is one measurement of the odometry's
relative error; their running median is the estimate, and the back-end multiplies every
odometry step that follows by ``1 / (1 + median)`` (:class:`sgf_pipeline.types.OdometryScale`).

The fit's turn, over the distance, is one measurement of the odometry's heading bias per metre
(``heading``): the ground in the two views turned by the robot's true turn, the odometry by that
plus its bias. Their running median is the estimate, with a standard error counted over the
independent stretches of ``baseline`` metres the measurements span (views overlap along the
drive); the back-end takes it as the heading bias's prior before any loop has measured it.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import cv2
import numpy as np
from pydantic import Field

from sgf_pipeline import RunContext, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.geometry import xy_yaw
from sgf_pipeline.types import BevGrid, CameraImage, Frame, OdometryScale
from sgf_plugins.shared.bev_homography import bev_to_image_homography, visible_mask
from sgf_plugins.shared.bev_region import Region, choose_region
from sgf_plugins.shared.se2 import se2

#: Parameters of the fit: shift (x, y) in metres, turn (rad), pitch-like a and roll-like b (1/m).
_PARAMS = 5


class MotionError(NamedTuple):
    """The odometry's errors over one pair of views ``length`` m apart: relative distance, heading per metre (rad/m)."""

    scale: float
    yaw_rate: float
    length: float


class BevMotionParams(StageParams):
    """The near-ground view, the pairing of views and the robust estimate."""

    resolution: float = Field(0.02, gt=0.0, description="m per pixel of the near-ground view")
    x_min: float = Field(0.5, ge=0.0, description="m ahead: nearest ground resampled")
    x_max: float = Field(3.0, gt=0.0, description="m ahead: farthest (a view's attitude error grows with the square)")
    y_half_width: float = Field(1.25, gt=0.0, description="m to each side")
    region: Region = Field(
        "auto",
        description="auto: that near ground when the camera sees at least half of it, else ground of its size "
        "nearest in view (logged); fixed: that ground, an error when the camera sees none of it",
    )
    baseline: float = Field(1.0, gt=0.0, description="m driven between the two views of a measurement")
    max_baseline: float = Field(1.6, gt=0.0, description="no measurement when the nearest view far enough is older")
    max_turn_deg: float = Field(15.0, gt=0.0, description="no measurement across a sharper turn")
    highpass: float = Field(0.6, gt=0.0, description="m: texture coarser than this is taken off each view")
    flat_field: float = Field(
        20.0, ge=0.0, description="keyframes: memory of the running mean view, light fixed to the robot (0 = none)"
    )
    blur: float = Field(1.0, gt=0.0, description="pixels: Gaussian blur of each view (grain finer than this)")
    iterations: int = Field(5, ge=1, description="Gauss-Newton iterations of one fit")
    huber: float = Field(0.5, gt=0.0, description="Huber width, in standard deviations of the view's intensity")
    min_pixels: int = Field(2000, ge=10, description="ground pixels both views must share")
    max_error: float = Field(0.1, gt=0.0, description="a measured relative error beyond this is refused (a bad fit)")
    min_pairs: int = Field(20, ge=1, description="measurements before the estimate is applied")
    heading: bool = Field(
        True, description="measure the odometry's heading bias per metre too (the back-end's prior for it)"
    )


class BevMotionScale(Stage):
    """The odometry's scale factor from the metric ground motion between keyframes (see the module docstring)."""

    kind = "odometry_scale"
    name = "bev_motion"
    output = "odometry_scale"
    Params = BevMotionParams

    def __init__(self, params: BevMotionParams) -> None:
        super().__init__(params)
        self.p = params
        if params.x_max <= params.x_min:
            raise ValueError(f"odometry_scale.x_max ({params.x_max}) must be larger than x_min ({params.x_min})")
        if params.max_baseline <= params.baseline:
            raise ValueError("odometry_scale.max_baseline must be larger than baseline")
        self.configured = BevGrid(
            params.resolution, params.x_min, params.x_max, -params.y_half_width, params.y_half_width
        )
        self._set_grid(self.configured)
        self._calibration: Calibration | None = None
        self._homography = np.eye(3)
        self._valid = np.zeros(0, dtype=bool)
        self._flat: np.ndarray | None = None
        self._weights: dict[float, np.ndarray] = {}
        self._inside = np.zeros(0, dtype=np.float32)

    def _set_grid(self, grid: BevGrid) -> None:
        """View the ground of ``grid``: its points and the fit's derivatives there."""
        self.grid = grid
        v, u = np.mgrid[0 : grid.height, 0 : grid.width].astype(np.float64)
        self._x, self._y = grid.pixel_to_ground(u, v)
        one, zero = np.ones_like(self._x), np.zeros_like(self._x)
        # d(shift)/d(params) per pixel: shift, turn about the robot, then the attitude terms (x, y)(a x + b y)
        self._bx = np.stack([one, zero, -self._y, self._x * self._x, self._x * self._y])
        self._by = np.stack([zero, one, self._x, self._y * self._x, self._y * self._y])

    def begin(self, context: RunContext) -> None:
        """Forget the previous sequence."""
        self._calibration = None
        self._views: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # travelled, planar odometry, view
        self._travelled = 0.0
        self._last: np.ndarray | None = None
        self.errors: list[float] = []
        self.yaw_rates: list[float] = []
        self.lengths: list[float] = []  # m driven between the two views of each measurement
        self._walks: tuple[int, float, float] = (0, math.inf, math.inf)  # measurements behind, sigma_xy, sigma_yaw
        self._measured_from: float | None = None  # travel at the first measurement
        self.refused = 0
        self._flat = None

    def process(self, frame: Frame, image: CameraImage) -> OdometryScale:
        """Measure the odometry's error against the view ``baseline`` back; the estimate so far."""
        odometry = se2(*xy_yaw(np.asarray(frame.odometry, dtype=np.float64)))
        if self._last is not None:
            self._travelled += float(np.hypot(*(odometry[:2, 2] - self._last[:2, 2])))
        self._last = odometry
        view = self._view(frame.calibration, image.pixels)
        earlier = None
        while self._views and self._travelled - self._views[0][0] > self.p.max_baseline:
            self._views.popleft()
        for travelled, pose, old in reversed(self._views):
            if self._travelled - travelled >= self.p.baseline:
                earlier = (pose, old)
                break
        self._views.append((self._travelled, odometry, view))
        if earlier is not None:
            error = self.measure(view, earlier[1], np.linalg.inv(earlier[0]) @ odometry)
            if error is None:
                self.refused += 1
            else:
                self.errors.append(error.scale)
                self.yaw_rates.append(error.yaw_rate)
                self.lengths.append(error.length)
                if self._measured_from is None:
                    self._measured_from = self._travelled - self.p.baseline
        return self.estimate()

    def estimate(self) -> OdometryScale:
        """The measured errors so far: a factor on the odometry, its heading bias per metre, its random walks.

        All are neutral (factor 1, no bias, infinite sigmas) before ``min_pairs`` measurements.
        """
        n = len(self.errors)
        if n < self.p.min_pairs or self._measured_from is None:
            return OdometryScale(1.0, math.inf, n)
        # pairs of views overlap along the drive: count the independent stretches one baseline long
        independent = min(n, max(1.0, (self._travelled - self._measured_from) / self.p.baseline))
        median, sigma = _median(np.asarray(self.errors), independent)
        factor, factor_sigma = 1.0 / (1.0 + median), sigma / (1.0 + median) ** 2
        sigma_xy, sigma_yaw = self._random_walks(independent)
        if not self.p.heading:
            return OdometryScale(factor, factor_sigma, n, sigma_xy=sigma_xy, sigma_yaw=sigma_yaw)
        bias, bias_sigma = _median(np.asarray(self.yaw_rates), independent)
        return OdometryScale(factor, factor_sigma, n, bias, bias_sigma, sigma_xy, sigma_yaw)

    def _random_walks(self, independent: float) -> tuple[float, float]:
        """The odometry's distance (m/sqrt(m)) and heading (rad/sqrt(m)) random walks, upper bounds.

        A measurement over ``L`` m has an error of ``sigma sqrt(L)``, so its error per metre times
        ``sqrt(L)`` spreads by ``sigma`` (with the camera's own noise: an upper bound); the spread
        from the median absolute deviation, raised by twice its standard error. Recomputed each
        ``min_pairs`` measurements: the walks change slowly.
        """
        n = len(self.errors)
        if n - self._walks[0] >= self.p.min_pairs:
            root = np.sqrt(np.asarray(self.lengths))
            upper = 1.0 + 2.0 * _MAD_SPREAD_ERROR / math.sqrt(independent)
            walks = (_spread(np.asarray(self.errors) * root), _spread(np.asarray(self.yaw_rates) * root))
            self._walks = (n, walks[0] * upper, walks[1] * upper)
        return self._walks[1], self._walks[2]

    def measure(self, view: np.ndarray, earlier: np.ndarray, motion: np.ndarray) -> MotionError | None:
        """The odometry's errors over ``motion`` (this view's pose in the earlier one's); None if unfit."""
        length = float(np.hypot(motion[0, 2], motion[1, 2]))
        if length <= 0.0 or abs(math.atan2(motion[1, 0], motion[0, 0])) > math.radians(self.p.max_turn_deg):
            return None
        xi = np.zeros(_PARAMS)
        for _ in range(self.p.iterations):
            dx, dy = np.tensordot(xi, self._bx, 1), np.tensordot(xi, self._by, 1)
            warped = self._warp(earlier, motion, self._x + dx, self._y + dy)
            gv, gu = np.gradient(warped)
            use = np.isfinite(view) & np.isfinite(warped) & np.isfinite(gv) & np.isfinite(gu)
            if int(use.sum()) < self.p.min_pixels:
                return None
            a, b = view[use], warped[use]
            sa, sb = float(a.std()) + 1e-6, float(b.std()) + 1e-6
            residual = (a - a.mean()) / sa - (b - b.mean()) / sb
            gx, gy = -gv[use] / (self.grid.resolution * sb), -gu[use] / (self.grid.resolution * sb)
            jac = gx[:, None] * self._bx[:, use].T + gy[:, None] * self._by[:, use].T
            weight = 1.0 / np.maximum(1.0, np.abs(residual) / self.p.huber)
            hessian = jac.T @ (jac * weight[:, None])
            if np.linalg.cond(hessian) > 1e10:
                return None
            xi += np.linalg.solve(hessian, jac.T @ (weight * residual))
        # The earlier view sampled at motion (p + shift) matches: the true motion is the odometry's less R shift,
        # and the true turn the odometry's plus the fit's.
        error = -float(xi[:2] @ (motion[:2, :2].T @ motion[:2, 2])) / length**2
        return MotionError(error, -float(xi[2]) / length, length) if abs(error) <= self.p.max_error else None

    def _view(self, calibration: Calibration, pixels: np.ndarray) -> np.ndarray:
        """The near ground by plain IPM, its fine texture only (log grey, band-passed), NaN outside the view."""
        if calibration is not self._calibration:
            grid = choose_region(calibration, self.configured, self.p.region, "odometry_scale")
            if grid != self.grid:
                self._set_grid(grid)
                self._views.clear()  # views of another region
            self._homography = bev_to_image_homography(calibration, self.grid)
            intr = calibration.intrinsics
            self._valid = visible_mask(self._homography, self.grid, intr.width, intr.height)
            # the normalising weights of both smoothings depend on the view's outline only: once per calibration
            self._inside = self._valid.astype(np.float32)
            self._weights = {
                sigma: np.maximum(cv2.GaussianBlur(self._inside, (0, 0), sigma), 1e-3)
                for sigma in (self.p.blur, self.p.highpass / self.grid.resolution)
            }
            self._calibration = calibration
        grey = pixels if pixels.ndim == 2 else cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY)
        view = cv2.warpPerspective(
            grey.astype(np.float32),
            self._homography,
            (self.grid.width, self.grid.height),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        )
        # Light that moves with the robot (the lens's vignetting, a headlight) would hold the fit at zero motion:
        # the log image less its local mean keeps the ground's texture; a slight blur takes off the grain too
        # fine for two views from different distances to agree on. Both by convolution normalised inside the view.
        log = np.log1p(view)
        if self.p.flat_field > 0:
            # Light fixed to the robot stays where it is in every view while the ground's texture moves on:
            # the running mean of the views is that light (in log, a sum), taken off before the band-pass.
            if self._flat is None:
                self._flat = log.copy()
            else:
                self._flat += (log - self._flat) / self.p.flat_field
            log = log - self._flat
        view = self._smooth(log, self.p.blur) - self._smooth(log, self.p.highpass / self.grid.resolution)
        view[~self._valid] = np.nan
        return view

    def _smooth(self, image: np.ndarray, sigma: float) -> np.ndarray:
        """Gaussian smoothing (``sigma`` pixels) of the pixels inside the camera's view."""
        return cv2.GaussianBlur(image * self._inside, (0, 0), sigma) / self._weights[sigma]

    def _warp(self, earlier: np.ndarray, motion: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The earlier view sampled at ground points ``(x, y)`` of this frame (NaN where it did not see them)."""
        qx = motion[0, 0] * x + motion[0, 1] * y + motion[0, 2]
        qy = motion[1, 0] * x + motion[1, 1] * y + motion[1, 2]
        u, v = self.grid.ground_to_pixel(qx, qy)
        return cv2.remap(
            earlier, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR, borderValue=float("nan")
        )

    def finalize(self, context: RunContext) -> None:
        """Write the estimate into ``metrics.json`` (``odometry_scale``)."""
        final = self.estimate()
        known = math.isfinite(final.yaw_bias_sigma)
        walks = math.isfinite(final.sigma_xy)
        context.metrics["odometry_scale"] = {
            "factor": final.factor,
            "sigma": final.sigma if math.isfinite(final.sigma) else None,
            "pairs": final.pairs,
            "refused": self.refused,
            "yaw_bias_deg_per_m": math.degrees(final.yaw_bias) if known else None,
            "yaw_bias_sigma_deg_per_m": math.degrees(final.yaw_bias_sigma) if known else None,
            "sigma_xy": final.sigma_xy if walks else None,
            "sigma_yaw_deg": math.degrees(final.sigma_yaw) if walks else None,
        }
        if self.grid != self.configured:
            g = self.grid
            context.metrics["odometry_scale"]["region"] = {
                "x_min": g.x_min,
                "x_max": g.x_max,
                "y_min": g.y_min,
                "y_max": g.y_max,
            }


#: The standard error of a spread from the median absolute deviation, per spread and sqrt(n) (normal errors).
_MAD_SPREAD_ERROR = 1.1664


def _spread(values: np.ndarray) -> float:
    """The standard deviation of ``values`` from their median absolute deviation."""
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def _median(values: np.ndarray, independent: float) -> tuple[float, float]:
    """The median of ``values`` and its standard error over ``independent`` measurements.

    The standard error is 1.2533 sigma / sqrt(n), sigma from the median absolute deviation.
    """
    return float(np.median(values)), 1.2533 * _spread(values) / math.sqrt(independent)


class NoOdometryScale(Stage):
    """The odometry's distances as they are (the paper)."""

    kind = "odometry_scale"
    name = "none"
    output = "odometry_scale"

    def process(self, frame: Frame) -> OdometryScale:
        """Always the factor 1."""
        return OdometryScale(1.0, 0.0, 0)


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the odometry scale variants."""
    registry.add(BevMotionScale)
    registry.add(NoOdometryScale)
