"""Parameters of a synthetic campus sequence (light: no rendering code is imported with them)."""

from __future__ import annotations

from pydantic import Field, model_validator

from sgf_pipeline.stage import StageParams
from sgf_plugins.shared.bev_region import BEV_GRID


class WorldParams(StageParams):
    """Parameters of a synthetic campus sequence (the ``dataset`` config of the campus presets)."""

    seed: int = Field(0, description="seed of the world (layout, textures, markings) and of all its noise")
    scale: float = Field(
        1.0, gt=0.0, le=1.0, description="fraction of the route's length: the campus shrinks, the route keeps its shape"
    )
    night: bool = Field(False, description="drive after dark: LED headlight, street lamps, high gain and noise")
    rate_hz: float = Field(10.0, gt=0.0, le=100.0, description="camera frame rate (Hz)")
    width: int = Field(640, ge=64, le=4096, description="image width (px)")
    height: int = Field(480, ge=48, le=4096, description="image height (px)")
    fx: float = Field(400.0, gt=0.0, description="focal length x (px)")
    fy: float = Field(400.0, gt=0.0, description="focal length y (px)")
    cx: float | None = Field(None, description="principal point x (px); null = image centre (width - 1) / 2")
    cy: float | None = Field(None, description="principal point y (px); null = image centre (height - 1) / 2")
    flat_ground: bool = Field(False, description="no hills, bumps or rough patches: the ground is the plane z = 0")
    rough_paving_per_km: float = Field(
        0.0,
        ge=0.0,
        description="more patches of uneven paving (8-18 mm waves, 5-12 m across) per km of every path over 20 m, "
        "on top of the campus's own (one on 30 % of them); the rest of the campus stays the same",
    )
    camera_height: float = Field(0.6, gt=0.1, le=3.0, description="camera height above the ground (m)")
    camera_tilt_deg: float = Field(25.0, ge=5.0, le=70.0, description="camera tilt below the horizon (deg)")
    speed_min: float = Field(1.0, gt=0.0, description="slowest cruising speed (m/s)")
    speed_max: float = Field(1.5, gt=0.0, description="fastest cruising speed (m/s)")
    odometry_seed: int | None = Field(
        None,
        description="seed of the wheel odometry's and the IMU's noise alone (null: seed); another value drives the "
        "same world, route and camera images with other sensor noise: a second drive of the same campus",
    )
    odometry_scale_error: float = Field(0.012, description="relative error of the wheel distance")
    odometry_yaw_bias_deg_per_m: float = Field(
        0.07, ge=-5.0, le=5.0, description="heading drift per metre driven (deg/m; its sign: see the next key)"
    )
    odometry_yaw_bias_seeded_sign: bool = Field(
        True,
        description="the seed turns the heading drift either way (either sign equally likely); false: it turns "
        "the way the sign of odometry_yaw_bias_deg_per_m says (positive: to the left)",
    )
    odometry_yaw_random_walk_deg_per_m: float = Field(
        0.0001, ge=0.0, description="random walk of the heading drift rate (deg/m per sqrt(m))"
    )
    odometry_distance_noise: float = Field(0.01, ge=0.0, description="wheel distance noise (m per sqrt(m))")
    odometry_yaw_noise_deg: float = Field(0.01, ge=0.0, description="per-frame heading noise (deg)")
    imu_noise_deg: float = Field(0.15, ge=0.0, description="IMU roll/pitch white noise (deg)")
    imu_bias_deg: float = Field(0.1, ge=0.0, description="IMU roll/pitch constant bias bound (deg)")
    clutter: float = Field(
        1.0,
        ge=0.0,
        le=10.0,
        description="ground clutter that is not a marking, relative to the campus's own (1): cracks, stains and "
        "asphalt patches scale with it; above 1 it also strews fallen leaves and casts the thin shadows of posts",
    )
    occluders: bool = Field(True, description="people and vehicles moving on the paths")
    pedestrians_per_km: float = Field(30.0, ge=0.0, description="people per km of path")
    vehicles_per_km: float = Field(4.0, ge=0.0, description="service vehicles per km of wide path")
    sensor_noise: bool = Field(True, description="camera read and shot noise")
    exposure_variation: float = Field(0.15, ge=0.0, le=1.0, description="amplitude of the auto-exposure wander")
    marking_spacing: float = Field(26.0, gt=2.0, description="mean distance between markings along a path (m)")
    exclude_designs: list[str] = Field(
        default_factory=list, description="marking designs or families never painted (held out for testing)"
    )
    only_designs: list[str] = Field(
        default_factory=list, description="paint only these designs or families (e.g. the held-out test split)"
    )
    design_weights: dict[str, float] | None = Field(
        None,
        description="how often a design is chosen, by name (relative; 0 = never; null = every design's own): "
        "e.g. {random_shape: 3} paints procedural custom markings, which no preset does, for saliency training worlds",
    )
    bev_resolution: float = Field(
        BEV_GRID.resolution, gt=0.0, description="visibility grid (the IPM's BEV grid) resolution (m)"
    )
    bev_x_min: float = Field(BEV_GRID.x_min, description="visibility grid near edge (m ahead of the base)")
    bev_x_max: float = Field(BEV_GRID.x_max, description="visibility grid far edge (m)")
    bev_y_min: float = Field(BEV_GRID.y_min, description="visibility grid right edge (m)")
    bev_y_max: float = Field(BEV_GRID.y_max, description="visibility grid left edge (m)")
    pass_merge_gap_s: float = Field(
        1.0, ge=0.0, description="join passes of one drive-by split by a gap this short (s)"
    )

    @model_validator(mode="after")
    def _check(self) -> WorldParams:
        if self.speed_min > self.speed_max:
            raise ValueError(f"speed_min ({self.speed_min}) must not exceed speed_max ({self.speed_max})")
        bad = {k: v for k, v in (self.design_weights or {}).items() if not v >= 0.0}
        if bad:
            raise ValueError(f"design_weights must be >= 0, got {bad}")
        if self.bev_x_min >= self.bev_x_max or self.bev_y_min >= self.bev_y_max:
            raise ValueError("the visibility grid needs bev_x_min < bev_x_max and bev_y_min < bev_y_max")
        return self


class NightWorldParams(WorldParams):
    """Parameters of the night sequence (the same as by day, with ``night`` on by default)."""

    night: bool = Field(True, description="drive after dark: LED headlight, street lamps, high gain and noise")
