"""Repeated patterns: neighbouring copies of one marking (give-way triangles, zebra bars, dashes)."""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.types import PoseEstimate, SgfDescriptor
from sgf_plugins.sgf.association.groups import GatedGroup
from sgf_plugins.sgf.association.state import AssociationState
from sgf_plugins.sgf.polar import shifted_distances


class RepeatedPattern(AssociationState):
    """The repeated-pattern test: members seen moments ago elsewhere, and whether the query looks like them.

    Give-way triangles, zebra bars and dashes repeat one marking metres apart: a group holding a
    member seen within ``repeat_window`` of travel at another place (beyond ``repeat_radius``,
    its ground footprint overlapping the query's by less than ``repeat_overlap``) that also looks
    like the query (``copy_distance``) is a neighbouring copy, not a revisit.
    """

    def _repeated(
        self,
        query: SgfDescriptor,
        estimate: PoseEstimate | None,
        travelled: np.ndarray,
        distance: np.ndarray,
        anchored: np.ndarray,
    ) -> np.ndarray:
        """Which members were seen moments ago at another place than the query (a partial view overlaps it)."""
        p, index = self.params, self._index
        repeated = ~anchored & (travelled < p.repeat_window) & (distance > p.repeat_radius)
        if p.repeat_overlap is not None and repeated.any():
            footprint = self._footprint(query, estimate)
            for k in np.flatnonzero(repeated):
                other = self._footprint(index.members[k], estimate)
                shared = len(footprint & other) / max(1, min(len(footprint), len(other)))
                repeated[k] = shared < p.repeat_overlap
        return repeated

    def _footprint(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> set[tuple[int, int]]:
        """The map cells (``footprint_cell`` wide) that a descriptor's ground points cover."""
        pose = self.map_pose(descriptor, estimate)
        xy = np.asarray(descriptor.points, dtype=np.float64)[:, :2] @ pose[:2, :2].T + pose[:2, 3]
        cells = np.floor(xy / self.params.footprint_cell).astype(np.int64)
        return set(map(tuple, cells.tolist()))

    def _copy_distances(self, query: SgfDescriptor, candidates: list[GatedGroup], eq10: np.ndarray) -> np.ndarray:
        """Eq. 10 from the query to each repeating group's members seen moments ago elsewhere (``copy_member``).

        Without ``copy_member``: the distance to the group (``eq10``), as the copy test had it before.
        """
        if not self.params.copy_member:
            return eq10
        out = np.full(len(candidates), math.inf)
        p = self.params
        for i, c in enumerate(candidates):
            if c.repeating is not None and len(c.repeating):  # set for repeated groups only
                profiles = shifted_distances(query.matrix, c.group.matrices[c.repeating], p.columns, p.min_overlap)
                out[i] = float(profiles.min())
        return out
