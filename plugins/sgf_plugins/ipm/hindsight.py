"""The ground ahead of a frame as the robot later drove over it (``ipm=mc_hindsight``, extension of Sec. III-A).

No pose before a frame knows the grade of the ground its BEV shows (0.5 to 5.6 m ahead): at the
foot or the crest of a hill it differs from the grade under the robot. A few seconds later the
robot has driven over that ground, and its odometry and IMU have measured it. Given the path
driven after the frame (:class:`~sgf_pipeline.types.PathAhead`, read ahead by the runner), this
module fits the plane the BEV is given:

* heights: the path's points in the frame's horizontal heading frame, ``x`` metres ahead and
  ``z`` up (the IMU's pitch integrated over the odometry's steps, so a planar odometry works
  too; the odometry's own heights when a path frame lacks an IMU attitude);
* grade: the least-squares slope ``a`` of ``z = a x`` through the ground under the robot, over
  the path points within the BEV's reach (the plane passes under the robot, as in eq. 2);
* roll: the median IMU roll of the frames driven within the BEV's reach (a cross slope tilts
  the robot by its own angle);
* the robot's own attitude against that ground: the median IMU attitude of the frames within
  ``window`` metres on either side (noise and bumps averaged out), plus the frame's deviation from
  it shrunk as ``d^3 / (d^2 + sigma^2)`` (the IMU's noise mostly dropped, a bump's pitch kept).

A constant IMU bias tilts the measured path and the robot alike and cancels in the difference.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from sgf_pipeline.types import PathAhead

#: Path points nearer than this (m ahead) carry no grade: ``z / x`` there is all noise.
MIN_AHEAD = 0.2


@dataclass(frozen=True)
class GroundAhead:
    """The plane fitted to the path driven after a frame: grade (rise over run), roll (rad), reach (m)."""

    grade: float
    roll: float | None
    reach: float
    points: int

    @property
    def pitch(self) -> float:
        """The pitch (rad, nose down positive, as the IMU's) a robot standing on this plane would have."""
        return -math.atan(self.grade)


def _heading(pose: np.ndarray) -> tuple[float, float]:
    """Cosine and sine of a pose's heading (the yaw of its forward axis)."""
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    return math.cos(yaw), math.sin(yaw)


def path_profile(pose: np.ndarray, path: PathAhead) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per path frame: metres driven since ``pose``, metres ahead in its heading, and height above it.

    Heights integrate ``-sin(pitch)`` of the IMU over each step (the pitch is nose down positive);
    when a path frame has no IMU attitude, the odometry's own heights are used for the whole path.
    """
    positions = np.concatenate([pose[None, :3, 3], path.odometry[:, :3, 3]])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    driven = np.cumsum(steps)
    c, s = _heading(pose)
    relative = positions[1:] - positions[0]
    ahead = c * relative[:, 0] + s * relative[:, 1]
    pitch = path.imu_roll_pitch[:, 1]
    if np.all(np.isfinite(pitch)):
        height = np.cumsum(-np.sin(pitch) * steps)
    else:
        height = relative[:, 2]
    return driven, ahead, height


def ground_ahead(
    pose: np.ndarray,
    path: PathAhead,
    near: float,
    far: float,
    min_reach: float = 2.0,
    min_points: int = 5,
    profile: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> GroundAhead | None:
    """The plane of the ground from ``near`` to ``far`` metres ahead of ``pose``, from the path driven after it.

    ``None`` when the path does not reach ``min_reach`` metres ahead within the BEV (the robot
    turned away, stopped or the sequence ended), or has fewer than ``min_points`` points there.
    ``profile``: :func:`path_profile` of ``pose`` and ``path`` when the caller has it already.
    """
    if len(path) == 0:
        return None
    driven, ahead, height = path_profile(pose, path) if profile is None else profile
    beyond = np.flatnonzero(ahead > far)
    end = int(beyond[0]) if beyond.size else len(ahead)  # the path leaves the BEV: what follows is elsewhere
    x, z = ahead[:end], height[:end]
    use = x >= MIN_AHEAD
    if use.sum() < max(min_points, 1) or float(x[use].max()) < min_reach:
        return None
    x, z = x[use], z[use]
    grade = float((x * z).sum() / (x * x).sum())
    rolls = path.imu_roll_pitch[:, 0][(driven >= near) & (driven <= far)]
    rolls = rolls[np.isfinite(rolls)]
    roll = float(np.median(rolls)) if rolls.size >= 3 else None
    return GroundAhead(grade, roll, float(x.max()), int(use.sum()))


class AttitudeWindow:
    """The IMU attitudes of every frame along the path, by metres driven, for a median around a frame.

    The runner's read-ahead gives each keyframe the frames after it; kept here, they also serve
    the keyframes that follow as the frames behind them.
    """

    def __init__(self, half_width: float) -> None:
        if half_width <= 0.0:
            raise ValueError(f"the attitude window's half width must be positive, got {half_width}")
        self.half_width = half_width
        self._samples: deque[tuple[float, float, float]] = deque()  # (metres driven, roll, pitch)

    def reset(self) -> None:
        """Forget every sample."""
        self._samples.clear()

    def add(self, travelled: float, roll: float, pitch: float) -> None:
        """A frame's attitude, ``travelled`` metres along the path (kept only when past the newest sample)."""
        if not (math.isfinite(roll) and math.isfinite(pitch)):
            return
        if self._samples and travelled <= self._samples[-1][0] + 1e-6:
            return
        self._samples.append((travelled, roll, pitch))

    def median(self, travelled: float) -> tuple[float, float] | None:
        """Median roll and pitch of the samples within the half width of ``travelled`` (older ones are dropped)."""
        while self._samples and self._samples[0][0] < travelled - self.half_width:
            self._samples.popleft()
        near = [(r, p) for s, r, p in self._samples if abs(s - travelled) <= self.half_width]
        if not near:
            return None
        values = np.asarray(near)
        return float(np.median(values[:, 0])), float(np.median(values[:, 1]))
