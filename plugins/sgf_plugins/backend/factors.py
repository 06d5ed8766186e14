"""The factors of eq. 11 in GTSAM: keys, pose conversions and the noise models of odometry, priors and loops.

GTSAM is imported inside functions so that listing plugins stays fast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from sgf_pipeline.geometry import rotation_rpy, xy_yaw

PoseKind = Literal["pose2", "pose3"]
Kernel = Literal["cauchy", "huber", "none"]


@dataclass(frozen=True)
class NoiseSettings:
    """Noise models of eq. 11 in radians (from the back-end's Params): odometry sigmas grow with sqrt(distance)."""

    odometry_sigma_xy: float
    odometry_sigma_yaw: float
    odometry_sigma_z: float
    odometry_sigma_roll_pitch: float
    odometry_floor_xy: float
    odometry_floor_yaw: float
    imu_sigma_roll_pitch: float
    loop_sigma_z: float
    loop_sigma_roll_pitch: float
    loop_kernel: Kernel
    loop_kernel_width: float
    prior_sigma_xy: float
    prior_sigma_yaw: float
    map_sigma_xy: float
    map_sigma_yaw: float
    yaw_bias_sigma: float | None  # rad/m, prior sigma of the odometry's heading bias (None: not estimated)
    yaw_bias_reading_sigma: float  # rad/m, the sigma that chooses between aliased readings


FRAME_SYMBOL = "x"  # GTSAM key character of a processed frame's pose
MAP_SYMBOL = "m"  # ...and of a prior map frame's pose


def X(frame_index: int) -> int:
    """GTSAM key of a processed frame's pose."""
    import gtsam

    return int(gtsam.symbol(FRAME_SYMBOL, frame_index))


def M(map_frame: int) -> int:
    """GTSAM key of a prior map frame's pose."""
    import gtsam

    return int(gtsam.symbol(MAP_SYMBOL, map_frame))


def planar(pose: np.ndarray) -> np.ndarray:
    """The planar part of a 4x4 pose, as a 4x4 pose (z, roll and pitch dropped)."""
    x, y, yaw = xy_yaw(pose)
    out = np.eye(4)
    out[:3, :3] = rotation_rpy(0.0, 0.0, yaw)
    out[:2, 3] = (x, y)
    return out


def _orthonormal(rot: np.ndarray) -> np.ndarray:
    """The nearest rotation matrix (guards against drift in composed poses)."""
    u, _, vt = np.linalg.svd(rot)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


class FactorBuilder:
    """GTSAM poses, noise models and factors of one kind of pose (``Pose2`` or ``Pose3``) under ``noise``."""

    def __init__(self, pose3: bool, noise: NoiseSettings) -> None:
        self.pose3 = pose3
        self.noise = noise

    def pose(self, pose: np.ndarray) -> Any:
        """A 4x4 pose as a GTSAM pose of the graph's kind."""
        import gtsam

        if self.pose3:
            return gtsam.Pose3(gtsam.Rot3(_orthonormal(pose[:3, :3])), np.asarray(pose[:3, 3], dtype=np.float64))
        x, y, yaw = xy_yaw(pose)
        return gtsam.Pose2(x, y, yaw)

    def matrix(self, value: Any) -> np.ndarray:
        """A GTSAM pose of the graph's kind as a 4x4 pose."""
        if self.pose3:
            return np.asarray(value.matrix(), dtype=np.float64)
        return planar_from_xyt(np.array([[value.x(), value.y(), value.theta()]]))[0]

    def diagonal(self, xy: float, yaw: float, z: float, roll_pitch: float) -> Any:
        """A diagonal noise model from sigmas (z, roll and pitch only in Pose3)."""
        import gtsam

        if self.pose3:
            return gtsam.noiseModel.Diagonal.Sigmas(np.array([roll_pitch, roll_pitch, yaw, xy, xy, z]))
        return gtsam.noiseModel.Diagonal.Sigmas(np.array([xy, xy, yaw]))

    def prior(self, key: int, pose: np.ndarray, model: Any) -> Any:
        """A prior factor holding ``key`` at ``pose``."""
        import gtsam

        factor = gtsam.PriorFactorPose3 if self.pose3 else gtsam.PriorFactorPose2
        return factor(key, self.pose(pose), model)

    def between(self, key_a: int, key_b: int, relative: np.ndarray, model: Any) -> Any:
        """A between factor: ``relative`` is the pose of ``key_b`` in the frame of ``key_a``."""
        import gtsam

        factor = gtsam.BetweenFactorPose3 if self.pose3 else gtsam.BetweenFactorPose2
        return factor(key_a, key_b, self.pose(relative), model)

    def attitude(self, key: int, roll: float, pitch: float) -> Any:
        """The IMU's roll and pitch as an attitude factor on a Pose3 (gravity's direction in the body frame)."""
        import gtsam

        up = rotation_rpy(float(roll), float(pitch), 0.0).T @ np.array([0.0, 0.0, 1.0])
        model = gtsam.noiseModel.Isotropic.Sigma(2, self.noise.imu_sigma_roll_pitch)
        return gtsam.AttitudeFactorPose3(key, gtsam.Unit3(np.array([0.0, 0.0, 1.0])), model, gtsam.Unit3(up))

    def poses(self, values: Any) -> np.ndarray:
        """The (N, 4, 4) poses of every pose in GTSAM ``values``, in key order."""
        import gtsam

        if self.pose3:
            rows = np.asarray(gtsam.utilities.extractPose3(values))
            out = np.tile(np.eye(4), (len(rows), 1, 1))
            out[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
            out[:, :3, 3] = rows[:, 9:12]
            return out
        return planar_from_xyt(np.asarray(gtsam.utilities.extractPose2(values)))

    def odometry_noise(self, relative: np.ndarray, distance: float | None = None, steps: int = 1) -> Any:
        """Odometry noise: sigma^2 = steps * floor^2 + (sigma over one metre)^2 * distance (a random walk).

        ``distance`` is the path length over the ``steps`` frames the factor spans (default: one step,
        the length of ``relative``).
        """
        n = self.noise
        d = float(np.linalg.norm(relative[:3, 3])) if distance is None else distance
        xy = math.sqrt(steps * n.odometry_floor_xy**2 + n.odometry_sigma_xy**2 * d)
        yaw = math.sqrt(steps * n.odometry_floor_yaw**2 + n.odometry_sigma_yaw**2 * d)
        z = math.sqrt(steps * n.odometry_floor_xy**2 + n.odometry_sigma_z**2 * d)
        rp = math.sqrt(steps * n.odometry_floor_yaw**2 + n.odometry_sigma_roll_pitch**2 * d)
        return self.diagonal(xy, yaw, z, rp)

    def loop_noise(self, covariance: np.ndarray, adjoint: np.ndarray | None = None) -> Any:
        """The loop factor's noise: the constraint's covariance (moved by ``adjoint``) under the robust kernel."""
        import gtsam

        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            raise ValueError(f"a loop covariance must be a finite 3x3 matrix over (x, y, yaw), got {cov!r}")
        cov = 0.5 * (cov + cov.T)
        if np.linalg.eigvalsh(cov).min() <= 0.0:
            raise ValueError("a loop covariance must be positive definite")
        if self.pose3:
            full = np.zeros((6, 6))
            idx = [3, 4, 2]  # (x, y, yaw) inside Pose3's (roll, pitch, yaw, x, y, z) tangent
            full[np.ix_(idx, idx)] = cov
            full[0, 0] = full[1, 1] = self.noise.loop_sigma_roll_pitch**2
            full[5, 5] = self.noise.loop_sigma_z**2
        else:
            full = cov
        if adjoint is not None:
            full = adjoint @ full @ adjoint.T
            full = 0.5 * (full + full.T)
        gaussian = gtsam.noiseModel.Gaussian.Covariance(full)
        kernel = self.noise.loop_kernel
        if kernel == "none":
            return gaussian
        width = self.noise.loop_kernel_width
        estimator = (
            gtsam.noiseModel.mEstimator.Cauchy.Create(width)
            if kernel == "cauchy"
            else gtsam.noiseModel.mEstimator.Huber.Create(width)
        )
        return gtsam.noiseModel.Robust.Create(estimator, gaussian)


def planar_from_xyt(xyt: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses from (N, 3) rows of ``x, y, yaw``."""
    xyt = np.asarray(xyt, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
    out = np.tile(np.eye(4), (len(xyt), 1, 1))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 0, 3], out[:, 1, 3] = xyt[:, 0], xyt[:, 1]
    return out
