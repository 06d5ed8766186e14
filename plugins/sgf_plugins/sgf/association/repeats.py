"""Repeated patterns: neighbouring copies of one marking (give-way triangles, zebra bars, dashes)."""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.types import PoseEstimate, SgfDescriptor
from sgf_plugins.sgf.association.groups import GatedGroup
from sgf_plugins.sgf.association.params import OnlineGroupsParams
from sgf_plugins.sgf.association.state import AssociationState
from sgf_plugins.shared.polar import shifted_distances


class RepeatedPattern:
    """The repeated-pattern test: members seen moments ago elsewhere, and whether the query looks like them.

    Give-way triangles, zebra bars and dashes repeat one marking metres apart: a group holding a
    member seen within ``repeats.window`` of travel at another place (beyond ``repeats.radius``)
    that also looks like the query (``repeats.copy_distance``) is a neighbouring copy, not a revisit.
    """

    def __init__(self, params: OnlineGroupsParams, state: AssociationState) -> None:
        self.params = params
        self.state = state

    def repeated(
        self,
        query: SgfDescriptor,
        estimate: PoseEstimate | None,
        travelled: np.ndarray,
        distance: np.ndarray,
        anchored: np.ndarray,
    ) -> np.ndarray:
        """Which members were seen moments ago at another place than the query."""
        p = self.params
        return ~anchored & (travelled < p.repeats.window) & (distance > p.repeats.radius)

    def copy_distances(self, query: SgfDescriptor, candidates: list[GatedGroup], eq10: np.ndarray) -> np.ndarray:
        """Eq. 10 from the query to each repeating group's members seen moments ago elsewhere (``repeats.copy_member``).

        Without ``repeats.copy_member``: the distance to the group (``eq10``).
        """
        if not self.params.repeats.copy_member:
            return eq10
        out = np.full(len(candidates), math.inf)
        p = self.params
        for i, c in enumerate(candidates):
            if c.repeating is not None and len(c.repeating):  # set for repeated groups only
                profiles = shifted_distances(
                    query.matrix, c.group.matrices[c.repeating], p.match.columns, p.match.min_overlap
                )
                out[i] = float(profiles.min())
        return out
