"""The wheel odometry's heading bias per metre, estimated from loop closures (``backend.heading_bias.enabled``).

Wheel odometry turns a little with every metre it drives (unequal wheel radii, a pulling tyre):
the heading error grows with the distance and the position error with its square. Eq. 11 spreads
each loop's error over the drive it closes, but the drive after the last loop keeps drifting. A
loop measures the bias: between its two frames the odometry turned by the true turn plus the bias
times the path length, and the loop's ICP measured the true turn. :class:`HeadingBias` keeps those
measurements, estimates the bias by weighted least squares (a zero-mean prior; a Cauchy weight
per loop, so that one false loop among true ones hardly moves it) and, once at least two loops
agree with it (a lone false loop must not bend the drive) and it stands out of its own uncertainty
(``significance`` sigmas), takes it off every odometry step that follows. Loops over one stretch
share that stretch's heading noise, so the uncertainty counts the best single loop's information,
not their sum: a bias the heading noise could explain is left alone.

The raw turn between two frames is known modulo a full turn, so each bias b gives each loop the
residual wrap(turn - b * length), and the cost has a valley for every way to read the turns. The
valley is chosen on a grid of ``GRID`` biases over +-``max_bias`` by a bounded cost (each loop's
whitened residual squared, at most the kernel width squared: the loops that agree with a reading
choose it, not how far the others lie), and the re-weighted least squares refine the estimate
in it. So a false loop accepted first, whose turn claims another reading (a look-alike laid the
wrong way round: 160 degrees over 450 m), decides neither how the true loops that follow are read
nor, with one of them, an alias between them. A lone loop over which the bias turns the odometry
by more than half a turn (0.07 deg/m over 2.6 km) is still read the nearest way. Loops that are
all one length (each one lap of a loop route) cannot tell b from b + 360 degrees / lap at all:
the valley is therefore chosen with the bias wheel odometry is expected to have (``reading_sigma``,
0.1 deg/m in the back-end), and refined with the looser prior, which barely pulls it to zero.

The camera measures the same bias from the ground's turn between views a metre apart
(``odometry_scale=bev_motion``, :meth:`HeadingBias.camera`). Its estimate, once more certain than
the prior, replaces the prior's mean and sigma: the bias is taken off from then on, before any
loop, when it stands out of its uncertainty, and the loops' turns are read the way it says.
"""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.geometry import invert, pose_from_xy_yaw, xy_yaw

#: Largest bias the estimate may take (rad per metre: 1 degree per metre turns a robot round in 360 m).
MAX_YAW_BIAS = math.radians(1.0)
#: Biases tried over +-max_bias for the global minimum (a step of 0.002 deg/m at 1 deg/m: a loop over
#: 2.6 km, the longest here, has a valley about 0.01 deg/m wide).
GRID = 1001


class HeadingBias:
    """Estimate of the odometry's heading bias (rad/m) from loops, and odometry corrected by it.

    ``correct`` turns each new odometry step by ``-bias * step length`` (the bias estimated from the
    loops seen so far) and returns the corrected odometry pose; ``observe`` adds a loop. Loops
    correct the drive they close themselves; the correction is for the drive after them, so earlier
    steps are never re-corrected.
    """

    def __init__(
        self,
        prior_sigma: float,
        odometry_sigma_yaw: float,
        kernel_width: float = 3.0,
        max_bias: float = MAX_YAW_BIAS,
        min_loops: int = 2,
        significance: float = 2.0,
        reading_sigma: float | None = None,
    ) -> None:
        self.min_loops = min_loops
        self.significance = significance
        self.sigma = math.inf  # the estimate's standard deviation (rad/m), from the best loop and the prior
        self.estimate = 0.0  # the least-squares estimate; ``value`` is what is applied
        self.agreeing = 0
        self.prior_sigma = prior_sigma
        self.reading_sigma = prior_sigma if reading_sigma is None else reading_sigma  # chooses the valley
        self.odometry_sigma_yaw = odometry_sigma_yaw
        self.kernel_width = kernel_width
        self.max_bias = max_bias
        self.value = 0.0
        self.since: int | None = None  # the frame after which ``value`` is taken off (None: nothing is)
        # per frame, in order: index, path length and raw heading change so far (24 bytes a frame)
        self._frames = np.zeros(0, dtype=np.int64)
        self._travel = np.zeros((0, 2))
        self._size = 0
        self._raw: np.ndarray | None = None
        self._corrected: np.ndarray | None = None  # the corrected planar path at the last frame
        self._distance = 0.0
        self._turn = 0.0
        self._camera: tuple[float, float] | None = None  # the camera's estimate and its sigma (rad/m)
        self._turns: list[float] = []  # per loop: the raw odometry's turn less the loop's (rad, modulo a full turn)
        self._lengths: list[float] = []  # ...the path between its frames (m)
        self._variances: list[float] = []  # ...and the variance of that difference (rad^2)

    @property
    def loops(self) -> int:
        """Loops observed so far."""
        return len(self._turns)

    @property
    def residual_sigma(self) -> float:
        """The uncertainty (rad/m) of the bias left in the odometry once ``value`` is taken off."""
        return math.hypot(self.sigma, self.estimate - self.value)

    @property
    def uncorrected_sigma(self) -> float:
        """The root mean square (rad/m) of the bias in odometry steps nothing was taken off.

        The estimate and its uncertainty once the camera or ``min_loops`` agreeing loops measured
        it; ``reading_sigma``, the bias odometry is expected to have, before.
        """
        if self._camera is None and self.agreeing < self.min_loops:
            return self.reading_sigma
        return math.hypot(self.sigma, self.estimate)

    def camera(self, bias: float, sigma: float) -> None:
        """Take the camera's estimate of the bias as the prior (ignored while no more certain than the prior)."""
        if not (math.isfinite(bias) and math.isfinite(sigma) and 0.0 < sigma < self.prior_sigma):
            return
        if self._camera != (bias, sigma):
            self._camera = (bias, sigma)
            self._estimate()

    def correct(self, frame_index: int, odometry: np.ndarray) -> np.ndarray:
        """The frame's odometry pose with every step since the first frame turned by the bias then known.

        The correction turns the planar path (x, y, heading) about the vertical; height, roll and
        pitch stay the odometry's own.
        """
        if self._size and frame_index <= self._frames[self._size - 1]:
            last = int(self._frames[self._size - 1])
            raise ValueError(f"frame {frame_index} came after frame {last}: frame indices must increase")
        raw = np.asarray(odometry, dtype=np.float64)
        flat = pose_from_xy_yaw(*xy_yaw(raw))
        if self._raw is None or self._corrected is None:
            path = flat
        else:
            length = float(np.linalg.norm(raw[:3, 3] - self._raw[:3, 3]))
            step = invert(pose_from_xy_yaw(*xy_yaw(self._raw))) @ flat
            self._distance += length
            self._turn += xy_yaw(step)[2]
            path = self._corrected @ step @ pose_from_xy_yaw(0.0, 0.0, -self.value * length)
        self._raw, self._corrected = raw, path
        if self._size == len(self._frames):
            grown = max(64, 2 * self._size)
            self._frames = np.resize(self._frames, grown)
            self._travel = np.resize(self._travel, (grown, 2))
        self._frames[self._size] = frame_index
        self._travel[self._size] = (self._distance, self._turn)
        self._size += 1
        return path @ invert(flat) @ raw

    def _travelled(self, frame_index: int) -> np.ndarray | None:
        """Path length and raw heading change up to a corrected frame (None when it was never seen)."""
        k = int(np.searchsorted(self._frames[: self._size], frame_index))
        return self._travel[k] if k < self._size and self._frames[k] == frame_index else None

    def observe(self, frame_from: int, frame_to: int, loop_yaw: float, loop_yaw_variance: float) -> bool:
        """Add a loop: its relative yaw (frame_to in frame_from) and that yaw's variance; False for unknown frames."""
        start, end = self._travelled(frame_from), self._travelled(frame_to)
        if start is None or end is None:
            return False
        length = abs(end[0] - start[0])
        if length <= 0.0:
            return False
        self._turns.append(float(end[1] - start[1] - loop_yaw))
        self._lengths.append(length)
        self._variances.append(self.odometry_sigma_yaw**2 * length + max(float(loop_yaw_variance), 0.0))
        self._estimate()
        return True

    def _estimate(self) -> None:
        """The valley of least bounded cost, refined there by least squares with the prior and a Cauchy kernel."""
        raw, lengths, variances = np.array(self._turns), np.array(self._lengths), np.array(self._variances)
        mean, prior = self._camera or (0.0, self.prior_sigma)
        bias = self._valley(raw, lengths, variances)
        turns = bias * lengths + _wrap(raw - bias * lengths)  # each turn read the way that valley reads it
        for _ in range(20):
            whitened = (turns - bias * lengths) / np.sqrt(variances)
            weights = 1.0 / (1.0 + (whitened / self.kernel_width) ** 2)
            information = 1.0 / prior**2 + float(np.sum(weights * lengths**2 / variances))
            updated = (mean / prior**2 + float(np.sum(weights * turns * lengths / variances))) / information
            done = abs(updated - bias) < 1e-12
            bias = updated
            if done:
                break
        self.estimate = float(np.clip(bias, -self.max_bias, self.max_bias))
        whitened = (turns - self.estimate * lengths) / np.sqrt(variances)
        agree = np.abs(whitened) <= self.kernel_width
        self.agreeing = int(np.sum(agree))
        best = float(np.max(lengths[agree] ** 2 / variances[agree])) if self.agreeing else 0.0
        self.sigma = 1.0 / math.sqrt(1.0 / prior**2 + best)
        significant = abs(self.estimate) >= self.significance * self.sigma
        trusted = self.agreeing >= self.min_loops or self._camera is not None  # a lone loop may be false; the camera
        self.value = self.estimate if trusted and significant else 0.0
        if self.value == 0.0 and self._camera is None:
            self.since = None
        elif self.since is None and self._size:
            self.since = int(self._frames[self._size - 1])

    def _valley(self, raw: np.ndarray, lengths: np.ndarray, variances: np.ndarray) -> float:
        """The bias of least bounded cost on a grid over +-``max_bias``, each turn wrapped.

        The reading's prior is the camera's estimate when there is one, else zero with ``reading_sigma``.
        """
        mean, reading = self._camera or (0.0, self.reading_sigma)
        grid = np.linspace(-self.max_bias, self.max_bias, GRID)
        cost = 0.5 * ((grid - mean) / reading) ** 2
        if raw.size:
            residual = _wrap(raw[None, :] - grid[:, None] * lengths[None, :]) / np.sqrt(variances)[None, :]
            cost = cost + 0.5 * np.minimum(residual**2, self.kernel_width**2).sum(axis=1)
        return float(grid[int(np.argmin(cost))])


def with_heading_bias(odometry: np.ndarray, bias: float) -> np.ndarray:
    """Odometry poses (N, 4, 4) with every step since the first turned by ``-bias`` (rad/m) times its length."""
    fixed = HeadingBias(prior_sigma=1.0, odometry_sigma_yaw=1.0)
    fixed.value = bias
    return np.stack([fixed.correct(k, pose) for k, pose in enumerate(np.asarray(odometry, dtype=np.float64))])


def _wrap(angles: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into [-pi, pi)."""
    return (angles + math.pi) % (2.0 * math.pi) - math.pi


class ScaledOdometry:
    """Odometry whose steps' translations are multiplied by the scale factor known when each step is taken.

    The factor comes from ``odometry_scale`` (:mod:`sgf_plugins.odometry.scale`). Like the heading
    bias, a new factor corrects the steps that follow; earlier steps keep the factor of their time.
    Until a factor other than 1 arrives, the odometry passes through unchanged.
    """

    def __init__(self) -> None:
        self._raw: np.ndarray | None = None
        self._path: np.ndarray | None = None
        self.scaled = False

    def correct(self, odometry: np.ndarray, factor: float) -> np.ndarray:
        """The frame's odometry pose with every step's translation scaled by the factor of its time."""
        if not (math.isfinite(factor) and factor > 0.0):
            raise ValueError(f"an odometry scale factor must be finite and positive, got {factor!r}")
        raw = np.asarray(odometry, dtype=np.float64)
        self.scaled = self.scaled or factor != 1.0
        if self._raw is None or self._path is None or not self.scaled:
            path = raw
        else:
            step = invert(self._raw) @ raw
            step[:3, 3] *= factor
            path = self._path @ step
        self._raw, self._path = raw, path
        return path
