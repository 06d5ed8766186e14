"""The end of the run: groups split and merged by the final estimate."""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.types import PoseEstimate
from sgf_plugins.sgf.association.gate import SpatialGate
from sgf_plugins.sgf.association.groups import SgfGroup
from sgf_plugins.sgf.association.params import OnlineGroupsParams
from sgf_plugins.sgf.association.state import AssociationState
from sgf_plugins.shared.anchoring import anchored_distances
from sgf_plugins.shared.polar import shifted_distances


class EndOfRun:
    """The split and merge of the groups at the end of the run, by the final estimate and the spatial gate."""

    def __init__(self, params: OnlineGroupsParams, state: AssociationState, gate: SpatialGate) -> None:
        self.params = params
        self.state = state
        self.gate = gate

    def split_groups(self, estimate: PoseEstimate | None) -> int:
        """Split each group into the parts the estimate puts within the spatial gate of each other; new groups made.

        Two members may stay together when their map distance is within the gate radius of the
        (anchored) distance travelled between their sightings; a part holds members that may all
        stay together (:meth:`parts`). Early in a run, before any loop, the gate is tens of metres wide and identical
        standard markings at different places (stop lines, chevrons) can join one group; once
        loops have corrected the estimate, their members lie far apart and the group is split:
        the part holding its first member keeps its id, the others get new ids. Groups seeded
        from a map are left alone.
        """
        index = self.state.index
        if not self.state.groups or index.size == 0:
            return 0
        positions = self.state.member_positions(estimate)
        shortcuts = self.gate.anchoring(estimate) if self.params.gate.anchored else []
        rows = np.arange(index.size)
        made = 0
        for slot, group in enumerate(list(self.state.groups)):
            mine = rows[index.group[: index.size] == slot]
            if len(mine) < 2 or any(a is not None for a in group.anchors) or np.isnan(index.travelled[mine]).any():
                continue
            parts = self.parts(positions[mine], index.travelled[mine], shortcuts)
            if parts.max() == 0:
                continue
            keep = parts == 0  # holds the first member, whose offset (the group's orientation) is 0
            for label in range(1, int(parts.max()) + 1):
                taken = np.flatnonzero(parts == label)
                new = SgfGroup(self.state.next_id, aliased=group.aliased)
                self.state.next_id += 1
                base = group.offsets[taken[0]]
                for k in taken:
                    new.add(group.members[k], group.offsets[k] - base)
                new.refresh(self.params.match.columns, self.params.match.symmetry_threshold)
                self.state.slot[new.group_id] = len(self.state.groups)
                index.group[mine[taken]] = len(self.state.groups)
                self.state.groups.append(new)
                made += 1
            group.members = [m for m, k in zip(group.members, keep, strict=True) if k]
            group.offsets = [o for o, k in zip(group.offsets, keep, strict=True) if k]
            group.anchors = [a for a, k in zip(group.anchors, keep, strict=True) if k]
            group.refresh(self.params.match.columns, self.params.match.symmetry_threshold)
        return made

    def merge_groups(self, estimate: PoseEstimate | None) -> int:
        """Merge groups whose members the estimate puts at one place and that look alike there; merges made.

        The counterpart of :meth:`split_groups`: a revisit seen before any loop, while the gate
        reached several look-alike markings (a dash, a tactile bar), may have joined the wrong one's
        group and been split off at the end. Candidates are member pairs of two groups within
        ``end.merge_radius`` on the map whose eq. 10 distance, at the column shift the estimate
        predicts (within ``end.merge_yaw_deg``; any shift when both groups are symmetric), is at most
        ``end.merge_distance``. The closest pairs merge first, and only when every member of the
        merged group stays within the spatial gate of every other (the split would not undo it)
        and no two of the groups' members were seen within ``repeats.window`` of travel (one
        drive-by: two copies of a repeated pattern, kept apart online).
        Groups seeded from a map are left alone.
        """
        from scipy.spatial import cKDTree

        p, index = self.params, self.state.index
        n = index.size
        if len(self.state.groups) < 2 or n < 2:
            return 0
        positions = self.state.member_positions(estimate)
        slots = index.group[:n].copy()
        free = np.array([all(a is None for a in g.anchors) for g in self.state.groups])
        rows = np.flatnonzero(free[slots] & ~np.isnan(index.travelled[:n]))
        if len(rows) < 2:
            return 0
        near = cKDTree(positions[rows]).query_pairs(p.end.merge_radius, output_type="ndarray")
        first, second = rows[near[:, 0]], rows[near[:, 1]]
        apart = slots[first] != slots[second]
        member_at = np.zeros(n, dtype=np.int64)  # a row's index among its group's members (rows keep member order)
        for slot in np.unique(slots):
            member_at[slots == slot] = np.arange(int((slots == slot).sum()))
        candidates: list[tuple[float, int, int, int]] = []
        n_s = index.members[0].matrix.shape[1]
        window = round(math.radians(p.end.merge_yaw_deg) * n_s / (2.0 * math.pi))
        for a, b in zip(first[apart].tolist(), second[apart].tolist(), strict=True):
            if index.frame[b] < index.frame[a]:
                a, b = b, a
            ga, gb = self.state.groups[slots[a]], self.state.groups[slots[b]]
            if ga.symmetric != gb.symmetric:
                continue
            profile = shifted_distances(index.members[b].matrix, index.members[a].matrix[None], p.match.columns)[0]
            if not ga.symmetric:
                predicted = round(self.state.predicted_shift(index.members[b], index.members[a], estimate))
                allowed = np.full(n_s, np.inf)
                shifts = np.arange(predicted - window, predicted + window + 1) % n_s
                allowed[shifts] = profile[shifts]
                profile = allowed
            shift = int(np.argmin(profile))
            if profile[shift] <= p.end.merge_distance:
                candidates.append((float(profile[shift]), a, b, shift))
        shortcuts = self.gate.anchoring(estimate) if p.gate.anchored else []
        made = 0
        for _, a, b, shift in sorted(candidates):
            sa, sb = int(slots[a]), int(slots[b])
            if sa == sb:
                continue
            in_a, in_b = slots == sa, slots == sb
            both = np.flatnonzero(in_a | in_b)
            seen_a, seen_b = index.travelled[:n][in_a], index.travelled[:n][in_b]
            if np.abs(seen_a[:, None] - seen_b[None, :]).min() < p.repeats.window:
                continue  # seen on one drive-by: two markings (a repeated pattern's copies), not a revisit
            if self.parts(positions[both], index.travelled[both], shortcuts).max() > 0:
                continue
            ga, gb = self.state.groups[sa], self.state.groups[sb]
            # Member b turned by ``shift`` lies on member a: B's members turn into A's orientation so.
            rebase = shift + ga.offsets[member_at[a]] - gb.offsets[member_at[b]]
            members = [(ga if slots[r] == sa else gb).members[member_at[r]] for r in both]
            offsets = [ga.offsets[member_at[r]] if slots[r] == sa else gb.offsets[member_at[r]] + rebase for r in both]
            ga.members = members
            ga.offsets = [o % n_s for o in offsets]
            ga.anchors = [None] * len(both)
            ga.aliased = ga.aliased or gb.aliased
            gb.members, gb.offsets, gb.anchors = [], [], []
            slots[both] = sa
            member_at[both] = np.arange(len(both))
            ga.refresh(p.match.columns, p.match.symmetry_threshold)
            made += 1
        if made:
            kept = [k for k, g in enumerate(self.state.groups) if g.members]
            renumber = np.full(len(self.state.groups), -1, dtype=np.int64)
            renumber[kept] = np.arange(len(kept))
            index.group[:n] = renumber[slots]
            self.state.groups = [self.state.groups[k] for k in kept]
            self.state.slot = {g.group_id: k for k, g in enumerate(self.state.groups)}
        return made

    def parts(
        self,
        positions: np.ndarray,
        travelled: np.ndarray,
        shortcuts: list[tuple[float, float]],
    ) -> np.ndarray:
        """Parts (labels from 0, in order of first member) whose members are all within the gate of each other.

        Agglomerative, closest pairs (by map distance over gate radius) first; two parts merge only
        when every pair across them is within the gate (complete linkage), so a member seen long
        after the last loop, with a gate wide enough to reach two places, does not chain them.
        """
        n = len(positions)
        distance = np.hypot(*(positions[:, None, :] - positions[None, :, :]).transpose(2, 0, 1))
        anchored = np.stack([anchored_distances(float(t), travelled, shortcuts) for t in travelled])
        ratio = distance / self.gate.radius(anchored, self.gate.quadratic())
        within = ratio <= 1.0
        label = np.arange(n)
        i, j = np.triu_indices(n, 1)
        for k in np.argsort(ratio[i, j], kind="stable"):
            a, b = label[i[k]], label[j[k]]
            if ratio[i[k], j[k]] > 1.0:
                break
            if a != b and within[np.ix_(label == a, label == b)].all():
                label[label == b] = a
        _, first, inverse = np.unique(label, return_index=True, return_inverse=True)
        rank = np.empty(len(first), dtype=np.int64)
        rank[np.argsort(first)] = np.arange(len(first))
        return rank[inverse]
