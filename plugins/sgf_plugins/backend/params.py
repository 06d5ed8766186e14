"""Parameters of the back-ends, one model per concern: ``backend.<concern>.<key>``."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from sgf_pipeline import StageParams
from sgf_pipeline.config import FROM_MAP_PRIOR
from sgf_plugins.backend.factors import NoiseSettings


class BackendParams(StageParams):
    """What every back-end writes at the end of a run."""

    save_map: bool = Field(True, description="write the run's SGF map into the run directory")
    map_file: str = Field("sgf_map.safetensors", description="file name of the saved SGF map")


class OdometryNoise(StageParams):
    """The odometry factors' noise, a random walk over the distance travelled (``backend.odometry``)."""

    sigma_xy: float = Field(0.05, gt=0.0, description="translation sigma over one metre (m/sqrt(m))")
    sigma_yaw_deg: float = Field(0.5, gt=0.0, description="heading sigma over one metre (deg/sqrt(m))")
    sigma_z: float = Field(0.02, gt=0.0, description="pose3: height sigma over one metre (m/sqrt(m))")
    sigma_roll_pitch_deg: float = Field(
        2.0, gt=0.0, description="pose3: roll/pitch sigma over one metre (deg/sqrt(m)); loose, the IMU observes them"
    )
    floor_xy: float = Field(0.005, gt=0.0, description="translation sigma of a standstill (m)")
    floor_yaw_deg: float = Field(0.05, gt=0.0, description="heading sigma of a standstill (deg)")


class ImuNoise(StageParams):
    """The IMU attitude factors of a pose3 graph (``backend.imu``)."""

    sigma_roll_pitch_deg: float = Field(0.5, gt=0.0, description="pose3: sigma of the IMU attitude factor (deg)")


class LoopNoise(StageParams):
    """The loop factors' noise beyond their covariance, and their robust kernel (``backend.loop``)."""

    sigma_z: float = Field(0.05, gt=0.0, description="pose3: loop factor height sigma (m)")
    sigma_roll_pitch_deg: float = Field(1.0, gt=0.0, description="pose3: loop factor roll/pitch sigma (deg)")
    kernel: Literal["cauchy", "huber", "none"] = Field(
        "cauchy", description="robust kernel on loop factors (cauchy ignores gross outliers, huber bounds them)"
    )
    kernel_width: float = Field(
        3.0,
        gt=0.0,
        description="kernel width in sigmas of the whitened loop error (a loop is closed from dead "
        "reckoning while its error is below about twice this many sigmas of the odometry chain)",
    )


class FirstPosePrior(StageParams):
    """The prior on the first pose, which fixes the map frame (``backend.first_pose``)."""

    sigma_xy: float = Field(1e-3, gt=0.0, description="sigma of the first pose (m)")
    sigma_yaw_deg: float = Field(0.01, gt=0.0, description="sigma of the first pose (deg)")


class MapPrior(StageParams):
    """The priors on a prior map's frame poses (``backend.map_frames``; the map itself is ``map.prior``)."""

    sigma_xy: float = Field(0.05, gt=0.0, description="prior sigma of a prior map's frame poses (m)")
    sigma_yaw_deg: float = Field(0.5, gt=0.0, description="prior sigma of a prior map's frame poses (deg)")


class HeadingBiasParams(StageParams):
    """The odometry's heading bias per metre, estimated from the loops (``backend.heading_bias``)."""

    enabled: bool = Field(
        True,
        description="estimate the odometry's heading bias per metre travelled from the loops, and take it off the "
        "odometry that follows (the drive after the last loop drifts less); false = eq. 11 as printed",
    )
    sigma_deg_per_m: float = Field(
        0.5, gt=0.0, description="prior sigma of that bias (deg per metre; the prior's mean is 0)"
    )
    reading_sigma_deg_per_m: float = Field(
        0.1,
        gt=0.0,
        description="the bias wheel odometry is expected to have (deg per metre): it chooses between readings of "
        "the loops' turns that the loops cannot tell apart (loops one lap long: b and b + 360 deg / lap)",
    )
    hindsight: bool = Field(
        True,
        description="at the end of the run, take the final heading bias off the whole drive from its first frame "
        "(online it corrects only the drive after the loops that measured it) and solve the graph again in batch",
    )


class GraphParams(BackendParams):
    """The pose graph of eq. 11: its poses, noise models by factor, the heading bias, a prior map."""

    pose: Literal["pose2", "pose3"] = Field("pose2", description="planar poses, or 3-D with IMU roll/pitch factors")
    node_distance: float = Field(
        1.0,
        ge=0.0,
        description="travel (m) between pose nodes; frames between ride on the last node by odometry "
        "(0 = a node per processed frame; the newest frame of a loop gets one)",
    )
    odometry: OdometryNoise = Field(default_factory=OdometryNoise, description="the odometry factors' noise")
    imu: ImuNoise = Field(default_factory=ImuNoise, description="the IMU attitude factors (pose3)")
    loop: LoopNoise = Field(default_factory=LoopNoise, description="the loop factors' noise and robust kernel")
    first_pose: FirstPosePrior = Field(default_factory=FirstPosePrior, description="the prior on the first pose")
    heading_bias: HeadingBiasParams = Field(
        default_factory=HeadingBiasParams, description="the odometry's heading bias, estimated from the loops"
    )
    prior_map: str | None = Field(
        None,
        description="SGF map of an earlier run to localize on (inter-session factors; set map.prior)",
        json_schema_extra=FROM_MAP_PRIOR,
    )
    map_frames: MapPrior = Field(default_factory=MapPrior, description="the priors on a prior map's frame poses")
    graph: Literal["none", "g2o"] = Field(
        "none",
        description="write the final pose graph the back-end optimised: g2o (pose_graph.g2o, VERTEX_SE2 and EDGE_SE2 "
        "lines that GTSAM and g2o read; pose2 without a prior map), or none",
    )

    @model_validator(mode="after")
    def _graph_fits_g2o(self) -> GraphParams:
        if self.graph == "g2o" and (self.pose == "pose3" or self.prior_map):
            raise ValueError(
                "graph=g2o writes the Pose2 graph of one session; the pose3 graph's IMU attitude factors and a prior "
                "map's poses have no g2o edge: use pose=pose2 without a prior map, or graph=none"
            )
        return self

    def noise(self) -> NoiseSettings:
        """The noise models in the graph's units (radians)."""
        r = math.radians
        o, bias = self.odometry, self.heading_bias
        return NoiseSettings(
            odometry_sigma_xy=o.sigma_xy,
            odometry_sigma_yaw=r(o.sigma_yaw_deg),
            odometry_sigma_z=o.sigma_z,
            odometry_sigma_roll_pitch=r(o.sigma_roll_pitch_deg),
            odometry_floor_xy=o.floor_xy,
            odometry_floor_yaw=r(o.floor_yaw_deg),
            imu_sigma_roll_pitch=r(self.imu.sigma_roll_pitch_deg),
            loop_sigma_z=self.loop.sigma_z,
            loop_sigma_roll_pitch=r(self.loop.sigma_roll_pitch_deg),
            loop_kernel=self.loop.kernel,
            loop_kernel_width=self.loop.kernel_width,
            prior_sigma_xy=self.first_pose.sigma_xy,
            prior_sigma_yaw=r(self.first_pose.sigma_yaw_deg),
            map_sigma_xy=self.map_frames.sigma_xy,
            map_sigma_yaw=r(self.map_frames.sigma_yaw_deg),
            yaw_bias_sigma=r(bias.sigma_deg_per_m) if bias.enabled else None,
            yaw_bias_reading_sigma=r(bias.reading_sigma_deg_per_m),
        )


class LmSolver(StageParams):
    """Batch Levenberg-Marquardt (``backend.solver``)."""

    every_loop: bool = Field(True, description="re-optimize the whole graph on every frame that adds loops")
    max_iterations: int = Field(100, ge=1, description="LM iterations per optimisation")
    relative_error_tol: float = Field(1e-6, gt=0.0, description="LM stops when the error improves by less (relative)")


class LmParams(GraphParams):
    """Batch Levenberg-Marquardt over the whole graph."""

    solver: LmSolver = Field(default_factory=LmSolver, description="batch Levenberg-Marquardt")


class Isam2Solver(StageParams):
    """iSAM2's factorization and relinearization (``backend.solver``)."""

    factorization: Literal["qr", "cholesky"] = Field(
        "qr", description="QR: robust on long loop-free drives, where Cholesky finds the system indeterminate"
    )
    relinearize_threshold: float = Field(
        0.1, gt=0.0, description="relinearize a pose whose delta exceeds this (rad; also m unless set below)"
    )
    relinearize_threshold_translation: float | None = Field(
        None,
        gt=0.0,
        description="relinearize a pose whose translation delta exceeds this (m); null = relinearize_threshold",
    )
    relinearize_skip: int = Field(
        1, ge=1, description="check relinearization every this many updates (with the partial check keep 1)"
    )
    partial_relinearization_check: bool = Field(
        True, description="check only the variables an update touched for relinearization, not all of them"
    )
    loop_updates: int = Field(
        0, ge=0, description="extra iSAM2 updates on a frame that adds loops (each re-linearizes widely: costly)"
    )
    final_batch: bool = Field(False, description="finish with a batch LM over the whole graph from iSAM2's estimate")


class Isam2Params(GraphParams):
    """Incremental smoothing and mapping (iSAM2), for online use."""

    solver: Isam2Solver = Field(default_factory=Isam2Solver, description="iSAM2's factorization and relinearization")
