"""The IPM stages' parameters: the BEV grid (plain IPM), MC-IPM's pose queue, and the variants' extensions."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from sgf_pipeline import StageParams
from sgf_pipeline.types import BevGrid
from sgf_plugins.ipm.reference import ReferenceCenter, ReferenceFit
from sgf_plugins.shared.bev_homography import RollAxis
from sgf_plugins.shared.bev_region import BEV_GRID, Region


class IpmParams(StageParams):
    """The metric BEV grid (the virtual camera of eq. 3-4) and how the image is resampled into it."""

    resolution: float = Field(BEV_GRID.resolution, gt=0.0, description="metres per BEV pixel")
    x_min: float = Field(BEV_GRID.x_min, description="near edge of the BEV, metres ahead of the base origin")
    x_max: float = Field(BEV_GRID.x_max, description="far edge of the BEV, metres ahead of the base origin")
    y_min: float = Field(BEV_GRID.y_min, description="right edge of the BEV (metres, y is left)")
    y_max: float = Field(BEV_GRID.y_max, description="left edge of the BEV (metres, y is left)")
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


#: The extensions the preset ``ipm=mc_ahead`` (conf/ipm/mc_ahead.yaml) turns on over the paper's MC-IPM (``ipm=mc``).
AHEAD_MC: dict[str, Any] = {"reference_fit": "line", "lookahead": 2.0, "attitude_noise": 0.005}


class PlaneMotionCompensatedIpmParams(MotionCompensatedIpmParams):
    """``ipm=mc_plane``: ``ipm=mc_ahead``'s attitude, with the ground ahead's plane measured from two views.

    Its pose queue reference is ``ipm=mc_ahead``'s: the three defaults below are :data:`AHEAD_MC`.
    """

    reference_fit: ReferenceFit = Field(
        AHEAD_MC["reference_fit"],
        description="line (mc_ahead): pitch over distance travelled, extrapolated lookahead metres ahead | "
        "mean: the inliers' average (paper)",
    )
    lookahead: float = Field(
        AHEAD_MC["lookahead"],
        ge=0.0,
        description="mc_ahead: metres ahead whose ground pitch the BEV plane gets until the first plane fit",
    )
    attitude_noise: float = Field(
        AHEAD_MC["attitude_noise"],
        ge=0.0,
        description="mc_ahead: noise scale sigma (rad); a deviation d from the reference counts d^3 / (d^2 + sigma^2)",
    )

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


class HindsightMotionCompensatedIpmParams(MotionCompensatedIpmParams):
    """``ipm=mc_hindsight``: ``ipm=mc_ahead`` until the path after a frame is known, then its plane.

    Its pose queue reference, the fallback, is ``ipm=mc_ahead``'s: the three defaults below are :data:`AHEAD_MC`.
    """

    reference_fit: ReferenceFit = Field(
        AHEAD_MC["reference_fit"],
        description="line (mc_ahead): pitch over distance travelled, extrapolated lookahead metres ahead | "
        "mean: the inliers' average (paper)",
    )
    lookahead: float = Field(
        AHEAD_MC["lookahead"],
        ge=0.0,
        description="mc_ahead: metres ahead whose ground pitch the fallback's BEV plane gets",
    )
    attitude_noise: float = Field(
        AHEAD_MC["attitude_noise"],
        ge=0.0,
        description="mc_ahead: noise scale sigma (rad); a deviation d from the reference, or from the median "
        "attitude around the frame, counts d^3 / (d^2 + sigma^2)",
    )

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
