"""Online grouping of SGF descriptors (Sec. III-C, eq. 10): each new SGF joins its nearest SGF group or opens one."""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from sgf_pipeline import Previous, RunContext, Stage, StageRegistry, hookimpl
from sgf_pipeline.stage import SettledGroup, Settlement
from sgf_pipeline.types import (
    Frame,
    GroupAssignment,
    GroupAssignments,
    LoopConstraints,
    PoseEstimate,
    SgfDescriptor,
    SgfDescriptors,
)
from sgf_plugins.sgf.association import evaluation
from sgf_plugins.sgf.association.end_of_run import EndOfRun
from sgf_plugins.sgf.association.gate import SpatialGate
from sgf_plugins.sgf.association.groups import (
    GatedGroup,
    Ranking,
    SgfGroup,
    groups_from_map,
    odometry_position,
    settled,
)
from sgf_plugins.sgf.association.matching import Eq10Matching
from sgf_plugins.sgf.association.params import OnlineGroupsParams
from sgf_plugins.sgf.association.repeats import RepeatedPattern
from sgf_plugins.sgf.association.state import AssociationState
from sgf_plugins.shared.polar import shift_to_yaw, shifted_distances, symmetry_spread


@dataclass(frozen=True)
class Choice:
    """What the ranking of the gated groups decided for one query.

    ``best``: the group to join and its eq. 10 distance (None: open a group, reporting
    ``opened_distance``); ``tied``: the look-alike groups level with it; ``copy_nearby``: a neighbouring copy of a
    repeated pattern was among the candidates.
    """

    best: tuple[SgfGroup, float] | None
    opened_distance: float
    tied: list[GatedGroup]
    copy_nearby: bool


class OnlineSgfGroups(Stage):
    """Assign each SGF descriptor to the nearest SGF group by the column-shifted cosine distance (eq. 10).

    Candidates: with ``gate.enabled``, only groups with a member whose map position lies within
    ``gate.radius + gate.drift_rate * (distance travelled between the two sightings)`` of the query's.
    Map positions apply the back-end's previous estimate of the member's frame to its centroid,
    or the odometry pose when no back-end runs; the gate keeps identical standard markings at
    different places (perceptual aliasing) in different groups while allowing for drift. With
    ``gate.anchored``, the distance travelled is counted as the loop stage counts it
    (:mod:`sgf_plugins.shared.anchoring`): a loop closure that the estimate meets (within
    ``gate.anchor_tolerance``) joins its two frames at no cost, so once a revisit is anchored the gate
    shrinks back to what the odometry drifts since the loop, not since the first sighting.

    Groups are ranked by eq. 10 distance, plus ``match.position_weight`` times the ratio of their nearest
    member's map distance to its gate radius (0 where the estimate puts the query, 1 at the
    gate's edge): once the gate is tens of metres wide, a small eq. 10 advantage of a look-alike
    far away does not outrank the group right where the query lies. The query joins the
    candidate group ranked first if its eq. 10 distance is at most
    ``match.new_group_distance`` (0.7), else it opens a group (then ``distance`` is the smallest
    distance to a gated group, 1 when none was gated, and ``shift``/``yaw`` are 0). ``matched`` is
    the closest member of that group (by eq. 10 against each member's own descriptor) and
    ``shift``/``yaw`` are relative to it: the query's frame is turned by ``yaw`` from the matched
    member's frame, so ``R(yaw) @ (points - centroid) + matched.centroid`` approximates
    ``matched.points``. Shifts within ``match.yaw_tolerance`` of the best (2- or 4-fold symmetric
    markings) are resolved by the relative yaw of the two poses, and groups level with the best
    distance (identical descriptors, which eq. 10 cannot tell apart) are resolved by the nearest
    member on the map; a query whose own profile is not flat leaves the symmetric groups among them
    out (a match into one gives no loop factor).

    The group descriptor is the mean of its members after turning each by its shift into the
    first member's orientation: averaging unaligned descriptors of a feature seen from different
    headings (a reverse loop) would smear it over all sectors. A group whose
    self-distance profile over the N_s shifts is flat (spread below ``match.symmetry_threshold``, like a
    round manhole) is ``symmetric``, and so is a match into it when the query's or the matched
    member's own profile is flat too; symmetric matches give no loop factors. (A group that took
    in members of different markings can have a flat mean of unflat views: its matches still go
    to ICP, which tells them apart.)

    N_c of eq. 10 (an ambiguity): ``intersection`` averages over the columns occupied in both
    descriptors, as Scan Context does. Over 12 rendered markings seen from 5 headings
    (bench/bench_sgf.py, count bins) it keeps the same marking at p95 0.043 and different
    markings at p5 0.131, where ``union`` gives 0.240 and 0.164. Different markings are then far
    below the paper's 0.7, so new groups come mostly from the spatial gate; 0.7 stays the default.
    """

    kind = "association"
    name = "online_groups"
    output = "assignments"
    Params = OnlineGroupsParams

    def __init__(self, params: OnlineGroupsParams) -> None:
        super().__init__(params)
        self.params: OnlineGroupsParams = params
        self._prior: list[SgfGroup] = []
        self.state = AssociationState()
        self.repeats = RepeatedPattern(params, self.state)
        self.gate = SpatialGate(params, self.state, self.repeats)
        self.matching = Eq10Matching(params, self.state)
        self.end = EndOfRun(params, self.state, self.gate)
        self._rankings: list[Ranking] = []  # every query's ranking of the gated groups (for the evaluation)
        self._estimate: PoseEstimate | None = None  # the newest estimate seen (for the split at the end)
        # the groups before the end of the run, and the splits and merges made then
        self._concluded: tuple[tuple[SettledGroup, ...], int | None, int | None] | None = None

    # -- groups ---------------------------------------------------------------------------

    @property
    def groups(self) -> list[SgfGroup]:
        """The SGF groups so far (seeded groups first)."""
        return list(self.state.groups)

    def gated(self, query: SgfDescriptor, estimate: PoseEstimate | None) -> list[GatedGroup]:
        """The groups the spatial gate lets the query meet (:meth:`SpatialGate.gated`)."""
        return self.gate.gated(query, estimate)

    def pose_of(self, frame_index: int, odometry: np.ndarray, estimate: PoseEstimate | None) -> np.ndarray:
        """The map pose of a frame (:meth:`AssociationState.pose_of`)."""
        return self.state.pose_of(frame_index, odometry, estimate)

    def position_of(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> np.ndarray:
        """The map position (x, y) of a descriptor's centroid (:meth:`AssociationState.position_of`)."""
        return self.state.position_of(descriptor, estimate)

    def split_groups(self, estimate: PoseEstimate | None) -> int:
        """Split the groups the estimate spreads beyond the spatial gate (:meth:`EndOfRun.split_groups`)."""
        return self.end.split_groups(estimate)

    def merge_groups(self, estimate: PoseEstimate | None) -> int:
        """Merge look-alike groups the estimate puts at one place (:meth:`EndOfRun.merge_groups`)."""
        return self.end.merge_groups(estimate)

    def seed_groups(self, groups: Iterable[SgfGroup]) -> None:
        """Start every sequence with prior groups (from a saved SGF map); their members keep fixed map positions.

        A member without an anchor is placed by its own odometry pose; a saved map should store the
        optimised positions as anchors.
        """
        prior = []
        for group in groups:
            g = copy.copy(group)
            g.members, g.offsets = list(group.members), list(group.offsets)
            g.anchors = [
                a if a is not None else odometry_position(m) for a, m in zip(group.anchors, group.members, strict=True)
            ]
            if not g.members:
                raise ValueError(f"seeded SGF group {group.group_id} has no members")
            g.refresh(self.params.match.columns, self.params.match.symmetry_threshold)
            prior.append(g)
        ids = [g.group_id for g in prior]
        if len(set(ids)) != len(ids):
            raise ValueError("seeded SGF groups must have distinct group ids")
        self._prior = prior
        self._reset()

    def _reset(self) -> None:
        self.state.reset(self._prior)
        self.gate.reset()
        self._rankings = []
        self._estimate = None
        self._concluded = None

    def begin(self, context: RunContext) -> None:
        """Start the sequence with the seeded groups only (those of ``prior_map`` when it is set)."""
        if self.params.prior_map is not None and not self._prior:
            from sgf_pipeline.errors import DataError
            from sgf_pipeline.sgf_map import load_map

            sgf_map = load_map(self.params.prior_map, calibration=context.calibration)
            groups = groups_from_map(sgf_map, self.params.match.columns)
            shape = context.artifacts.get("descriptor_shape")
            found = {tuple(m.matrix.shape) for g in groups for m in g.members}
            if shape is not None and found and found != {tuple(shape)}:
                sizes = " / ".join("x".join(map(str, f)) for f in sorted(found))
                raise DataError(
                    f"SGF map {self.params.prior_map} holds descriptors of N_r x N_s = {sizes}, this run makes "
                    f"{shape[0]}x{shape[1]}: set descriptor.num_rings and descriptor.num_sectors to the map's"
                )
            self.seed_groups(groups)
        self._reset()

    # -- eq. 10 ------------------------------------------------------------------------------

    def assign(self, query: SgfDescriptor, estimate: PoseEstimate | None = None) -> GroupAssignment:
        """Assign one descriptor to its SGF group (eq. 10), creating a group when none is close enough."""
        candidates = self.gate.gated(query, estimate)
        choice = self._choose(query, candidates)
        if choice.best is None or choice.best[1] > self.params.match.new_group_distance:
            return self._open(query, choice)
        group, best_distance = choice.best
        return self._join(query, estimate, group, best_distance, choice)

    def _choose(self, query: SgfDescriptor, candidates: list[GatedGroup]) -> Choice:
        """Rank the gated groups by eq. 10 and the position weight; the group the query joins, if any."""
        p = self.params
        best: tuple[SgfGroup, float] | None = None
        opened_distance = 1.0  # reported when the query opens a group and no group was kept
        tied: list[GatedGroup] = []
        copy_nearby = False
        if candidates:
            stack = np.stack([c.group.descriptor for c in candidates])
            if stack.shape[1:] != query.matrix.shape:
                raise ValueError(
                    f"descriptor shape {query.matrix.shape} differs from the groups' {stack.shape[1:]}; "
                    "all SGF descriptors of a run (and of a seeded map) need the same N_r and N_s"
                )
            eq10 = shifted_distances(query.matrix, stack, p.match.columns, p.match.min_overlap).min(axis=1)
            # Where the estimate puts the query counts too: a group at the gate's edge pays position_weight.
            score = eq10 + p.match.position_weight * np.array([c.ratio for c in candidates])
            self._rankings.append(
                Ranking(query, tuple((c.group.group_id, len(c.group.members)) for c in candidates), score)
            )
            # A look-alike group just seen elsewhere is a neighbouring copy of a repeated pattern
            # (give-way triangles, dashes): the query may not join it, and neither gives loop factors.
            copy = np.array([c.repeated for c in candidates]) & (
                self.repeats.copy_distances(query, candidates, eq10) <= p.repeats.copy_distance
            )
            for i in np.flatnonzero(copy):
                candidates[i].group.aliased = True
            copy_nearby = bool(copy.any())
            best_kept = score[~copy].min() if not copy.all() else math.inf
            if p.repeats.copies == "new" and copy_nearby and score[copy].min() <= best_kept:
                # The query is one more copy of the pattern here, not a revisit elsewhere: a group of its own.
                opened_distance = float(eq10.min())
            elif not copy.all():
                ties = np.flatnonzero(~copy & (score <= best_kept))
                ties = self.matching.closable_ties(query, candidates, ties)
                i = int(min(ties, key=lambda t: candidates[t].nearest))
                best = (candidates[i].group, float(eq10[i]))
                # Look-alike groups inside the gate (identical standard markings) cannot be told apart
                # by eq. 10: the query joins the nearest, the match is ambiguous, and the others are
                # handed on as alternatives (a loop stage may tell them apart by their neighbours).
                tied = [candidates[t] for t in ties if t != i]
        return Choice(best, opened_distance, tied, copy_nearby)

    def _open(self, query: SgfDescriptor, choice: Choice) -> GroupAssignment:
        """Open a group for the query."""
        p, state = self.params, self.state
        group = SgfGroup(state.next_id, aliased=choice.copy_nearby)
        state.next_id += 1
        group.add(query, 0)
        state.index.add(len(state.groups), query, state.frames.get_distance(query.sgf.frame_index), None)
        group.refresh(p.match.columns, p.match.symmetry_threshold)
        state.slot[group.group_id] = len(state.groups)
        state.groups.append(group)
        distance = choice.opened_distance if choice.best is None else choice.best[1]
        return GroupAssignment(
            query,
            group.group_id,
            True,
            distance,
            0,
            0.0,
            None,
            group.symmetric,
            ambiguous=group.aliased,
            aliased=group.aliased,
        )

    def _join(
        self, query: SgfDescriptor, estimate: PoseEstimate | None, group: SgfGroup, best_distance: float, choice: Choice
    ) -> GroupAssignment:
        """Add the query to the chosen group, turned by the shift to its closest member."""
        p, state = self.params, self.state
        n_s = query.matrix.shape[1]
        group.aliased = group.aliased or choice.copy_nearby
        m, matched, shift = self.matching.closest_member(query, group, estimate)
        # An aliased look-alike (a repeated pattern) could be the true one: then nothing resolves the tie.
        alternatives = (
            ()
            if any(g.group.aliased for g in choice.tied)
            else tuple(self.matching.look_alike(query, g, estimate) for g in choice.tied)
        )
        group.add(query, shift + group.offsets[m])
        state.index.add(state.slot[group.group_id], query, state.frames.get_distance(query.sgf.frame_index), None)
        group.refresh(p.match.columns, p.match.symmetry_threshold)
        # A flat group mean may only be a smear of members from different markings: the match is
        # symmetric when one of its two own views is flat too. Two flat views are symmetric whatever
        # the group's mean (a round manhole in a group that also took a shaped view): no yaw to fit.
        spreads = (symmetry_spread(query.matrix, p.match.columns), symmetry_spread(matched.matrix, p.match.columns))
        symmetric = (group.symmetric and min(spreads) < p.match.symmetry_threshold) or max(
            spreads
        ) < p.match.symmetry_threshold
        return GroupAssignment(
            descriptor=query,
            group_id=group.group_id,
            new_group=False,
            distance=best_distance,
            shift=shift,
            yaw=shift_to_yaw(shift, n_s),
            matched=matched,
            symmetric=symmetric,
            ambiguous=group.aliased or bool(choice.tied),
            aliased=group.aliased,
            alternatives=alternatives,
        )

    def process(
        self,
        frame: Frame,
        descriptors: SgfDescriptors,
        estimate: Previous[PoseEstimate],
        loops: Previous[LoopConstraints] = None,
    ) -> GroupAssignments:
        """Group this frame's SGF descriptors."""
        self.state.record(frame)
        self.state.remember_loops(loops)
        if estimate is not None:
            self._estimate = estimate
        return GroupAssignments(tuple(self.assign(d, estimate) for d in descriptors.items))

    # -- the end of the run ----------------------------------------------------------------

    def conclude(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Regroup at the end of the run; hands on the final groups (``settlement.groups``, ``settlement.group_of``).

        With ``end.split`` the groups are split by the newest estimate (:meth:`split_groups`), and
        with ``end.merge`` look-alikes it puts at one place merged (:meth:`merge_groups`).
        ``group_of`` maps each run member's ``(frame_index, track_id)`` to its final group, for the
        loop stage's final pass and the SGF map.
        """
        online = settled(self.state.groups)
        estimate = self._estimate
        split = merged = None
        if self.params.end.split and self.params.gate.enabled:
            split = self.end.split_groups(estimate)
        if self.params.end.merge:
            merged = self.end.merge_groups(estimate)
        self._concluded = (online, split, merged)
        group_of = {
            (m.sgf.frame_index, m.sgf.track_id): g.group_id
            for g in self.state.groups
            for m, a in zip(g.members, g.anchors, strict=True)
            if a is None
        }
        return replace(settlement, groups=settled(self.state.groups), group_of=group_of)

    def finalize(self, context: RunContext) -> None:
        """Publish the groups and the group metrics (:meth:`conclude` runs here first when the run ended without it).

        Artifacts, for observers and the evaluation (:mod:`sgf_plugins.sgf.association.evaluation`):
        ``sgf_groups`` (the final groups), ``sgf_groups_online`` (the groups before the split and merge
        at the end) and ``sgf_rankings`` (every query's ranking of the gated groups).
        """
        if self._concluded is None:
            self.conclude(context, Settlement())
        assert self._concluded is not None
        online, split, merged = self._concluded
        sgf: dict[str, Any] = context.metrics.setdefault("sgf", {})
        if split is not None:
            sgf["groups_split"] = split
        if merged is not None:
            sgf["groups_merged"] = merged
        context.artifacts["sgf_groups"] = list(self.state.groups)
        context.artifacts["sgf_groups_online"] = online
        context.artifacts["sgf_rankings"] = list(self._rankings)
        sgf["groups"] = len(self.state.groups)
        sgf["symmetric_groups"] = sum(1 for g in self.state.groups if g.symmetric)
        sgf["aliased_groups"] = sum(1 for g in self.state.groups if g.aliased)


# The ground-truth scores of the groups, from what the stage publishes, when a run ends.
sgf_report_metrics = evaluation.sgf_report_metrics


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the online SGF grouping."""
    registry.add(OnlineSgfGroups)
