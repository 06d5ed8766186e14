"""Anchoring: the accepted loops the estimate has absorbed, the distance since them, and a prior map's anchor.

The gate's drift grows with ``d``, the shortest odometry path between the two frames of a match
in a graph where each accepted loop that the estimate satisfies (the back-end has absorbed it)
joins its two frames at no cost; a loop that the back-end did not absorb (``backend=none``, batch
optimisation only at the end, a loop down-weighted by the robust kernel) anchors nothing, so the
gate stays as loose as the dead-reckoned drift. The heading bias in the drift is the back-end's
model of it, the random walks and scale error the camera's measurement of them where it has one
(:mod:`sgf_plugins.shared.drift`).

On a prior SGF map (``matched`` is a :class:`~sgf_pipeline.sgf_map.MapDescriptor`), a match is
an inter-session constraint (``from_map``). Before the run is anchored in the map frame there is
no prediction: the first ``map.anchor_matches`` matches of different map groups must agree with
each other (the map-implied relative pose between their frames against the run's own estimate,
same test); afterwards map matches are gated like loops, the map acting as one anchored node.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from sgf_pipeline.geometry import invert
from sgf_pipeline.types import PoseEstimate
from sgf_plugins.loop.candidate import Candidate
from sgf_plugins.loop.params import GateParams, MapParams
from sgf_plugins.shared.anchoring import anchored_distances
from sgf_plugins.shared.drift import (
    EXPECTED_YAW_BIAS,
    corrected_yaw_bias,
    drift_covariance,
    mahalanobis2,
    measured_sigmas,
    pose_error,
    uncorrected_yaw_bias,
)
from sgf_plugins.shared.frame_log import FrameLog

MAP = -1  # the prior map as one node of the anchoring graph


class LoopAnchoring:
    """The accepted loops and the map matches held back, and what they anchor in the estimate."""

    def __init__(self, frames: FrameLog, gate: GateParams, prior_map: MapParams, threshold: float) -> None:
        self.frames = frames
        self.p = gate
        self.map = prior_map
        self.threshold = threshold  # the gate's chi-square bound (3 dof)
        self.accepted: list[Candidate] = []
        self.pending: list[Candidate] = []  # map matches waiting for the run's anchoring in the map
        # the absorbed constraints for one estimate (a snapshot: held, so its identity is not reused) and count
        self._absorbed_for: PoseEstimate | None = None
        self._absorbed_count = -1
        self._absorbed_cache: list[Candidate] = []

    def pose(self, k: int, estimate: PoseEstimate | None) -> np.ndarray:
        """Frame ``k``'s pose in the estimate (dead-reckoned past its newest frame), or its odometry."""
        if estimate is None:
            return self.frames.odometry(k)
        if k in estimate.poses:
            return np.asarray(estimate.poses[k])
        last = estimate.frame_index
        return np.asarray(estimate.poses[last]) @ invert(self.frames.odometry(last)) @ self.frames.odometry(k)

    def drift(self, distance: float, newest: int, estimate: PoseEstimate | None) -> np.ndarray:
        """The gate's drift covariance across ``distance`` m since the last anchor up to frame ``newest``.

        The heading bias counted is the uncertainty of the bias left when the back-end corrected the
        odometry over all of that (the drive from its ``since`` frame to ``newest``), else the bias
        as the back-end's model holds it.
        """
        sigmas = measured_sigmas(self.p, estimate)
        if not self.p.bias_from_backend:
            return drift_covariance(distance, sigmas, EXPECTED_YAW_BIAS)
        bias = uncorrected_yaw_bias(estimate)
        corrected = corrected_yaw_bias(estimate)
        if corrected is not None:
            start = self.frames.get_distance(corrected[0])
            if start is not None and self.frames.distance(newest) - start >= distance:
                bias = corrected[1]
        return drift_covariance(distance, sigmas, bias)

    def absorbed_loops(self, estimate: PoseEstimate | None) -> list[Candidate]:
        """The accepted constraints the estimate satisfies; kept while the estimate and the accepted list stay."""
        if self._absorbed_for is not estimate or self._absorbed_count != len(self.accepted) or estimate is None:
            self._absorbed_for, self._absorbed_count = estimate, len(self.accepted)
            # a position-only loop fixes no heading: the drift since it is not reset
            self._absorbed_cache = [
                c for c in self.accepted if not c.constraint.position_only and self.absorbed(c, estimate)
            ]
        return self._absorbed_cache

    def absorbed(self, c: Candidate, estimate: PoseEstimate | None) -> bool:
        """Whether the estimate satisfies an accepted constraint (so it anchors its two frames)."""
        if estimate is None:
            return False
        k = c.constraint
        start = c.map_pose if k.from_map else self.pose(k.frame_from, estimate)
        assert start is not None
        predicted = invert(start) @ self.pose(k.frame_to, estimate)
        cov = k.covariance + drift_covariance(0.0, self.p)
        return mahalanobis2(pose_error(predicted, k.relative), cov) <= self.threshold

    def map_anchored(self, estimate: PoseEstimate | None) -> bool:
        """Whether the estimate is in the map frame (it satisfies an accepted map constraint)."""
        return any(c.constraint.from_map for c in self.absorbed_loops(estimate))

    def anchored_distance(self, a: int, b: int, estimate: PoseEstimate | None) -> float:
        """Path distance from ``a`` to ``b`` where absorbed loops (and the map) join frames at no cost."""
        shortcuts: list[tuple[float, float]] = []
        on_map: list[float] = []  # frames anchored in the map are all joined through it
        for c in self.absorbed_loops(estimate):
            k = c.constraint
            if k.from_map:
                on_map.append(self.frames.distance(k.frame_to))
            else:
                shortcuts.append((self.frames.distance(k.frame_from), self.frames.distance(k.frame_to)))
        on_map.sort()
        shortcuts.extend(itertools.pairwise(on_map))
        if a == MAP:
            if not on_map:
                return math.inf
            start = on_map[0]
        else:
            start = self.frames.distance(a)
        return float(anchored_distances(start, np.array([self.frames.distance(b)]), shortcuts)[0])

    def agree(self, first: Candidate, second: Candidate, estimate: PoseEstimate | None) -> bool:
        """Whether two map matches imply the run's relative pose between their frames, as the estimate has it."""
        a, b = first.constraint, second.constraint
        assert first.map_pose is not None and second.map_pose is not None
        from_map = invert(first.map_pose @ a.relative) @ (second.map_pose @ b.relative)
        own = invert(self.pose(a.frame_to, estimate)) @ self.pose(b.frame_to, estimate)
        distance = self.anchored_distance(a.frame_to, b.frame_to, estimate)
        cov = a.covariance + b.covariance + self.drift(distance, max(a.frame_to, b.frame_to), estimate)
        return mahalanobis2(pose_error(own, from_map), cov) <= self.threshold

    def confirm_map(self, candidate: Candidate, estimate: PoseEstimate | None) -> list[Candidate]:
        """Hold map matches until enough of them (different groups) agree on where the run is in the map.

        The matches this one confirms, itself last (accepted now); none while they are held.
        """
        agreeing = [q for q in self.pending if q.group_id != candidate.group_id and self.agree(q, candidate, estimate)]
        if len(agreeing) + 1 < self.map.anchor_matches:
            self.pending = [*self.pending, candidate][-self.map.pending :]
            return []
        confirmed = [*agreeing, candidate]
        self.pending = [q for q in self.pending if all(q is not c for c in confirmed)]
        self.accepted.extend(confirmed)
        return confirmed
