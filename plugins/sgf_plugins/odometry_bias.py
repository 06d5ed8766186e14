"""The wheel odometry's heading bias per metre, estimated from loop closures (``backend.odometry_yaw_bias``).

Wheel odometry turns a little with every metre it drives (unequal wheel radii, a pulling tyre):
the heading error grows with the distance and the position error with its square. Eq. 11 spreads
each loop's error over the drive it closes, but the drive after the last loop keeps drifting. A
loop measures the bias: between its two frames the odometry turned by the true turn plus the bias
times the path length, and the loop's ICP measured the true turn. :class:`HeadingBias` keeps those
measurements, estimates the bias by weighted least squares (a zero-mean prior; a Cauchy weight
per loop, so that one false loop cannot set it) and takes it off every odometry step that follows.
"""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.geometry import invert, rotation_rpy, xy_yaw

#: Largest bias the estimate may take (rad per metre: 1 degree per metre turns a robot round in 360 m).
MAX_YAW_BIAS = math.radians(1.0)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class HeadingBias:
    """Estimate of the odometry's heading bias (rad/m) from loops, and odometry corrected by it.

    ``correct`` turns each new odometry step by ``-bias * step length`` (the bias estimated from the
    loops seen so far) and returns the corrected odometry pose; ``observe`` adds a loop. Loops
    correct the drive they close themselves; the correction is for the drive after them, so earlier
    steps are never re-corrected.
    """

    def __init__(
        self, prior_sigma: float, odometry_sigma_yaw: float, kernel_width: float = 3.0, max_bias: float = MAX_YAW_BIAS
    ) -> None:
        self.prior_sigma = prior_sigma
        self.odometry_sigma_yaw = odometry_sigma_yaw
        self.kernel_width = kernel_width
        self.max_bias = max_bias
        self.value = 0.0
        self._travel: dict[int, tuple[float, float]] = {}  # frame: path length and raw heading change so far
        self._raw: np.ndarray | None = None
        self._corrected: np.ndarray | None = None
        self._distance = 0.0
        self._turn = 0.0
        self._turns: list[float] = []  # per loop: the raw odometry's turn less the loop's (rad)
        self._lengths: list[float] = []  # ...the path between its frames (m)
        self._variances: list[float] = []  # ...and the variance of that difference (rad^2)

    @property
    def loops(self) -> int:
        """Loops observed so far."""
        return len(self._turns)

    def correct(self, frame_index: int, odometry: np.ndarray) -> np.ndarray:
        """The frame's odometry pose with every step since the first frame turned by the bias then known."""
        raw = np.asarray(odometry, dtype=np.float64)
        if self._raw is None or self._corrected is None:
            corrected = raw.copy()
        else:
            step = invert(self._raw) @ raw
            length = float(np.linalg.norm(step[:3, 3]))
            self._distance += length
            self._turn += xy_yaw(step)[2]
            turn = np.eye(4)
            turn[:3, :3] = rotation_rpy(0.0, 0.0, -self.value * length)
            corrected = self._corrected @ step @ turn
        self._raw, self._corrected = raw, corrected
        self._travel[frame_index] = (self._distance, self._turn)
        return corrected

    def observe(self, frame_from: int, frame_to: int, loop_yaw: float, loop_yaw_variance: float) -> bool:
        """Add a loop: its relative yaw (frame_to in frame_from) and that yaw's variance; False for unknown frames."""
        start, end = self._travel.get(frame_from), self._travel.get(frame_to)
        if start is None or end is None:
            return False
        length = abs(end[0] - start[0])
        if length <= 0.0:
            return False
        prediction = self.value * length
        turn = prediction + _wrap(end[1] - start[1] - loop_yaw - prediction)
        self._turns.append(turn)
        self._lengths.append(length)
        self._variances.append(self.odometry_sigma_yaw**2 * length + max(float(loop_yaw_variance), 0.0))
        self._estimate()
        return True

    def _estimate(self) -> None:
        """Weighted least squares with the prior, re-weighted by a Cauchy kernel on each loop's residual."""
        turns, lengths, variances = np.array(self._turns), np.array(self._lengths), np.array(self._variances)
        bias = self.value
        for _ in range(20):
            whitened = (turns - bias * lengths) / np.sqrt(variances)
            weights = 1.0 / (1.0 + (whitened / self.kernel_width) ** 2)
            information = 1.0 / self.prior_sigma**2 + float(np.sum(weights * lengths**2 / variances))
            updated = float(np.sum(weights * turns * lengths / variances)) / information
            done = abs(updated - bias) < 1e-12
            bias = updated
            if done:
                break
        self.value = float(np.clip(bias, -self.max_bias, self.max_bias))
