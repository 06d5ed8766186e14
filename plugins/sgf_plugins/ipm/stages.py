"""The IPM stages: plain inverse perspective mapping and motion-compensated IPM (paper Sec. III-A)."""

from __future__ import annotations

import logging
import math
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from sgf_pipeline import DataError, RunContext, Stage, StageParams
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.geometry import rpy_from_rotation
from sgf_pipeline.imu import shrink_noise, steadied
from sgf_pipeline.types import Bev, BevGrid, CameraImage, Frame
from sgf_plugins.ipm.ground_plane import GradeFilter, GroundPlaneTracker
from sgf_plugins.ipm.hindsight import AttitudeWindow, GroundAhead, ground_ahead, path_profile
from sgf_plugins.ipm.reference import PoseQueue, ReferenceAttitude, ReferenceCenter, ReferenceFit
from sgf_plugins.shared.bev_homography import RollAxis, bev_to_image_homography, visible_mask
from sgf_plugins.shared.bev_region import Region, choose_region

_INTERPOLATION = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}
_LOGGED_DROPOUTS = 5
log = logging.getLogger("sgf_pipeline.ipm")


class IpmParams(StageParams):
    """The metric BEV grid (the virtual camera of eq. 3-4) and how the image is resampled into it."""

    resolution: float = Field(0.02, gt=0.0, description="metres per BEV pixel")
    x_min: float = Field(0.5, description="near edge of the BEV, metres ahead of the base origin")
    x_max: float = Field(5.62, description="far edge of the BEV, metres ahead of the base origin")
    y_min: float = Field(-2.56, description="right edge of the BEV (metres, y is left)")
    y_max: float = Field(2.56, description="left edge of the BEV (metres, y is left)")
    interpolation: Literal["linear", "nearest", "cubic"] = Field(
        "linear", description="image resampling (cubic: cv2 backend only)"
    )
    backend: Literal["cv2", "kornia"] = Field(
        "cv2", description="cv2: one warpPerspective per frame; kornia: torch warp (batched, differentiable, GPU)"
    )
    device: str = Field("auto", description="kornia backend device: auto (cuda when available), cpu, cuda, cuda:1, ...")
    region: Region = Field(
        "auto",
        description="auto: the region above when the camera sees at least half of it, else one of its size on the "
        "nearest ground in view (logged); fixed: the region above, an error when the camera sees none of it",
    )

    @model_validator(mode="after")
    def _check_grid(self) -> IpmParams:
        for low, high, axis in ((self.x_min, self.x_max, "x"), (self.y_min, self.y_max, "y")):
            if high <= low:
                raise ValueError(f"{axis}_max ({high}) must be greater than {axis}_min ({low})")
            cells = (high - low) / self.resolution
            if abs(cells - round(cells)) > 1e-6 * max(1.0, cells):
                raise ValueError(
                    f"the {axis} extent {high - low:g} m is not a whole number of {self.resolution:g} m pixels "
                    f"({cells:.4f}); adjust {axis}_min/{axis}_max or resolution"
                )
        if self.backend == "kornia" and self.interpolation == "cubic":
            raise ValueError("interpolation=cubic is available with backend=cv2 only; use linear or nearest")
        return self

    @property
    def grid(self) -> BevGrid:
        """The BEV grid these parameters describe."""
        return BevGrid(self.resolution, self.x_min, self.x_max, self.y_min, self.y_max)


class InversePerspectiveMapping(Stage):
    """Plain IPM: the calibrated camera's view of a flat ground, resampled onto a metric BEV grid.

    The BEV's pixel <-> ground mapping is exactly its ``BevGrid`` (eq. 3-4 and eq. 9): ground
    coordinates in the robot's base frame on the ground plane. ``Bev.instance_ids`` is the frame's
    ground-truth instance mask warped with the same homography (nearest neighbour), so BEV masks
    align pixel for pixel. One ``cv2.warpPerspective`` per frame, or kornia with ``backend=kornia``.
    """

    kind = "ipm"
    name = "plain"
    output = "bev"
    Params = IpmParams

    def __init__(self, params: IpmParams) -> None:
        super().__init__(params)
        self.params: IpmParams = params
        self.grid = params.grid
        self._checked: Calibration | None = None
        self._device: str | None = None

    def begin(self, context: RunContext) -> None:
        """Forget the calibration checked, and the region chosen, on the previous sequence."""
        self._checked = None
        self.set_grid(self.params.grid)

    def set_grid(self, grid: BevGrid) -> None:
        """Resample into ``grid`` (the configured region, or the one :func:`choose_region` moved)."""
        self.grid = grid

    def finalize(self, context: RunContext) -> None:
        """The region resampled into ``metrics.json`` (``ipm.region``) when it is not the configured one."""
        if self.grid != self.params.grid:
            g = self.grid
            context.metrics.setdefault("ipm", {})["region"] = {
                "x_min": g.x_min,
                "x_max": g.x_max,
                "y_min": g.y_min,
                "y_max": g.y_max,
                "configured": [self.params.x_min, self.params.x_max, self.params.y_min, self.params.y_max],
            }

    def compensation(self, frame: Frame, image: np.ndarray | None = None) -> tuple[float, float]:
        """``(psi, theta)`` of eq. 1-2 for this frame (``image``: the pixels the IPM warps): none for plain IPM."""
        return 0.0, 0.0

    def homography(self, calibration: Calibration, psi: float = 0.0, theta: float = 0.0) -> np.ndarray:
        """BEV index coordinates -> image pixels for this stage's grid (eq. 1-4)."""
        return bev_to_image_homography(calibration, self.grid, psi, theta)

    def process(self, frame: Frame, image: CameraImage) -> Bev:
        """The metric BEV of the frame's (enhanced) image."""
        pixels = image.pixels
        calibration = frame.calibration
        self._check(calibration, pixels)
        psi, theta = self.compensation(frame, pixels)
        h = self.homography(calibration, psi, theta)
        bev, valid = self.warp(pixels, h)
        ids = frame.truth_ids()
        instance_ids = None if ids is None else self.warp_ids(ids, h, valid, pixels.shape[:2])
        return Bev(
            bev, valid, self.grid, frame.index, frame.timestamp, instance_ids, roll=-psi, pitch=theta, homography=h
        )

    def warp(self, pixels: np.ndarray, homography: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Resample an image into the BEV; pixels outside the visible ground are zero."""
        if self.params.backend == "kornia":
            from sgf_plugins.ipm.kornia_backend import resolve_device, warp_image

            if self._device is None:
                self._device = resolve_device(self.params.device)
            return warp_image(pixels, homography, self.grid, self.params.interpolation, self._device)
        height, width = pixels.shape[:2]
        valid = visible_mask(homography, self.grid, width, height)
        bev = cv2.warpPerspective(
            pixels,
            homography,
            (self.grid.width, self.grid.height),
            flags=_INTERPOLATION[self.params.interpolation] | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return cv2.bitwise_and(bev, bev, mask=valid.view(np.uint8)), valid  # zero outside the view

    def warp_ids(
        self, ids: np.ndarray, homography: np.ndarray, valid: np.ndarray, image_shape: tuple[int, ...]
    ) -> np.ndarray:
        """Warp per-pixel instance ids with the same mapping, nearest neighbour (0 outside the view)."""
        if ids.shape[:2] != tuple(image_shape[:2]):
            raise DataError(f"instance id mask {ids.shape[:2]} does not match the image {tuple(image_shape[:2])}")
        source = ids.astype(np.int32) if ids.dtype not in (np.uint16, np.int32) else ids
        out = cv2.warpPerspective(
            source,
            homography,
            (self.grid.width, self.grid.height),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return cv2.bitwise_and(out, out, mask=valid.view(np.uint8))

    def _check(self, calibration: Calibration, pixels: np.ndarray) -> None:
        intr = calibration.intrinsics
        if pixels.ndim not in (2, 3) or pixels.shape[:2] != (intr.height, intr.width):
            raise DataError(
                f"image of shape {pixels.shape} does not match the calibration's {intr.width}x{intr.height} "
                "(the intrinsics must belong to the image the IPM receives)"
            )
        if calibration is self._checked:
            return
        if calibration.height <= 0.0:
            raise DataError(f"the camera is {calibration.height:.3f} m above the ground; IPM needs it above (> 0)")
        self.set_grid(choose_region(calibration, self.params.grid, self.params.region, "ipm"))
        self._checked = calibration


def _odometry_attitude(frame: Frame) -> tuple[float, float]:
    """Roll and pitch (rad) of the frame's odometry pose; NaN when the pose is not a finite 4x4 matrix."""
    odometry = np.asarray(frame.odometry, dtype=np.float64)
    if odometry.shape != (4, 4) or not np.all(np.isfinite(odometry)):
        return math.nan, math.nan
    roll, pitch, _ = rpy_from_rotation(odometry[:3, :3])
    return roll, pitch


class MotionCompensatedIpmParams(IpmParams):
    """MC-IPM: the grid of plain IPM, plus the pose queue and the attitude it compensates."""

    queue_size: int = Field(50, ge=1, description="N: poses in the queue whose robust average is the reference")
    pitch_threshold: float = Field(
        0.025, gt=0.0, description="d_theta (rad): queued poses whose pitch is further from the centre are left out"
    )
    reference_center: ReferenceCenter = Field(
        "median", description="centre the pitch threshold is measured from: median (robust) or mean (literal)"
    )
    roll_threshold: float | None = Field(
        None, gt=0.0, description="also leave out poses whose roll is this far (rad) from the median; null = paper"
    )
    settle: int | None = Field(
        None,
        ge=1,
        description="extension: after this many poses settled at a new pitch (a slope), drop the older ones; "
        "null = paper (a slope takes over after N/2 + 1 poses)",
    )
    reference_fit: ReferenceFit = Field(
        "mean",
        description="mean: the inliers' average (paper); line: extension, a line of pitch over distance travelled, "
        "which follows a hill's changing grade and extrapolates it lookahead metres ahead",
    )
    lookahead: float = Field(
        0.0, ge=0.0, description="extension (reference_fit=line): metres ahead whose ground pitch the BEV plane gets"
    )
    attitude_noise: float = Field(
        0.0,
        ge=0.0,
        description="extension: noise scale sigma (rad, about twice the IMU's roll/pitch noise); a deviation d "
        "from the reference is compensated by d^3 / (d^2 + sigma^2): noise mostly left alone, bumps wholly undone; "
        "0 = paper",
    )
    attitude: Literal["auto", "imu", "odometry"] = Field(
        "auto", description="roll/pitch source: imu, odometry pose, or auto (IMU when the frame has it)"
    )
    roll_axis: RollAxis = Field(
        "optical",
        description="optical: eq. 1 as printed (image rotation about the principal point); "
        "base: roll about the robot's forward axis (exact for a tilted camera)",
    )
    compensate_roll: bool = Field(True, description="apply eq. 1 (roll); false for an ablation")
    compensate_pitch: bool = Field(True, description="apply theta in eq. 2 (pitch); false for an ablation")

    @model_validator(mode="after")
    def _check_reference(self) -> MotionCompensatedIpmParams:
        if self.lookahead > 0.0 and self.reference_fit != "line":
            raise ValueError(f"lookahead ({self.lookahead} m) needs reference_fit=line (a mean has no slope to follow)")
        return self


#: The extensions ``ipm=mc_ahead`` (conf/ipm/mc_ahead.yaml) turns on over the paper's MC-IPM (``ipm=mc``).
AHEAD_MC: dict[str, Any] = {"reference_fit": "line", "lookahead": 2.0, "attitude_noise": 0.005}


class MotionCompensatedIPM(InversePerspectiveMapping):
    """MC-IPM: IPM compensated by the roll and pitch of the robot relative to a reference attitude (eq. 1-4).

    Per frame: read the attitude (IMU roll/pitch, or the odometry pose's), push it into the pose
    queue, take the queue's robust average as the reference (:class:`PoseQueue`: median-centred,
    poses with a pitch further than ``pitch_threshold`` from it left out), and compensate the
    difference: ``theta = pitch - pitch_ref`` in eq. 2 (positive nose down, like ``alpha``) and
    ``psi = -(roll - roll_ref)`` in eq. 1 (eq. 1's rotation sense in image coordinates). A speed
    bump is compensated by its own pitch; a slope becomes the reference after half a queue.
    ``Bev.roll`` and ``Bev.pitch`` carry the compensated relative roll and pitch; the BEV shows the
    ground plane under the robot as seen at the reference attitude, so ground points lifted from
    it (eq. 9) belong with the planar part (x, y, yaw) of the robot's pose.

    A frame whose attitude is not finite (an IMU dropout) keeps the run going: with
    ``attitude=auto`` the odometry pose's attitude stands in (``attitude_from_odometry``), else the
    frame is warped at the reference attitude without compensation and is not queued
    (``attitude_dropouts``). ``finalize`` writes these counts to metrics.json under ``ipm``, with
    ``outlier_frames`` (frames whose own pitch lay beyond ``pitch_threshold`` of the reference pitch,
    compensated by their full relative pitch) and ``reference_without_inliers`` (frames whose queue
    had no pose within the threshold of its centre, e.g. on rough ground).

    Extensions, off by default and on in ``ipm=mc_ahead``: ``reference_fit=line`` with
    ``lookahead`` (the reference follows a hill's grade and the BEV's plane takes the grade ahead,
    :class:`PoseQueue`), and ``attitude_noise`` (the IMU's noise shrunk out of psi and theta).
    """

    name = "mc"
    Params = MotionCompensatedIpmParams

    def __init__(self, params: MotionCompensatedIpmParams) -> None:
        super().__init__(params)
        self.params: MotionCompensatedIpmParams = params
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
        self.last_motion = (0.0, 0.0)
        self.last_step = 0.0
        self.counts: dict[str, int] = {}
        self._reset_counts()

    def _reset_counts(self) -> None:
        self.counts = {
            "frames": 0,
            "attitude_from_odometry": 0,
            "attitude_dropouts": 0,
            "outlier_frames": 0,
            "reference_without_inliers": 0,
        }
        self._max_theta = 0.0

    def begin(self, context: RunContext) -> None:
        """Empty the pose queue: a new sequence starts with no reference."""
        super().begin(context)
        self.queue.reset()
        self._last_position = None
        self.last_reference = None
        self._reset_counts()

    def finalize(self, context: RunContext) -> None:
        """Write the frame counts and the largest pitch compensation to metrics.json under ``ipm``."""
        super().finalize(context)
        entry: dict[str, Any] = dict(self.counts)
        entry["max_abs_pitch_compensation"] = round(self._max_theta, 6)
        context.metrics.setdefault("ipm", {}).update(entry)

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

    def compensation(self, frame: Frame, image: np.ndarray | None = None) -> tuple[float, float]:
        """``(psi, theta)`` of eq. 1-2: the current attitude relative to the queue's reference."""
        self.counts["frames"] += 1
        roll, pitch = self.attitude(frame)
        if not (math.isfinite(roll) and math.isfinite(pitch)) and self.params.attitude == "auto":
            roll, pitch = _odometry_attitude(frame)
            if math.isfinite(roll) and math.isfinite(pitch):
                self._count("attitude_from_odometry", frame, "the IMU roll/pitch is not finite; the odometry's is used")
        self.last_motion = (0.0, 0.0)
        self.last_step = 0.0  # a frame without attitude is not queued: the next frame's step covers it
        if not (math.isfinite(roll) and math.isfinite(pitch)):
            self._count("attitude_dropouts", frame, "no finite roll/pitch; warped at the reference attitude")
            return 0.0, 0.0
        self.last_step = self._step(frame)
        self.queue.push(roll, pitch, self.last_step)
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
        self.last_motion = (-roll_motion, pitch_motion)  # the robot's own (psi, theta) against its ground
        psi = -roll_motion if self.params.compensate_roll else 0.0
        # the ground ahead's pitch against the ground under the robot: exactly 0.0 for the paper's mean
        ahead = reference.pitch - reference.target_pitch
        theta = pitch_motion + ahead if self.params.compensate_pitch else 0.0
        self._max_theta = max(self._max_theta, abs(theta))
        return psi, theta

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

    def homography(self, calibration: Calibration, psi: float = 0.0, theta: float = 0.0) -> np.ndarray:
        """BEV index coordinates -> image pixels, compensated by ``psi`` and ``theta`` (eq. 1-4)."""
        return bev_to_image_homography(calibration, self.grid, psi, theta, self.params.roll_axis)


class _AheadDefaults(MotionCompensatedIpmParams):
    """MC-IPM with ``ipm=mc_ahead``'s extensions on by default: the base of the variants built on it."""

    reference_fit: ReferenceFit = "line"
    lookahead: float = 2.0
    attitude_noise: float = 0.005


class PlaneMotionCompensatedIpmParams(_AheadDefaults):
    """``ipm=mc_plane``: ``ipm=mc_ahead``'s attitude, with the ground ahead's plane measured from two views."""

    plane_baseline: float = Field(
        0.6,
        gt=0.0,
        description="metres driven between the two views the plane is fitted to (near a paving's period, "
        "0.7-1.0 m here, the fit can lock onto the wrong joint)",
    )
    plane_min_baseline: float = Field(0.4, gt=0.0, description="no fit with less than this between the views")
    plane_scales: list[int] = Field(
        default_factory=lambda: [4, 2, 1],
        min_length=1,
        description="image downsampling per level of the fit, coarse to fine",
    )
    plane_iterations: int = Field(8, ge=1, description="Gauss-Newton iterations per level")
    plane_rotation_prior: float = Field(
        0.003, gt=0.0, description="rad: the odometry's relative rotation between the views, corrected by the fit"
    )
    plane_height_prior: float = Field(
        0.005,
        gt=0.0,
        description="relative: the odometry's scale (camera height over the plane), corrected by the fit; tight, "
        "so that the height cannot stand in for the plane's pitch on a curved ground",
    )
    plane_measurement_noise: float = Field(0.003, gt=0.0, description="rad: one fit's noise (the filter's R)")
    plane_rate_noise: float = Field(
        0.01, gt=0.0, description="rad/m per sqrt(m): how fast the grade ahead may change (the filter's Q)"
    )
    plane_bump_threshold: float = Field(
        0.01,
        gt=0.0,
        description="rad: while the robot's own pitch (the IMU against the reference) exceeds this, "
        "within a baseline, the fit is not used (a bump's image pair breaks the plane); the IMU compensates",
    )

    @model_validator(mode="after")
    def _check_plane(self) -> PlaneMotionCompensatedIpmParams:
        if self.plane_min_baseline > self.plane_baseline:
            raise ValueError(
                f"plane_min_baseline ({self.plane_min_baseline}) must not exceed plane_baseline ({self.plane_baseline})"
            )
        if any(scale < 1 for scale in self.plane_scales):
            raise ValueError(f"plane_scales must be whole downsampling factors >= 1, got {list(self.plane_scales)}")
        return self


class PlaneMotionCompensatedIPM(MotionCompensatedIPM):
    """MC-IPM whose BEV plane is the ground ahead as the camera sees it (extension of Sec. III-A).

    The robot's own roll and pitch against its ground (a bump) come from the IMU as in ``ipm=mc_ahead``
    (eq. 1-2 against the queue's reference, the noise shrunk out). The ground ahead's attitude
    against the ground under the robot, which no past pose knows at the foot or crest of a hill,
    is measured from the image: :class:`~sgf_plugins.ipm.ground_plane.GroundPlaneTracker` fits the
    plane that maps the current view onto one about ``plane_baseline`` metres back, and a Kalman
    filter over distance (:class:`~sgf_plugins.ipm.ground_plane.GradeFilter`) smooths the fitted
    ``(psi, theta)`` minus the robot's own. Until the first fit, and without an image, it is
    ``ipm=mc_ahead``. ``finalize`` adds ``plane_fits``, ``plane_skipped_bumps`` and
    ``plane_no_fit`` to metrics.json under ``ipm``.
    """

    name = "mc_plane"
    Params = PlaneMotionCompensatedIpmParams

    def __init__(self, params: PlaneMotionCompensatedIpmParams) -> None:
        super().__init__(params)
        self.params: PlaneMotionCompensatedIpmParams = params
        self.tracker = GroundPlaneTracker(
            self.grid,
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
        self.plane_counts = {"plane_fits": 0, "plane_skipped_bumps": 0, "plane_no_fit": 0}

    def set_grid(self, grid: BevGrid) -> None:
        """Resample, and fit the plane, in ``grid``."""
        super().set_grid(grid)
        self.tracker.grid = grid

    def begin(self, context: RunContext) -> None:
        """Forget the views, the filters and the counts of the previous sequence."""
        super().begin(context)
        self.tracker.reset()
        self.pitch_filter.reset()
        self.roll_filter.reset()
        self._recent_motion = []
        self._start = None
        self.plane_counts = dict.fromkeys(self.plane_counts, 0)

    def finalize(self, context: RunContext) -> None:
        """MC-IPM's counts, and how many frames had a plane fit, were skipped in a bump, or had none."""
        super().finalize(context)
        context.metrics.setdefault("ipm", {}).update(self.plane_counts)

    def compensation(self, frame: Frame, image: np.ndarray | None = None) -> tuple[float, float]:
        """``(psi, theta)``: the robot's own attitude (IMU) plus the ground ahead's (fitted, filtered)."""
        psi_ahead, theta_ahead = super().compensation(frame, image)
        psi_motion, theta_motion = self.last_motion
        step, travelled = self.last_step, self.queue.travelled
        self.pitch_filter.predict(step)
        self.roll_filter.predict(step)
        threshold = self.params.plane_bump_threshold
        window = self.params.plane_baseline + 0.4
        self._recent_motion = [(d, m) for d, m in self._recent_motion if travelled - d <= window]
        bumpy = abs(theta_motion) > threshold or any(m > threshold for _, m in self._recent_motion)
        self._recent_motion.append((travelled, abs(theta_motion)))
        if image is not None:
            start = self._start if self._start is not None else (psi_ahead, theta_ahead)
            fit = self.tracker.measure(image, frame.odometry, frame.calibration, *start)
            if fit is None:
                self.plane_counts["plane_no_fit"] += 1
                self._start = None
            elif bumpy:
                self.plane_counts["plane_skipped_bumps"] += 1
                self._start = (fit.psi, fit.theta)
            else:
                self.plane_counts["plane_fits"] += 1
                self.pitch_filter.update(fit.theta - theta_motion)
                self.roll_filter.update(fit.psi - psi_motion)
                self._start = (fit.psi, fit.theta)
        pitch_ahead, roll_ahead = self.pitch_filter.value, self.roll_filter.value
        if pitch_ahead is None or roll_ahead is None:
            return psi_ahead, theta_ahead
        psi = psi_motion + roll_ahead if self.params.compensate_roll else 0.0
        theta = theta_motion + pitch_ahead if self.params.compensate_pitch else 0.0
        return psi, theta


class HindsightMotionCompensatedIpmParams(_AheadDefaults):
    """``ipm=mc_hindsight``: ``ipm=mc_ahead`` until the path after a frame is known, then its plane."""

    hindsight: float = Field(
        6.5,
        gt=0.0,
        description="metres of path driven after a frame before its BEV is made (the BEV's far edge and a "
        "margin); the whole pipeline runs this far behind the camera",
    )
    hindsight_min_reach: float = Field(
        2.0, gt=0.0, description="metres ahead the path must reach inside the BEV for a plane; else mc_ahead's"
    )
    attitude_window: float = Field(
        0.6,
        gt=0.0,
        description="metres on either side of a frame whose median IMU attitude is the robot's on its ground "
        "(the frame's own deviation from it is shrunk by attitude_noise)",
    )


class HindsightMotionCompensatedIPM(MotionCompensatedIPM):
    """MC-IPM whose BEV plane is the ground ahead as the robot later drove over it (extension of Sec. III-A).

    The pipeline reads ``hindsight`` metres of path ahead of each frame (``Frame.path_ahead``,
    :attr:`read_ahead`); :func:`~sgf_plugins.ipm.hindsight.ground_ahead` fits the plane of the
    ground within the BEV's reach to it, and the robot's own attitude against its ground is the
    median IMU attitude around the frame plus the frame's shrunk deviation
    (:mod:`sgf_plugins.ipm.hindsight`). Then ``theta`` (eq. 2) is the robot's pitch against that
    plane and ``psi`` (eq. 1) its roll against the ground's roll there. Without a path (a robot
    feeding frames live, or one that turns out of the BEV or stops at the sequence's end) it is
    ``ipm=mc_ahead``. ``finalize`` adds ``hindsight_planes`` and ``hindsight_fallbacks`` to
    metrics.json under ``ipm``.
    """

    name = "mc_hindsight"
    Params = HindsightMotionCompensatedIpmParams

    def __init__(self, params: HindsightMotionCompensatedIpmParams) -> None:
        super().__init__(params)
        self.params: HindsightMotionCompensatedIpmParams = params
        self.window = AttitudeWindow(params.attitude_window)
        self.last_ground: GroundAhead | None = None
        self.hindsight_counts = {"hindsight_planes": 0, "hindsight_fallbacks": 0}

    @property
    def read_ahead(self) -> float:
        """The metres of path the runner reads ahead of each frame for this stage."""
        return self.params.hindsight

    def begin(self, context: RunContext) -> None:
        """Forget the attitudes and counts of the previous sequence."""
        super().begin(context)
        self.window.reset()
        self.last_ground = None
        self.hindsight_counts = dict.fromkeys(self.hindsight_counts, 0)

    def finalize(self, context: RunContext) -> None:
        """MC-IPM's counts, and how many frames had a plane from the path ahead or fell back to mc_ahead."""
        super().finalize(context)
        context.metrics.setdefault("ipm", {}).update(self.hindsight_counts)

    def compensation(self, frame: Frame, image: np.ndarray | None = None) -> tuple[float, float]:
        """``(psi, theta)``: the robot's attitude against the plane of the path it drove next."""
        largest = self._max_theta
        fallback = super().compensation(frame, image)  # keeps the queue and its counts going
        travelled = self.queue.travelled
        roll, pitch = self.attitude(frame)
        path = frame.path_ahead
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        ground = None
        if path is not None and math.isfinite(roll) and math.isfinite(pitch):
            profile = path_profile(odometry, path)
            ground = ground_ahead(
                odometry, path, self.grid.x_min, self.grid.x_max, self.params.hindsight_min_reach, profile=profile
            )
            self.window.add(travelled, roll, pitch)
            for distance, (r, p) in zip(profile[0], path.imu_roll_pitch, strict=True):
                self.window.add(travelled + float(distance), float(r), float(p))
        self.last_ground = ground
        smooth = self.window.median(travelled) if ground is not None else None
        if ground is None or smooth is None:
            self.hindsight_counts["hindsight_fallbacks"] += 1
            return fallback
        self.hindsight_counts["hindsight_planes"] += 1
        noise = self.params.attitude_noise
        body_roll = steadied(roll, smooth[0], noise)
        body_pitch = steadied(pitch, smooth[1], noise)
        ground_roll = body_roll if ground.roll is None else ground.roll
        psi = -(body_roll - ground_roll) if self.params.compensate_roll else 0.0
        theta = body_pitch - ground.pitch if self.params.compensate_pitch else 0.0
        self._max_theta = max(largest, abs(theta))  # this pitch, not the fallback's
        return psi, theta
