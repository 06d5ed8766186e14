"""The odometry's corrections before it enters the pose graph: its scale, then its heading bias when estimated.

The scaled odometry of every processed frame is kept, so that the bias known at the end can be
applied to the whole drive.
"""

from __future__ import annotations

import numpy as np

from sgf_pipeline.geometry import xy_yaw
from sgf_pipeline.types import LoopConstraint
from sgf_plugins.backend.factors import NoiseSettings
from sgf_plugins.backend.poses import grown
from sgf_plugins.shared.heading_bias import HeadingBias, ScaledOdometry, with_heading_bias


class OdometryCorrection:
    """Scale and heading-bias corrections of the processed frames' odometry, in the order they came."""

    def __init__(self, noise: NoiseSettings) -> None:
        self.scaled_odometry = ScaledOdometry()
        self.heading_bias = (
            None
            if noise.yaw_bias_sigma is None
            else HeadingBias(
                noise.yaw_bias_sigma,
                noise.odometry_sigma_yaw,
                noise.loop_kernel_width,
                reading_sigma=noise.yaw_bias_reading_sigma,
            )
        )
        self._scaled = np.zeros((64, 4, 4))  # per processed frame: its odometry before the bias correction
        self.size = 0

    def correct(
        self, index: int, odometry: np.ndarray, scale: float, camera_bias: tuple[float, float] | None
    ) -> np.ndarray:
        """The corrected odometry of a new processed frame (``scale`` and ``camera_bias`` as known now)."""
        odometry = self.scaled_odometry.correct(odometry, scale)
        scaled = odometry
        if self.heading_bias is not None:
            if camera_bias is not None:
                self.heading_bias.camera(*camera_bias)
            odometry = self.heading_bias.correct(index, odometry)
        row = self.size
        if row == len(self._scaled):
            self._scaled = grown(self._scaled, row)
        self._scaled[row] = scaled
        self.size += 1
        return odometry

    def observe(self, loop: LoopConstraint, relative: np.ndarray) -> None:
        """Let the heading bias read a loop's turn (``relative``: its relative pose), if it has one to read."""
        if self.heading_bias is not None and not loop.from_map and not loop.position_only:  # no turn to read
            yaw, variance = xy_yaw(relative)[2], float(loop.covariance[2][2])
            self.heading_bias.observe(loop.frame_from, loop.frame_to, yaw, variance)

    def in_hindsight(self, size: int) -> np.ndarray | None:
        """The first ``size`` frames' odometry with the heading bias known now taken off every step; None if none is."""
        if self.heading_bias is None or self.heading_bias.value == 0.0 or not size:
            return None
        return with_heading_bias(self._scaled[:size], self.heading_bias.value)
