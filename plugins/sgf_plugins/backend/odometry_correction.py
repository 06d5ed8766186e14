"""The odometry's corrections before it enters the pose graph: its scale, then its heading bias when estimated.

What the heading bias saw is kept (per processed frame the scaled odometry and the camera's bias
estimate, per loop its turn), so that the correction can be replayed with loops taken back, or the
bias known at the end applied to the whole drive.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sgf_pipeline.geometry import xy_yaw
from sgf_pipeline.types import LoopConstraint
from sgf_plugins.backend.factors import NoiseSettings
from sgf_plugins.backend.poses import grown
from sgf_plugins.shared.heading_bias import HeadingBias, ScaledOdometry, with_heading_bias

LoopKey = tuple[int, int, bool]  # a loop's ends: frame from, frame to, from the map


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
        # Per processed frame its odometry before the bias correction, and per loop what the bias
        # saw (newest frame then, ends, yaw, variance).
        self._scaled = np.zeros((64, 4, 4))
        self._camera_bias = np.full((64, 2), np.inf)  # per processed frame: the camera's heading bias and sigma
        self._bias_loops: list[tuple[int, LoopKey, float, float]] = []
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
            self._camera_bias = grown(self._camera_bias, row)
        self._scaled[row] = scaled
        self._camera_bias[row] = camera_bias if camera_bias is not None else (np.inf, np.inf)
        self.size += 1
        return odometry

    def observe(self, loop: LoopConstraint, relative: np.ndarray, newest_frame: int) -> None:
        """Let the heading bias read a loop's turn (``relative``: its relative pose), if it has one to read."""
        if self.heading_bias is not None and not loop.from_map and not loop.position_only:  # no turn to read
            yaw, variance = xy_yaw(relative)[2], float(loop.covariance[2][2])
            self.heading_bias.observe(loop.frame_from, loop.frame_to, yaw, variance)
            key = (loop.frame_from, loop.frame_to, loop.from_map)
            self._bias_loops.append((newest_frame, key, yaw, variance))

    def saw_any(self, keys: set[LoopKey]) -> bool:
        """Whether the heading bias read any of the loops ``keys``."""
        return self.heading_bias is not None and any(b[1] in keys for b in self._bias_loops)

    def replayed_without(self, keys: set[LoopKey], frames: Sequence[int]) -> np.ndarray:
        """The odometry (N, 4, 4) of ``frames`` corrected again from the first on, the loops ``keys`` left out.

        Every frame and every other loop is given to a new estimator in the order they came, so the
        correction of each step is the one it would have had without those loops.
        """
        assert self.heading_bias is not None
        bias = self.heading_bias.restarted()
        self._bias_loops = [b for b in self._bias_loops if b[1] not in keys]
        corrected = np.empty((len(frames), 4, 4))
        k = 0
        for row, frame in enumerate(frames):
            bias.camera(*self._camera_bias[row])
            corrected[row] = bias.correct(frame, self._scaled[row])
            while k < len(self._bias_loops) and self._bias_loops[k][0] == frame:
                _, (frame_from, frame_to, _), yaw, variance = self._bias_loops[k]
                bias.observe(frame_from, frame_to, yaw, variance)
                k += 1
        self.heading_bias = bias
        return corrected

    def in_hindsight(self, size: int) -> np.ndarray | None:
        """The first ``size`` frames' odometry with the heading bias known now taken off every step; None if none is."""
        if self.heading_bias is None or self.heading_bias.value == 0.0 or not size:
            return None
        return with_heading_bias(self._scaled[:size], self.heading_bias.value)
