"""Eq. 10 matching of a query SGF against the groups the spatial gate lets it meet."""

from __future__ import annotations

import numpy as np

from sgf_pipeline.types import LookAlike, PoseEstimate, SgfDescriptor
from sgf_plugins.sgf.association.groups import GatedGroup, SgfGroup
from sgf_plugins.sgf.association.params import OnlineGroupsParams
from sgf_plugins.sgf.association.state import AssociationState
from sgf_plugins.shared.polar import best_shift, shift_to_yaw, shifted_distances, symmetry_spread


class Eq10Matching:
    """Eq. 10 between a query and the gated groups: their closest members, the shift, ties and look-alikes."""

    def __init__(self, params: OnlineGroupsParams, state: AssociationState) -> None:
        self.params = params
        self.state = state

    def prior_shift(self, query: SgfDescriptor, member: SgfDescriptor, estimate: PoseEstimate | None) -> float | None:
        """The column shift that the pose estimate predicts between two sightings (None for map members)."""
        if self.params.match.yaw_tolerance <= 0.0:
            return None
        return self.state.predicted_shift(query, member, estimate)

    def closable_ties(self, query: SgfDescriptor, candidates: list[GatedGroup], ties: np.ndarray) -> np.ndarray:
        """The tied groups a match could close a loop with: a shaped query leaves out the symmetric ones.

        A query whose own profile is not flat matched into a symmetric group (a round manhole
        whose closest member is flat) gives no loop factor. When it ties with a group it could
        close with (its own marking, ranked level by the position weight), that group takes it.
        """
        p = self.params
        if len(ties) < 2 or symmetry_spread(query.matrix, p.match.columns) < p.match.symmetry_threshold:
            return ties
        closable = [t for t in ties if not self.symmetric_match(query, candidates[t])]
        return np.asarray(closable, dtype=np.int64) if closable else ties

    def symmetric_match(self, query: SgfDescriptor, gated: GatedGroup) -> bool:
        """Whether a match of a shaped query into this gated group would be symmetric (its closest member flat)."""
        if not gated.group.symmetric:
            return False
        m, _ = self.nearest_member(query, gated.group)
        return (
            symmetry_spread(gated.group.members[m].matrix, self.params.match.columns)
            < self.params.match.symmetry_threshold
        )

    def closest_member(
        self, query: SgfDescriptor, group: SgfGroup, estimate: PoseEstimate | None
    ) -> tuple[int, SgfDescriptor, int]:
        """The group member closest to the query by eq. 10, its index, and the shift."""
        m, profile = self.nearest_member(query, group)
        matched = group.members[m]
        prior = None if group.anchors[m] is not None else self.prior_shift(query, matched, estimate)
        return m, matched, best_shift(profile, prior, self.params.match.yaw_tolerance)

    def nearest_member(self, query: SgfDescriptor, group: SgfGroup) -> tuple[int, np.ndarray]:
        """The index of the group member closest by eq. 10, and its shift profile."""
        p = self.params
        profiles = shifted_distances(query.matrix, group.matrices, p.match.columns, p.match.min_overlap)
        k = int(np.argmin(profiles.min(axis=1)))
        return k, profiles[k]

    def look_alike(self, query: SgfDescriptor, gated: GatedGroup, estimate: PoseEstimate | None) -> LookAlike:
        """A tied group's closest member, as an alternative match of the query."""
        _, matched, shift = self.closest_member(query, gated.group, estimate)
        return LookAlike(gated.group.group_id, matched, shift, shift_to_yaw(shift, query.matrix.shape[1]))
