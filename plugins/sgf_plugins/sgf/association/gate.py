"""The spatial gate of the online SGF grouping and its drift radius."""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.types import PoseEstimate, SgfDescriptor
from sgf_plugins.sgf.association.groups import NO_ESTIMATE, GatedGroup
from sgf_plugins.sgf.association.params import OnlineGroupsParams
from sgf_plugins.sgf.association.repeats import RepeatedPattern
from sgf_plugins.sgf.association.state import AssociationState
from sgf_plugins.shared.anchoring import anchored_distances
from sgf_plugins.shared.drift import EXPECTED_YAW_BIAS, bias_growth, drift_radius

#: A loop anchors the gate when the estimate's relative yaw between its frames is within this of the loop's (rad).
ANCHOR_YAW_TOLERANCE = 0.05


class SpatialGate:
    """The spatial gate: the groups with a member near the query on the map, its radius growing with drift.

    The radius between two sightings is ``gate.radius + gate.drift_rate * d + q * d^2`` for the
    distance ``d`` travelled between them (:meth:`radius`), with the heading-bias term ``q``
    (:meth:`quadratic`, :meth:`per_bias`); with ``gate.anchored``, ``d`` restarts at the loop
    closures the estimate satisfies (:meth:`anchoring`).
    """

    def __init__(self, params: OnlineGroupsParams, state: AssociationState, repeats: RepeatedPattern) -> None:
        self.params = params
        self.state = state
        self.repeats = repeats
        self.reset()

    def reset(self) -> None:
        """Forget the anchoring cache (a new sequence)."""
        self._shortcuts: tuple[object, list[tuple[float, float]]] = (NO_ESTIMATE, [])

    def gated(self, query: SgfDescriptor, estimate: PoseEstimate | None) -> list[GatedGroup]:
        """The groups the spatial gate lets the query meet, with their nearest member's map distance (m).

        ``repeated`` marks a group holding a member seen moments ago (within ``repeats.window`` of
        travel) at another place (beyond ``repeats.radius``): if it also looks like the query, the
        two are neighbouring copies of a repeated pattern (see the stage's ``assign``).
        """
        p, index = self.params, self.state.index
        n = index.size
        if n == 0:
            return []
        here = self.state.position_of(query, estimate)
        distance = np.hypot(*(self.state.member_positions(estimate) - here).T)
        anchored = ~np.isnan(index.anchor[:n, 0])
        # Distance travelled between the two sightings; straight-line odometry distance where unknown.
        since = self.state.frames.get_distance(query.sgf.frame_index)
        travelled = np.abs(index.travelled[:n] - since) if since is not None else np.full(n, np.nan)
        unknown = np.isnan(travelled)
        if unknown.any():
            odometry = np.asarray(query.sgf.odometry, dtype=np.float64)[:3, 3]
            travelled[unknown] = np.linalg.norm(index.odometry[:n][unknown, :3, 3] - odometry, axis=1)
        repeated = self.repeats.repeated(query, estimate, travelled, distance, anchored)
        if p.gate.anchored and since is not None:
            shortcuts = self.anchoring(estimate)
            if shortcuts:
                known = ~unknown
                travelled[known] = anchored_distances(since, index.travelled[:n][known], shortcuts)
        radius = self.radius(travelled, self.quadratic())
        radius[anchored] = math.inf if p.gate.prior_radius is None else p.gate.prior_radius
        groups = index.group[:n]
        count = len(self.state.groups)
        member_inside = (distance <= radius) | (not p.gate.enabled)
        nearest = np.full(count, math.inf)
        np.minimum.at(nearest, groups, distance)
        ratio = np.full(count, math.inf)
        np.minimum.at(ratio, groups, distance / radius)
        inside = np.bincount(groups, weights=member_inside, minlength=count) > 0
        repeats = np.bincount(groups, weights=repeated, minlength=count) > 0
        repeating: list[np.ndarray | None] = [None] * count
        if (repeats & inside).any():
            # members sit in the index in the order they joined their group: rank within the group = member index
            order = np.argsort(groups, kind="stable")
            starts = np.concatenate([[0], np.cumsum(np.bincount(groups, minlength=count))[:-1]])
            rank = np.arange(n) - starts[groups[order]]  # of each member, in ``order``

            def per_group(flags: np.ndarray) -> list[np.ndarray]:
                kept = flags[order]
                return np.split(rank[kept], np.cumsum(np.bincount(groups[order][kept], minlength=count))[:-1])

            repeating = [r if repeats[k] else None for k, r in enumerate(per_group(repeated))]
        return [
            GatedGroup(group, float(nearest[k]), bool(repeats[k]), float(min(ratio[k], 1.0)), repeating[k])
            for k, group in enumerate(self.state.groups)
            if inside[k]
        ]

    def anchoring(self, estimate: PoseEstimate | None) -> list[tuple[float, float]]:
        """Travelled distances of the two frames of each loop closure the estimate satisfies (cached per estimate).

        A loop the back-end has not absorbed (no back-end, a loop down-weighted by the robust kernel)
        anchors nothing: between its frames the estimate may still carry the whole drift.
        """
        if estimate is None or not self.state.closures:
            return []
        if self._shortcuts[0] is estimate:
            return self._shortcuts[1]
        tolerance = self.params.gate.anchor_tolerance
        shortcuts = []
        for c in self.state.closures:
            start, end = estimate.poses.get(c.frame_from), estimate.poses.get(c.frame_to)
            if start is None or end is None:
                continue
            error = invert(c.relative) @ invert(np.asarray(start)) @ np.asarray(end)
            if math.hypot(error[0, 3], error[1, 3]) <= tolerance and abs(xy_yaw(error)[2]) <= ANCHOR_YAW_TOLERANCE:
                shortcuts.append((c.travelled_from, c.travelled_to))
        self._shortcuts = (estimate, shortcuts)
        return shortcuts

    def per_bias(self, bias: float) -> float:
        """The gate's growth per squared metre for a heading bias (rad/m): ``gate.drift_bias_share`` of 0.5 b."""
        return bias_growth(bias, self.params.gate.drift_bias_share)

    def radius(self, travelled: np.ndarray, quadratic: float) -> np.ndarray:
        """The spatial gate's radius (m) for the distances travelled between two sightings.

        ``quadratic``: the heading bias term (:meth:`quadratic`).
        """
        return drift_radius(travelled, self.params.gate.radius, self.params.gate.drift_rate, quadratic)

    def quadratic(self) -> float:
        """The gate's heading bias term: the bias wheel odometry is expected to have (``EXPECTED_YAW_BIAS``)."""
        return self.per_bias(EXPECTED_YAW_BIAS)
