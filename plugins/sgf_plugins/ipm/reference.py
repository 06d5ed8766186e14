"""The reference attitude of MC-IPM: a robust average over a queue of the last N poses (paper Sec. III-A)."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

ReferenceCenter = Literal["median", "mean"]
#: A line needs this many inlier poses spread over at least this many metres (else the mean is used).
MIN_LINE_POSES = 10
MIN_LINE_SPAN = 1.0
ReferenceFit = Literal["mean", "line"]


@dataclass(frozen=True)
class ReferenceAttitude:
    """The reference roll and pitch (rad), how many queued poses were averaged into it, and the ground ahead.

    ``pitch`` is the ground's pitch under the robot; ``ahead_pitch`` the pitch of the ground
    ``lookahead`` metres further on (the same as ``pitch`` unless the queue fits a line).
    """

    roll: float
    pitch: float
    inliers: int
    queued: int
    ahead_pitch: float | None = None

    @property
    def target_pitch(self) -> float:
        """The pitch the BEV's ground plane is given: the ground ahead when known, else the reference."""
        return self.pitch if self.ahead_pitch is None else self.ahead_pitch


class PoseQueue:
    """The last ``size`` attitudes and their average without pitch outliers (paper: N=50, d_theta=0.025 rad).

    The paper stores N poses, averages them, and leaves out of the average the poses whose pitch
    differs by more than ``d_theta`` -- from what, it does not say. Here that is a choice
    (``center``), and the steps are:

    1. push the current ``(roll, pitch)``; the queue keeps the last ``size`` of them;
    2. centre ``c``: the median of the queued pitches (``median``, default), or their mean (``mean``,
       the literal "average, then exclude" reading, which a long slope drags between two levels);
    3. inliers: the queued poses with ``|pitch - c| <= pitch_threshold`` (and, when
       ``roll_threshold`` is set, ``|roll - median roll| <= roll_threshold``);
    4. reference: the mean roll and mean pitch of the inliers (the centre itself if none).

    With the median, a disturbance shorter than half the queue (a speed bump, a crack) never moves
    the reference: its poses are outliers and the relative pitch is the bump's own. A slope that
    lasts longer than half the queue becomes the majority: the centre jumps to it, the flat poses
    become the outliers, and the reference follows the slope, so a constant slope is not
    compensated away. The transition takes ``size // 2 + 1`` poses.

    ``fit="line"`` (an extension; ``"mean"`` is the paper): the queue also keeps the distance
    travelled at each pose, and step 4 fits a straight line ``pitch = a + b s`` to the inliers
    (then once more to the poses within ``pitch_threshold`` of that line). The ground under the
    robot is the line at the current distance, and the ground ahead the line ``lookahead``
    metres on (``ahead_pitch``). On a hill, whose grade changes over metres, the mean of the last
    N poses lags behind the ground under the robot by half a queue and tells nothing of the ground
    ahead that the BEV shows; the line follows the change and extrapolates it. The change over
    the lookahead is bounded by ``pitch_threshold``, so a wrong fit cannot tilt the BEV by more.

    ``settle`` (an extension, off by default): when the last ``settle`` pitches agree with one
    another within ``pitch_threshold`` but lie more than ``pitch_threshold`` from the centre of
    the older poses, the attitude has settled at a new level -- the robot is on a slope, not on a
    bump, whose pitch rises and falls -- and the older poses are dropped, so the reference follows
    the slope after ``settle`` poses instead of ``size // 2 + 1``.
    """

    def __init__(
        self,
        size: int = 50,
        pitch_threshold: float = 0.025,
        center: ReferenceCenter = "median",
        roll_threshold: float | None = None,
        settle: int | None = None,
        fit: ReferenceFit = "mean",
        lookahead: float = 0.0,
    ) -> None:
        if size < 1:
            raise ValueError(f"the pose queue needs at least one pose, got size={size}")
        self.size = size
        self.pitch_threshold = pitch_threshold
        self.center = center
        self.roll_threshold = roll_threshold
        if settle is not None and not 1 <= settle < size:
            raise ValueError(f"settle must lie in [1, size), got settle={settle} with size={size}")
        self.settle = settle
        if lookahead < 0.0 or (lookahead > 0.0 and fit != "line"):
            raise ValueError(f"lookahead must be >= 0 and needs fit='line', got lookahead={lookahead} with fit={fit!r}")
        self.fit = fit
        self.lookahead = lookahead
        self._poses: deque[tuple[float, float]] = deque(maxlen=size)
        self._distances: deque[float] = deque(maxlen=size)
        self._travelled = 0.0

    def __len__(self) -> int:
        return len(self._poses)

    @property
    def travelled(self) -> float:
        """Metres driven over the steps pushed since the last reset."""
        return self._travelled

    def reset(self) -> None:
        """Forget every queued pose."""
        self._poses.clear()
        self._distances.clear()
        self._travelled = 0.0

    def push(self, roll: float, pitch: float, step: float = 0.0) -> None:
        """Append the current attitude, ``step`` metres on from the previous one (the oldest leaves a full queue)."""
        if math.isfinite(step) and step > 0.0:
            self._travelled += step
        self._poses.append((float(roll), float(pitch)))
        self._distances.append(self._travelled)
        k = self.settle
        if k is None or len(self._poses) <= k:
            return
        pitches = np.fromiter((p for _, p in self._poses), dtype=np.float64)
        recent, older = pitches[-k:], pitches[:-k]
        if np.ptp(recent) <= self.pitch_threshold and abs(recent.mean() - np.median(older)) > self.pitch_threshold:
            for _ in range(len(older)):
                self._poses.popleft()
                self._distances.popleft()

    def reference(self) -> ReferenceAttitude:
        """The robust average attitude of the queue (steps 2-4 of the class docstring)."""
        if not self._poses:
            raise ValueError("the pose queue is empty: push the current attitude first")
        poses = np.asarray(self._poses, dtype=np.float64)
        rolls, pitches = poses[:, 0], poses[:, 1]
        center = float(np.median(pitches)) if self.center == "median" else float(pitches.mean())
        keep = np.abs(pitches - center) <= self.pitch_threshold
        if self.roll_threshold is not None:
            keep &= np.abs(rolls - np.median(rolls)) <= self.roll_threshold
        count = int(keep.sum())
        if count == 0:
            return ReferenceAttitude(float(np.median(rolls)), center, 0, len(poses))
        roll = float(rolls[keep].mean())
        if self.fit == "mean":
            return ReferenceAttitude(roll, float(pitches[keep].mean()), count, len(poses))
        return self._line(roll, pitches, keep)

    def _line(self, roll: float, pitches: np.ndarray, keep: np.ndarray) -> ReferenceAttitude:
        """Step 4 with ``fit="line"``: the ground's pitch under the robot and ``lookahead`` metres ahead."""
        s = np.asarray(self._distances, dtype=np.float64) - self._travelled  # <= 0: metres behind the robot
        slope, here = 0.0, float(pitches[keep].mean())
        for _ in range(2):
            if keep.sum() < MIN_LINE_POSES or np.ptp(s[keep]) < MIN_LINE_SPAN:
                break  # too few poses or too short a stretch for a slope: the mean, as in the paper
            slope, here = np.polyfit(s[keep], pitches[keep], 1)
            keep = np.abs(pitches - (here + slope * s)) <= self.pitch_threshold
            if not keep.any():
                break
        change = float(np.clip(slope * self.lookahead, -self.pitch_threshold, self.pitch_threshold))
        return ReferenceAttitude(roll, float(here), int(keep.sum()), len(pitches), float(here) + change)
