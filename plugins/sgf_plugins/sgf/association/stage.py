"""Online grouping of SGF descriptors (Sec. III-C, eq. 10): each new SGF joins its nearest SGF group or opens one."""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from pydantic import Field

from sgf_pipeline import Previous, RunContext, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.stage import SettledGroup, Settlement
from sgf_pipeline.types import (
    Frame,
    GroupAssignment,
    GroupAssignments,
    LookAlike,
    LoopConstraints,
    MarkingPass,
    PoseEstimate,
    SequenceTruth,
    SgfDescriptor,
    SgfDescriptors,
)
from sgf_plugins.backend.heading_bias import EXPECTED_YAW_BIAS, corrected_yaw_bias, uncorrected_yaw_bias
from sgf_plugins.odometry.anchoring import anchored_distances
from sgf_plugins.odometry.frame_log import FrameLog
from sgf_plugins.sgf.polar import (
    ColumnSet,
    align,
    best_shift,
    shift_to_yaw,
    shifted_distances,
    symmetry_spread,
    yaw_to_shift,
)

#: Frames whose odometry and travelled distance are remembered at least (older ones only for group members).
HISTORY_FRAMES = 20_000


@dataclass
class SgfGroup:
    """An SGF group: descriptors of one physical ground feature, aligned to the first member's orientation.

    ``offsets[i]`` turns member i into the group's orientation (``align(matrix, offset)``);
    ``descriptor`` is the mean of the aligned members (D^sg of eq. 10). ``anchors[i]`` is a fixed
    map position (x, y) of member i for groups loaded from a saved map, or None for members whose
    position follows the current pose estimate.
    """

    group_id: int
    members: list[SgfDescriptor] = field(default_factory=list)
    offsets: list[int] = field(default_factory=list)
    anchors: list[np.ndarray | None] = field(default_factory=list)
    descriptor: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    spread: float = 0.0
    symmetric: bool = False
    aliased: bool = False

    def add(self, member: SgfDescriptor, offset: int, anchor: np.ndarray | None = None) -> None:
        """Append a member turned by ``offset`` columns into the group's orientation (kept without its BEV pixels)."""
        self.members.append(member.without_pixels())
        self.offsets.append(int(offset) % member.matrix.shape[1])
        self.anchors.append(None if anchor is None else np.asarray(anchor, dtype=np.float64).reshape(2))

    def refresh(self, columns: ColumnSet, symmetry_threshold: float) -> None:
        """Recompute the group descriptor (mean of aligned members) and its rotational symmetry."""
        aligned = [align(m.matrix, o) for m, o in zip(self.members, self.offsets, strict=True)]
        self.descriptor = np.mean(aligned, axis=0)
        self.spread = symmetry_spread(self.descriptor, columns)
        self.symmetric = self.spread < symmetry_threshold

    @property
    def matrices(self) -> np.ndarray:
        """The members' own (unaligned) descriptors, (M, N_r, N_s)."""
        return np.stack([m.matrix for m in self.members])

    @property
    def instance_ids(self) -> list[int | None]:
        """The ground-truth instance of each member (None when unknown)."""
        return [m.sgf.instance_id for m in self.members]


class OnlineGroupsParams(StageParams):
    """Eq. 10 grouping with the paper's 0.7 threshold, a spatial gate and the symmetry test."""

    new_group_distance: float = Field(
        0.7, gt=0.0, le=1.0, description="eq. 10 distance above which (to every group) an SGF opens a new group"
    )
    columns: Literal["union", "intersection", "all"] = Field(
        "intersection", description="columns averaged in eq. 10: occupied in both (Scan Context), in either, or all N_s"
    )
    min_overlap: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="eq. 10 is 1 at a column shift where fewer than this share of the emptier descriptor's occupied "
        "columns are occupied in both (a sliver lining up with two columns of another marking is no match); 0 = off",
    )
    symmetry_threshold: float = Field(
        0.065,
        ge=0.0,
        description="a group whose self-distance over all column shifts varies less is symmetric (a round manhole "
        "as the saliency network fills it: at most 0.06; a wheelchair symbol, a logo in a ring: 0.07 and more)",
    )
    spatial_gate: bool = Field(True, description="only consider groups with a member near the SGF on the map")
    gate_radius: float = Field(1.5, gt=0.0, description="gate radius (m) between SGF centroids seen from one place")
    drift_rate: float = Field(
        0.05, ge=0.0, description="gate growth per metre travelled between the two sightings (odometry drift)"
    )
    drift_bias_share: float = Field(
        0.5,
        ge=0.0,
        description="gate growth per squared metre travelled, for the odometry's heading bias b (rad/m; position "
        "error ~ d^2), as a share of a straight drive's bound 0.5 b: a route that turns back stays under it "
        "(a loop route's return to its start after 1.5 km: 0.4 of it)",
    )
    gate_bias_from_backend: bool = Field(
        True,
        description="b as the back-end's model holds it (the estimate's yaw_bias): the uncertainty of the bias left "
        "between members whose drive its correction covers (seen after it began, or between the two frames of an "
        "anchoring loop), the measured bias elsewhere; false = the bias wheel odometry is expected to have",
    )
    member_gate: bool = Field(
        True,
        description="eq. 10 against a group's members inside the gate only; false = against every member once one "
        "is inside (a group then reaches far: a member seen long ago opens the gate, a recent one far away matches)",
    )
    prior_gate_radius: float | None = Field(
        None, gt=0.0, description="gate (m) around members of groups seeded from a saved map; null = no gate"
    )
    group_distance: Literal["mean", "nearest_member"] = Field(
        "nearest_member",
        description="a group's eq. 10 distance: to the mean of its aligned members (the paper's D^sg), or to its "
        "closest member (a view that differs from the others by a partial mask still matches its own)",
    )
    position_weight: float = Field(
        0.3,
        ge=0.0,
        description="added to a group's eq. 10 distance times how far out in the spatial gate its nearest member lies "
        "(0 at the query's map position, this at the gate's edge): groups are ranked by both; 0 = eq. 10 alone",
    )
    tie_margin: float = Field(
        0.05,
        ge=0.0,
        description="groups within this eq. 10 distance of the best are equally good; the nearest on the map wins",
    )
    repeat_window: float = Field(
        15.0,
        ge=0.0,
        description="a group member seen within this many metres of travel, but away from the query, is another "
        "copy of a repeated pattern (give-way triangles, zebra bars, dashes): the query may not join it; 0 = no "
        "repeated-pattern test",
    )
    repeat_radius: float = Field(0.5, gt=0.0, description="...away means farther than this on the map (m)")
    repeat_overlap: float | None = Field(
        0.25,
        gt=0.0,
        le=1.0,
        description="...and its ground footprint shares less than this share of the smaller one's cells with the "
        "query's (a partial view of the same marking moves the centroid but overlaps it); null = no footprint test",
    )
    footprint_cell: float = Field(0.1, gt=0.0, description="cell size (m) of the footprints the overlap compares")
    copy_distance: float = Field(
        0.2, ge=0.0, description="...and a copy looks like the query: eq. 10 distance at most this (0 = no copies)"
    )
    copy_member: bool = Field(
        True,
        description="a copy is judged by eq. 10 to the member seen moments ago elsewhere itself; false = to the "
        "group's closest member (a group that once took in an unlike SGF seen nearby then turns every revisit of "
        "its marking into a copy)",
    )
    copies: Literal["apart", "new"] = Field(
        "new",
        description="a query whose best match is a neighbouring copy (ties it within tie_margin): joins the best "
        "other group (apart), or opens its own (new, aliased: no loop factors)",
    )
    prior_map: str | None = Field(
        None, description="an SGF map (sgf_map.safetensors) whose groups seed the association: localization on it"
    )
    anchored_gate: bool = Field(
        True,
        description="count the gate's distance travelled from the loop closures the estimate satisfies (drift "
        "restarts at a closed loop); false = between the two sightings only",
    )
    anchor_tolerance: float = Field(
        0.5, gt=0.0, description="a loop anchors the gate when the estimate meets its relative pose within this (m)"
    )
    yaw_tolerance: float = Field(
        0.02,
        ge=0.0,
        description="shifts within this eq. 10 distance of the best are ties, resolved by the pose estimate's yaw",
    )
    split_at_end: bool = Field(
        True,
        description="at the end of the run, split each group into the parts that the final estimate puts within "
        "the spatial gate of each other (identical markings joined while the gate was tens of metres wide)",
    )
    merge_at_end: bool = Field(
        True,
        description="at the end of the run, after the split, merge groups whose members the final estimate puts at "
        "one place and that look alike there (a revisit that joined another group while the gate was wide)",
    )
    merge_radius: float = Field(1.0, gt=0.0, description="...at one place: member centroids this close on the map (m)")
    merge_distance: float = Field(
        0.15, ge=0.0, le=1.0, description="...and look alike: eq. 10 at most this, at the shift the estimate predicts"
    )
    merge_yaw_deg: float = Field(
        10.0, ge=0.0, le=180.0, description="...within this many degrees of it (symmetric groups: at any shift)"
    )


@dataclass(frozen=True)
class GatedGroup:
    """A group inside the query's spatial gate: its nearest member's map distance, and whether it repeats."""

    group: SgfGroup
    nearest: float
    repeated: bool
    ratio: float = 0.0
    members: np.ndarray | None = None  # indices of the members inside the gate (None: every member)
    repeating: np.ndarray | None = None  # indices of the members seen moments ago elsewhere (when ``repeated``)


class _MemberIndex:
    """Every group member in flat arrays (group, frame, centroid, odometry, travelled, anchor) for the spatial gate.

    The gate then costs a few numpy passes over all members instead of Python work per member;
    map positions are computed once per pose estimate (one per frame) and extended as members join.
    """

    def __init__(self) -> None:
        self.size = 0
        self.group = np.zeros(64, dtype=np.int64)
        self.frame = np.zeros(64, dtype=np.int64)
        self.centroid = np.zeros((64, 2))
        self.odometry = np.zeros((64, 4, 4))
        self.travelled = np.zeros(64)
        self.anchor = np.zeros((64, 2))
        self.positions = np.zeros((0, 2))
        self.estimate: object = _NO_ESTIMATE
        self.members: list[SgfDescriptor] = []

    def add(self, group: int, member: SgfDescriptor, travelled: float | None, anchor: np.ndarray | None) -> None:
        """Append one member of the group at position ``group`` in the group list."""
        if self.size == len(self.group):
            for name in ("group", "frame", "centroid", "odometry", "travelled", "anchor"):
                old = getattr(self, name)
                grown = np.zeros((2 * len(old), *old.shape[1:]), dtype=old.dtype)
                grown[: self.size] = old[: self.size]
                setattr(self, name, grown)
        k = self.size
        self.group[k] = group
        self.frame[k] = member.sgf.frame_index
        self.centroid[k] = np.asarray(member.centroid, dtype=np.float64)[:2]
        self.odometry[k] = np.asarray(member.sgf.odometry, dtype=np.float64)
        self.travelled[k] = math.nan if travelled is None else travelled
        self.anchor[k] = math.nan if anchor is None else anchor
        self.members.append(member)
        self.size += 1


_NO_ESTIMATE = object()
#: A loop anchors the gate when the estimate's relative yaw between its frames is within this of the loop's (rad).
ANCHOR_YAW_TOLERANCE = 0.05


@dataclass(frozen=True)
class _Closure:
    """An accepted loop closure of this run and the distance travelled up to each of its frames."""

    frame_from: int
    frame_to: int
    relative: np.ndarray
    travelled_from: float
    travelled_to: float


class OnlineSgfGroups(Stage):
    """Assign each SGF descriptor to the nearest SGF group by the column-shifted cosine distance (eq. 10).

    Candidates: with ``spatial_gate``, only groups with a member whose map position lies within
    ``gate_radius + drift_rate * (distance travelled between the two sightings)`` of the query's;
    with ``member_gate`` a group is compared through those members only (a sighting from long ago
    has a wide gate, and must not let a recent member of its group far from the query match it).
    Map positions apply the back-end's previous estimate of the member's frame to its centroid,
    or the odometry pose when no back-end runs; the gate keeps identical standard markings at
    different places (perceptual aliasing) in different groups while allowing for drift. With
    ``anchored_gate``, the distance travelled is counted as the loop stage counts it
    (:mod:`sgf_plugins.odometry.anchoring`): a loop closure that the estimate meets (within
    ``anchor_tolerance``) joins its two frames at no cost, so once a revisit is anchored the gate
    shrinks back to what the odometry drifts since the loop, not since the first sighting.

    Groups are ranked by eq. 10 distance, plus ``position_weight`` times the ratio of their nearest
    member's map distance to its gate radius (0 where the estimate puts the query, 1 at the
    gate's edge): once the gate is tens of metres wide, a small eq. 10 advantage of a look-alike
    far away no longer outranks the group right where the query lies. The query joins the
    candidate group ranked first if its eq. 10 distance is at most
    ``new_group_distance`` (0.7), else it opens a group (then ``distance`` is the smallest
    distance to a gated group, 1 when none was gated, and ``shift``/``yaw`` are 0). ``matched`` is
    the closest member of that group (by eq. 10 against each member's own descriptor) and
    ``shift``/``yaw`` are relative to it: the query's frame is turned by ``yaw`` from the matched
    member's frame, so ``R(yaw) @ (points - centroid) + matched.centroid`` approximates
    ``matched.points``. Shifts within ``yaw_tolerance`` of the best (2- or 4-fold symmetric
    markings) are resolved by the relative yaw of the two poses, and groups within ``tie_margin``
    of the best distance (identical standard markings, which eq. 10 cannot tell apart) are
    resolved by the nearest member on the map; a query whose own profile is not flat leaves the
    symmetric groups among them out (a match into one gives no loop factor).

    The group descriptor is the mean of its members after turning each by its shift into the
    first member's orientation: averaging unaligned descriptors of a feature seen from different
    headings (a reverse loop) would smear it over all sectors. A group whose
    self-distance profile over the N_s shifts is flat (spread below ``symmetry_threshold``, like a
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
        self._groups: list[SgfGroup] = []
        self._frames = FrameLog(keep=HISTORY_FRAMES)
        self._next_id = 0
        self._index = _MemberIndex()
        self._slot: dict[int, int] = {}
        self._closures: list[_Closure] = []
        self._shortcuts: tuple[object, list[tuple[float, float]]] = (_NO_ESTIMATE, [])
        self._ranked = [0, 0]  # labelled decisions between the own marking's group and others; own ranked first
        self._estimate: PoseEstimate | None = None  # the newest estimate seen (for the split at the end)
        self._bias_began: tuple[int, float] | None = None  # frame and travelled distance the bias correction began
        self._end: tuple[tuple[SettledGroup, ...], int | None, int | None] | None = None  # online groups, split, merged

    # -- groups ---------------------------------------------------------------------------

    @property
    def groups(self) -> list[SgfGroup]:
        """The SGF groups so far (seeded groups first)."""
        return list(self._groups)

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
                a if a is not None else _odometry_position(m) for a, m in zip(group.anchors, group.members, strict=True)
            ]
            if not g.members:
                raise ValueError(f"seeded SGF group {group.group_id} has no members")
            g.refresh(self.params.columns, self.params.symmetry_threshold)
            prior.append(g)
        ids = [g.group_id for g in prior]
        if len(set(ids)) != len(ids):
            raise ValueError("seeded SGF groups must have distinct group ids")
        self._prior = prior
        self._reset()

    def _reset(self) -> None:
        self._groups = [copy.copy(g) for g in self._prior]
        for g, p in zip(self._groups, self._prior, strict=True):
            g.members, g.offsets, g.anchors = list(p.members), list(p.offsets), list(p.anchors)
        self._next_id = max((g.group_id for g in self._prior), default=-1) + 1
        self._frames = FrameLog(keep=HISTORY_FRAMES)
        self._index = _MemberIndex()
        self._slot = {g.group_id: k for k, g in enumerate(self._groups)}
        self._closures = []
        self._shortcuts = (_NO_ESTIMATE, [])
        self._ranked = [0, 0]
        self._estimate = None
        self._bias_began = None
        self._end = None
        for k, group in enumerate(self._groups):
            for member, anchor in zip(group.members, group.anchors, strict=True):
                self._index.add(k, member, None, anchor)

    def begin(self, context: RunContext) -> None:
        """Start the sequence with the seeded groups only (those of ``prior_map`` when it is set)."""
        if self.params.prior_map is not None and not self._prior:
            from sgf_pipeline.errors import DataError
            from sgf_pipeline.sgf_map import load_map

            sgf_map = load_map(self.params.prior_map, calibration=context.calibration)
            groups = groups_from_map(sgf_map, self.params.columns)
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

    # -- map positions and the spatial gate ---------------------------------------------------

    def _record(self, frame: Frame) -> None:
        """Remember the frame's odometry and the distance travelled up to it (the last HISTORY_FRAMES frames)."""
        self._frames.append(frame)  # bounded over hours: the oldest frames go, members keep theirs

    def pose_of(self, frame_index: int, odometry: np.ndarray, estimate: PoseEstimate | None) -> np.ndarray:
        """The map pose of a frame: the estimate's, else its odometry corrected like the estimate's newest frame."""
        if estimate is None:
            return odometry
        pose = estimate.poses.get(frame_index)
        if pose is not None:
            return np.asarray(pose, dtype=np.float64)
        ref = estimate.frame_index
        ref_odometry = self._frames.get_odometry(ref)
        if ref_odometry is None or ref not in estimate.poses:
            return odometry
        return np.asarray(estimate.poses[ref]) @ invert(ref_odometry) @ odometry

    def map_pose(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> np.ndarray:
        """The map pose of the frame a descriptor was seen from (:meth:`pose_of` its frame)."""
        sgf = descriptor.sgf
        return self.pose_of(sgf.frame_index, np.asarray(sgf.odometry, dtype=np.float64), estimate)

    def position_of(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> np.ndarray:
        """The map position (x, y) of a descriptor's centroid."""
        pose = self.map_pose(descriptor, estimate)
        c = descriptor.centroid
        return pose[:2, :2] @ np.asarray(c[:2], dtype=np.float64) + pose[:2, 3]

    def _member_positions(self, estimate: PoseEstimate | None) -> np.ndarray:
        """Map positions (x, y) of every member, cached for one estimate (members that joined since are added)."""
        index = self._index
        done = len(index.positions) if index.estimate is estimate else 0
        if done < index.size:
            fresh = slice(done, index.size)
            odometry = index.odometry[fresh]
            if estimate is None:
                poses = odometry
            else:
                poses, found = estimate.stack(index.frame[fresh])
                if not found.all():
                    ref = estimate.frame_index
                    ref_odometry = self._frames.get_odometry(ref)
                    if ref_odometry is None or ref not in estimate.poses:
                        poses[~found] = odometry[~found]
                    else:
                        correction = np.asarray(estimate.poses[ref]) @ invert(ref_odometry)
                        poses[~found] = correction @ odometry[~found]
            positions = np.einsum("nij,nj->ni", poses[:, :2, :2], index.centroid[fresh]) + poses[:, :2, 3]
            anchor = index.anchor[fresh]
            anchored = ~np.isnan(anchor[:, 0])
            positions[anchored] = anchor[anchored]
            index.positions = np.concatenate([index.positions[:done], positions])
            index.estimate = estimate
        return index.positions

    def _footprint(self, descriptor: SgfDescriptor, estimate: PoseEstimate | None) -> set[tuple[int, int]]:
        """The map cells (``footprint_cell`` wide) that a descriptor's ground points cover."""
        pose = self.map_pose(descriptor, estimate)
        xy = np.asarray(descriptor.points, dtype=np.float64)[:, :2] @ pose[:2, :2].T + pose[:2, 3]
        cells = np.floor(xy / self.params.footprint_cell).astype(np.int64)
        return set(map(tuple, cells.tolist()))

    def gated(self, query: SgfDescriptor, estimate: PoseEstimate | None) -> list[GatedGroup]:
        """The groups the spatial gate lets the query meet, with their nearest member's map distance (m).

        ``repeated`` marks a group holding a member seen moments ago (within ``repeat_window`` of
        travel) at another place (beyond ``repeat_radius``, and with a ground footprint that
        overlaps the query's by less than ``repeat_overlap``): if it also looks like the query, the
        two are neighbouring copies of a repeated pattern (see :meth:`assign`). A partial view of
        the same marking moves its centroid by up to a metre or two but covers the same paint.
        """
        p, index = self.params, self._index
        n = index.size
        if n == 0:
            return []
        here = self.position_of(query, estimate)
        distance = np.hypot(*(self._member_positions(estimate) - here).T)
        anchored = ~np.isnan(index.anchor[:n, 0])
        # Distance travelled between the two sightings; straight-line odometry distance where unknown.
        since = self._frames.get_distance(query.sgf.frame_index)
        travelled = np.abs(index.travelled[:n] - since) if since is not None else np.full(n, np.nan)
        unknown = np.isnan(travelled)
        if unknown.any():
            odometry = np.asarray(query.sgf.odometry, dtype=np.float64)[:3, 3]
            travelled[unknown] = np.linalg.norm(index.odometry[:n][unknown, :3, 3] - odometry, axis=1)
        repeated = ~anchored & (travelled < p.repeat_window) & (distance > p.repeat_radius)
        if p.repeat_overlap is not None and repeated.any():
            footprint = self._footprint(query, estimate)
            for k in np.flatnonzero(repeated):
                other = self._footprint(index.members[k], estimate)
                shared = len(footprint & other) / max(1, min(len(footprint), len(other)))
                repeated[k] = shared < p.repeat_overlap
        if p.anchored_gate and since is not None:
            shortcuts = self._anchoring(estimate)
            if shortcuts:
                known = ~unknown
                travelled[known] = anchored_distances(since, index.travelled[:n][known], shortcuts)
        quadratic = self._quadratic(index.travelled[:n], self._anchoring(estimate), estimate)
        radius = self._gate_radius(travelled, quadratic)
        radius[anchored] = math.inf if p.prior_gate_radius is None else p.prior_gate_radius
        groups = index.group[:n]
        count = len(self._groups)
        member_inside = (distance <= radius) | (not p.spatial_gate)
        nearest = np.full(count, math.inf)
        np.minimum.at(nearest, groups, np.where(member_inside | (not p.member_gate), distance, math.inf))
        ratio = np.full(count, math.inf)
        np.minimum.at(ratio, groups, distance / radius)
        inside = np.bincount(groups, weights=member_inside, minlength=count) > 0
        repeats = np.bincount(groups, weights=repeated, minlength=count) > 0
        members: list[np.ndarray | None] = [None] * count
        repeating: list[np.ndarray | None] = [None] * count
        if inside.any() and ((p.member_gate and p.spatial_gate) or (repeats & inside).any()):
            # members sit in the index in the order they joined their group: rank within the group = member index
            order = np.argsort(groups, kind="stable")
            starts = np.concatenate([[0], np.cumsum(np.bincount(groups, minlength=count))[:-1]])
            rank = np.arange(n) - starts[groups[order]]  # of each member, in ``order``

            def per_group(flags: np.ndarray) -> list[np.ndarray]:
                kept = flags[order]
                return np.split(rank[kept], np.cumsum(np.bincount(groups[order][kept], minlength=count))[:-1])

            if p.member_gate and p.spatial_gate:
                members = [m if inside[k] else None for k, m in enumerate(per_group(member_inside))]
            repeating = [r if repeats[k] else None for k, r in enumerate(per_group(repeated))]
        return [
            GatedGroup(group, float(nearest[k]), bool(repeats[k]), float(min(ratio[k], 1.0)), members[k], repeating[k])
            for k, group in enumerate(self._groups)
            if inside[k]
        ]

    def _remember_loops(self, loops: LoopConstraints | None) -> None:
        """Keep this run's accepted loop closures (map matches are anchored by the map's own gate)."""
        for c in () if loops is None else loops.items:
            if c.from_map:
                continue
            ends = [self._travelled_at(c.frame_from), self._travelled_at(c.frame_to)]
            if all(t is not None for t in ends):
                self._closures.append(_Closure(c.frame_from, c.frame_to, np.asarray(c.relative), *ends))  # type: ignore[arg-type]

    def _per_bias(self, bias: float) -> float:
        """The gate's growth per squared metre for a heading bias (rad/m): ``drift_bias_share`` of 0.5 b."""
        return self.params.drift_bias_share * 0.5 * abs(bias)

    def _travelled_at(self, frame_index: int) -> float | None:
        """Distance travelled up to a frame: remembered for recent frames and for group members."""
        known = self._frames.get_distance(frame_index)
        if known is not None:
            return known
        index = self._index
        hits = np.flatnonzero(index.frame[: index.size] == frame_index)
        if hits.size and not math.isnan(index.travelled[hits[0]]):
            return float(index.travelled[hits[0]])
        return None

    def _anchoring(self, estimate: PoseEstimate | None) -> list[tuple[float, float]]:
        """Travelled distances of the two frames of each loop closure the estimate satisfies (cached per estimate).

        A loop the back-end has not absorbed (no back-end, a loop down-weighted by the robust kernel)
        anchors nothing: between its frames the estimate may still carry the whole drift.
        """
        if estimate is None or not self._closures:
            return []
        if self._shortcuts[0] is estimate:
            return self._shortcuts[1]
        tolerance = self.params.anchor_tolerance
        shortcuts = []
        for c in self._closures:
            start, end = estimate.poses.get(c.frame_from), estimate.poses.get(c.frame_to)
            if start is None or end is None:
                continue
            error = invert(c.relative) @ invert(np.asarray(start)) @ np.asarray(end)
            if math.hypot(error[0, 3], error[1, 3]) <= tolerance and abs(xy_yaw(error)[2]) <= ANCHOR_YAW_TOLERANCE:
                shortcuts.append((c.travelled_from, c.travelled_to))
        self._shortcuts = (estimate, shortcuts)
        return shortcuts

    def _gate_radius(self, travelled: np.ndarray, quadratic: np.ndarray | float) -> np.ndarray:
        """The spatial gate's radius (m) for the distances travelled between two sightings.

        ``quadratic``: the heading bias term per pair (:meth:`_quadratic`).
        """
        p = self.params
        return p.gate_radius + p.drift_rate * travelled + quadratic * travelled**2

    def _quadratic(
        self, travelled: np.ndarray, shortcuts: list[tuple[float, float]], estimate: PoseEstimate | None
    ) -> np.ndarray:
        """The gate's heading bias term for members seen at ``travelled`` metres (``gate_bias_from_backend``).

        The bias is the back-end's model of it (``PoseEstimate.yaw_bias``): as measured so far on
        odometry nothing was taken off. Once the back-end takes its estimate off, the estimate keeps
        only the bias left in it, about its sigma, on the drive after the correction began; between
        the two frames of a loop it satisfies, the pose graph has spread the loop's error, a constant
        bias included. There the term counts that sigma (never more than elsewhere); for a pair with
        one member elsewhere it stays.
        """
        p = self.params
        if not p.gate_bias_from_backend:
            return np.full(np.shape(travelled), self._per_bias(EXPECTED_YAW_BIAS))
        q = np.full(np.shape(travelled), self._per_bias(uncorrected_yaw_bias(estimate)))
        corrected = corrected_yaw_bias(estimate)
        if corrected is None:
            return q
        since, sigma = corrected
        if self._bias_began is None or self._bias_began[0] != since:
            known = self._travelled_at(since)  # remembered: the frame log forgets old frames
            self._bias_began = None if known is None else (since, known)
        if self._bias_began is None:
            return q
        began = self._bias_began[1]
        covered = travelled >= began  # NaN (a map member): never covered
        for a, b in shortcuts:
            covered |= (travelled >= min(a, b)) & (travelled <= max(a, b))
        q[covered] = self._per_bias(sigma)
        return q

    def split_groups(self, estimate: PoseEstimate | None) -> int:
        """Split each group into the parts the estimate puts within the spatial gate of each other; new groups made.

        Two members may stay together when their map distance is within the gate radius of the
        (anchored) distance travelled between their sightings; a part holds members that may all
        stay together (:meth:`_parts`). Early in a run, before any loop, the gate is tens of metres wide and identical
        standard markings at different places (stop lines, chevrons) can join one group; once
        loops have corrected the estimate, their members lie far apart and the group is split:
        the part holding its first member keeps its id, the others get new ids. Groups seeded
        from a map are left alone.
        """
        index = self._index
        if not self._groups or index.size == 0:
            return 0
        positions = self._member_positions(estimate)
        shortcuts = self._anchoring(estimate) if self.params.anchored_gate else []
        rows = np.arange(index.size)
        made = 0
        for slot, group in enumerate(list(self._groups)):
            mine = rows[index.group[: index.size] == slot]
            if len(mine) < 2 or any(a is not None for a in group.anchors) or np.isnan(index.travelled[mine]).any():
                continue
            parts = self._parts(positions[mine], index.travelled[mine], shortcuts, estimate)
            if parts.max() == 0:
                continue
            keep = parts == 0  # holds the first member, whose offset (the group's orientation) is 0
            for label in range(1, int(parts.max()) + 1):
                taken = np.flatnonzero(parts == label)
                new = SgfGroup(self._next_id, aliased=group.aliased)
                self._next_id += 1
                base = group.offsets[taken[0]]
                for k in taken:
                    new.add(group.members[k], group.offsets[k] - base)
                new.refresh(self.params.columns, self.params.symmetry_threshold)
                self._slot[new.group_id] = len(self._groups)
                index.group[mine[taken]] = len(self._groups)
                self._groups.append(new)
                made += 1
            group.members = [m for m, k in zip(group.members, keep, strict=True) if k]
            group.offsets = [o for o, k in zip(group.offsets, keep, strict=True) if k]
            group.anchors = [a for a, k in zip(group.anchors, keep, strict=True) if k]
            group.refresh(self.params.columns, self.params.symmetry_threshold)
        return made

    def merge_groups(self, estimate: PoseEstimate | None) -> int:
        """Merge groups whose members the estimate puts at one place and that look alike there; merges made.

        The counterpart of :meth:`split_groups`: a revisit seen before any loop, while the gate
        reached several look-alike markings (a dash, a tactile bar), may have joined the wrong one's
        group and been split off at the end. Candidates are member pairs of two groups within
        ``merge_radius`` on the map whose eq. 10 distance, at the column shift the estimate
        predicts (within ``merge_yaw_deg``; any shift when both groups are symmetric), is at most
        ``merge_distance``. The closest pairs merge first, and only when every member of the
        merged group stays within the spatial gate of every other (the split would not undo it)
        and no two of the groups' members were seen within ``repeat_window`` of travel (one
        drive-by: two copies of a repeated pattern, kept apart online).
        Groups seeded from a map are left alone.
        """
        from scipy.spatial import cKDTree

        p, index = self.params, self._index
        n = index.size
        if len(self._groups) < 2 or n < 2:
            return 0
        positions = self._member_positions(estimate)
        slots = index.group[:n].copy()
        free = np.array([all(a is None for a in g.anchors) for g in self._groups])
        rows = np.flatnonzero(free[slots] & ~np.isnan(index.travelled[:n]))
        if len(rows) < 2:
            return 0
        near = cKDTree(positions[rows]).query_pairs(p.merge_radius, output_type="ndarray")
        first, second = rows[near[:, 0]], rows[near[:, 1]]
        apart = slots[first] != slots[second]
        member_at = np.zeros(n, dtype=np.int64)  # a row's index among its group's members (rows keep member order)
        for slot in np.unique(slots):
            member_at[slots == slot] = np.arange(int((slots == slot).sum()))
        candidates: list[tuple[float, int, int, int]] = []
        n_s = index.members[0].matrix.shape[1]
        window = round(math.radians(p.merge_yaw_deg) * n_s / (2.0 * math.pi))
        for a, b in zip(first[apart].tolist(), second[apart].tolist(), strict=True):
            if index.frame[b] < index.frame[a]:
                a, b = b, a
            ga, gb = self._groups[slots[a]], self._groups[slots[b]]
            if ga.symmetric != gb.symmetric:
                continue
            profile = shifted_distances(index.members[b].matrix, index.members[a].matrix[None], p.columns)[0]
            if not ga.symmetric:
                predicted = round(self._predicted_shift(index.members[b], index.members[a], estimate))
                allowed = np.full(n_s, np.inf)
                shifts = np.arange(predicted - window, predicted + window + 1) % n_s
                allowed[shifts] = profile[shifts]
                profile = allowed
            shift = int(np.argmin(profile))
            if profile[shift] <= p.merge_distance:
                candidates.append((float(profile[shift]), a, b, shift))
        shortcuts = self._anchoring(estimate) if p.anchored_gate else []
        made = 0
        for _, a, b, shift in sorted(candidates):
            sa, sb = int(slots[a]), int(slots[b])
            if sa == sb:
                continue
            in_a, in_b = slots == sa, slots == sb
            both = np.flatnonzero(in_a | in_b)
            seen_a, seen_b = index.travelled[:n][in_a], index.travelled[:n][in_b]
            if np.abs(seen_a[:, None] - seen_b[None, :]).min() < p.repeat_window:
                continue  # seen on one drive-by: two markings (a repeated pattern's copies), not a revisit
            if self._parts(positions[both], index.travelled[both], shortcuts, estimate).max() > 0:
                continue
            ga, gb = self._groups[sa], self._groups[sb]
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
            ga.refresh(p.columns, p.symmetry_threshold)
            made += 1
        if made:
            kept = [k for k, g in enumerate(self._groups) if g.members]
            renumber = np.full(len(self._groups), -1, dtype=np.int64)
            renumber[kept] = np.arange(len(kept))
            index.group[:n] = renumber[slots]
            self._groups = [self._groups[k] for k in kept]
            self._slot = {g.group_id: k for k, g in enumerate(self._groups)}
        return made

    def _parts(
        self,
        positions: np.ndarray,
        travelled: np.ndarray,
        shortcuts: list[tuple[float, float]],
        estimate: PoseEstimate | None = None,
    ) -> np.ndarray:
        """Parts (labels from 0, in order of first member) whose members are all within the gate of each other.

        Agglomerative, closest pairs (by map distance over gate radius) first; two parts merge only
        when every pair across them is within the gate (complete linkage), so a member seen long
        after the last loop, with a gate wide enough to reach two places, does not chain them.
        """
        n = len(positions)
        distance = np.hypot(*(positions[:, None, :] - positions[None, :, :]).transpose(2, 0, 1))
        anchored = np.stack([anchored_distances(float(t), travelled, shortcuts) for t in travelled])
        quadratic = self._quadratic(travelled, shortcuts, estimate)
        ratio = distance / self._gate_radius(anchored, np.maximum(quadratic[:, None], quadratic[None, :]))
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

    # -- eq. 10 ------------------------------------------------------------------------------

    def _prior_shift(self, query: SgfDescriptor, member: SgfDescriptor, estimate: PoseEstimate | None) -> float | None:
        """The column shift that the pose estimate predicts between two sightings (None for map members)."""
        if self.params.yaw_tolerance <= 0.0:
            return None
        return self._predicted_shift(query, member, estimate)

    def _predicted_shift(self, query: SgfDescriptor, member: SgfDescriptor, estimate: PoseEstimate | None) -> float:
        """The (fractional) column shift of the query against the member that their map poses predict."""
        yaw = xy_yaw(self.map_pose(query, estimate))[2] - xy_yaw(self.map_pose(member, estimate))[2]
        return yaw_to_shift(yaw, query.matrix.shape[1])

    def assign(self, query: SgfDescriptor, estimate: PoseEstimate | None = None) -> GroupAssignment:
        """Assign one descriptor to its SGF group (eq. 10), creating a group when none is close enough."""
        p = self.params
        n_s = query.matrix.shape[1]
        candidates = self.gated(query, estimate)
        best: tuple[SgfGroup, float] | None = None
        opened_distance = 1.0  # reported when the query opens a group and no group was kept
        tied: list[GatedGroup] = []
        gated_members: np.ndarray | None = None
        copy_nearby = False
        if candidates:
            stack = np.stack([c.group.descriptor for c in candidates])
            if stack.shape[1:] != query.matrix.shape:
                raise ValueError(
                    f"descriptor shape {query.matrix.shape} differs from the groups' {stack.shape[1:]}; "
                    "all SGF descriptors of a run (and of a seeded map) need the same N_r and N_s"
                )
            if p.group_distance == "mean":
                eq10 = shifted_distances(query.matrix, stack, p.columns, p.min_overlap).min(axis=1)
            else:
                eq10 = self._nearest_member_distances(
                    query, [c.group for c in candidates], [c.members for c in candidates]
                )
            # Where the estimate puts the query counts too: a group at the gate's edge pays position_weight.
            score = eq10 + p.position_weight * np.array([c.ratio for c in candidates])
            self._rank_own_group(query, candidates, score)
            # A look-alike group just seen elsewhere is a neighbouring copy of a repeated pattern
            # (give-way triangles, dashes): the query may not join it, and neither gives loop factors.
            copy = np.array([c.repeated for c in candidates]) & (
                self._copy_distances(query, candidates, eq10) <= p.copy_distance
            )
            for i in np.flatnonzero(copy):
                candidates[i].group.aliased = True
            copy_nearby = bool(copy.any())
            best_kept = score[~copy].min() if not copy.all() else math.inf
            if p.copies == "new" and copy_nearby and score[copy].min() <= best_kept + p.tie_margin:
                # The query is one more copy of the pattern here, not a revisit elsewhere: a group of its own.
                opened_distance = float(eq10.min())
            elif not copy.all():
                ties = np.flatnonzero(~copy & (score <= best_kept + p.tie_margin))
                ties = self._closable_ties(query, candidates, ties)
                i = int(min(ties, key=lambda t: candidates[t].nearest))
                best = (candidates[i].group, float(eq10[i]))
                # Look-alike groups inside the gate (identical standard markings) cannot be told apart
                # by eq. 10: the query joins the nearest, the match is ambiguous, and the others are
                # handed on as alternatives (a loop stage may tell them apart by their neighbours).
                tied = [candidates[t] for t in ties if t != i]
                gated_members = candidates[i].members
        if best is None or best[1] > p.new_group_distance:
            group = SgfGroup(self._next_id, aliased=copy_nearby)
            self._next_id += 1
            group.add(query, 0)
            self._index.add(len(self._groups), query, self._frames.get_distance(query.sgf.frame_index), None)
            group.refresh(p.columns, p.symmetry_threshold)
            self._slot[group.group_id] = len(self._groups)
            self._groups.append(group)
            distance = opened_distance if best is None else best[1]
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
        group, best_distance = best
        group.aliased = group.aliased or copy_nearby
        m, matched, shift = self._closest_member(query, group, estimate, gated_members)
        # An aliased look-alike (a repeated pattern) could be the true one: then nothing resolves the tie.
        alternatives = (
            () if any(g.group.aliased for g in tied) else tuple(self._look_alike(query, g, estimate) for g in tied)
        )
        group.add(query, shift + group.offsets[m])
        self._index.add(self._slot[group.group_id], query, self._frames.get_distance(query.sgf.frame_index), None)
        group.refresh(p.columns, p.symmetry_threshold)
        # A flat group mean may only be a smear of members from different markings: the match is
        # symmetric when one of its two own views is flat too. Two flat views are symmetric whatever
        # the group's mean (a round manhole in a group that also took a shaped view): no yaw to fit.
        spreads = (symmetry_spread(query.matrix, p.columns), symmetry_spread(matched.matrix, p.columns))
        symmetric = (group.symmetric and min(spreads) < p.symmetry_threshold) or max(spreads) < p.symmetry_threshold
        return GroupAssignment(
            descriptor=query,
            group_id=group.group_id,
            new_group=False,
            distance=best_distance,
            shift=shift,
            yaw=shift_to_yaw(shift, n_s),
            matched=matched,
            symmetric=symmetric,
            ambiguous=group.aliased or bool(tied),
            aliased=group.aliased,
            alternatives=alternatives,
        )

    def _closable_ties(self, query: SgfDescriptor, candidates: list[GatedGroup], ties: np.ndarray) -> np.ndarray:
        """The tied groups a match could close a loop with: a shaped query leaves out the symmetric ones.

        A query whose own profile is not flat matched into a symmetric group (a round manhole
        whose closest member is flat) gives no loop factor. When it ties with a group it could
        close with (its own marking, ranked level by the position weight), that group takes it.
        """
        p = self.params
        if len(ties) < 2 or symmetry_spread(query.matrix, p.columns) < p.symmetry_threshold:
            return ties
        closable = [t for t in ties if not self._symmetric_match(query, candidates[t])]
        return np.asarray(closable, dtype=np.int64) if closable else ties

    def _symmetric_match(self, query: SgfDescriptor, gated: GatedGroup) -> bool:
        """Whether a match of a shaped query into this gated group would be symmetric (its closest member flat)."""
        if not gated.group.symmetric:
            return False
        m, _ = self._nearest_member(query, gated.group, gated.members)
        return symmetry_spread(gated.group.members[m].matrix, self.params.columns) < self.params.symmetry_threshold

    def _rank_own_group(self, query: SgfDescriptor, candidates: list[GatedGroup], score: np.ndarray) -> None:
        """Count whether the ranking ranks the group of the query's own marking (its members' majority) first.

        The ranking is eq. 10, plus ``position_weight`` times the gate ratio when that is set. Only
        labelled queries whose own group and another one are both gated count: the share ranked
        first measures how well the association tells markings apart on this run.
        """
        instance = query.sgf.instance_id
        if instance is None:
            return
        own = np.array([_majority_instance(c.group) == instance for c in candidates])
        if own.any() and not own.all():
            self._ranked[0] += 1
            self._ranked[1] += int(score[own].min() < score[~own].min())

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

    def _nearest_member_distances(
        self, query: SgfDescriptor, groups: list[SgfGroup], members: list[np.ndarray | None] | None = None
    ) -> np.ndarray:
        """Eq. 10 distance (best shift) from the query to each group's closest member (of ``members``, when given)."""
        members = [None] * len(groups) if members is None else members
        chosen = [g.matrices if m is None else g.matrices[m] for g, m in zip(groups, members, strict=True)]
        p = self.params
        per_member = shifted_distances(query.matrix, np.concatenate(chosen), p.columns, p.min_overlap).min(axis=1)
        starts = np.cumsum([0] + [len(c) for c in chosen[:-1]])
        return np.minimum.reduceat(per_member, starts)

    def _closest_member(
        self, query: SgfDescriptor, group: SgfGroup, estimate: PoseEstimate | None, members: np.ndarray | None = None
    ) -> tuple[int, SgfDescriptor, int]:
        """The group member (of ``members``, when given) closest to the query by eq. 10, its index, and the shift."""
        m, profile = self._nearest_member(query, group, members)
        matched = group.members[m]
        prior = None if group.anchors[m] is not None else self._prior_shift(query, matched, estimate)
        return m, matched, best_shift(profile, prior, self.params.yaw_tolerance)

    def _nearest_member(
        self, query: SgfDescriptor, group: SgfGroup, members: np.ndarray | None = None
    ) -> tuple[int, np.ndarray]:
        """The index of the group member (of ``members``, when given) closest by eq. 10, and its shift profile."""
        p = self.params
        candidates = np.arange(len(group.members)) if members is None else members
        profiles = shifted_distances(query.matrix, group.matrices[candidates], p.columns, p.min_overlap)
        k = int(np.argmin(profiles.min(axis=1)))
        return int(candidates[k]), profiles[k]

    def _look_alike(self, query: SgfDescriptor, gated: GatedGroup, estimate: PoseEstimate | None) -> LookAlike:
        """A tied group's closest member, as an alternative match of the query."""
        _, matched, shift = self._closest_member(query, gated.group, estimate, gated.members)
        return LookAlike(gated.group.group_id, matched, shift, shift_to_yaw(shift, query.matrix.shape[1]))

    def process(
        self,
        frame: Frame,
        descriptors: SgfDescriptors,
        estimate: Previous[PoseEstimate],
        loops: Previous[LoopConstraints] = None,
    ) -> GroupAssignments:
        """Group this frame's SGF descriptors."""
        self._record(frame)
        self._remember_loops(loops)
        if estimate is not None:
            self._estimate = estimate
        return GroupAssignments(tuple(self.assign(d, estimate) for d in descriptors.items))

    # -- evaluation ---------------------------------------------------------------------------

    def conclude(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Regroup at the end of the run; hands on the final groups (``settlement.groups``, ``settlement.group_of``).

        With ``split_at_end`` the groups are split by the newest estimate (:meth:`split_groups`: the
        back-end's ``settlement.estimate``, re-solved without the loops taken back, when it re-solved
        one), and with ``merge_at_end`` look-alikes it puts at one place merged (:meth:`merge_groups`).
        ``group_of`` maps each run member's ``(frame_index, track_id)`` to its final group, for the
        loop stage's final pass and the SGF map.
        """
        online = _settled(self._groups)
        estimate = settlement.estimate if settlement.estimate is not None else self._estimate
        split = merged = None
        if self.params.split_at_end and self.params.spatial_gate:
            split = self.split_groups(estimate)
        if self.params.merge_at_end:
            merged = self.merge_groups(estimate)
        self._end = (online, split, merged)
        group_of = {
            (m.sgf.frame_index, m.sgf.track_id): g.group_id
            for g in self._groups
            for m, a in zip(g.members, g.anchors, strict=True)
            if a is None
        }
        return replace(settlement, groups=_settled(self._groups), group_of=group_of)

    def finalize(self, context: RunContext) -> None:
        """Publish the groups (``artifacts['sgf_groups']``) and write purity and loop-pair metrics.

        ``purity_online`` and ``pairs_found_online`` are from before the split and merge at the end
        (:meth:`conclude`, run here first when the run ended without it).
        """
        if self._end is None:
            self.conclude(context, Settlement())
        assert self._end is not None
        online_groups, split, merged = self._end
        sgf: dict[str, Any] = context.metrics.setdefault("sgf", {})
        online = group_purity(online_groups) if context.truth is not None else None
        online_pairs = loop_pairs(online_groups, context.truth) if context.truth is not None else None
        if split is not None:
            sgf["groups_split"] = split
        if merged is not None:
            sgf["groups_merged"] = merged
        context.artifacts["sgf_groups"] = list(self._groups)
        sgf["groups"] = len(self._groups)
        sgf["symmetric_groups"] = sum(1 for g in self._groups if g.symmetric)
        sgf["aliased_groups"] = sum(1 for g in self._groups if g.aliased)
        sgf["purity"] = None
        loops: dict[str, Any] = context.metrics.setdefault("loops", {})
        loops.update(
            {"pairs_found": None, "pairs_total": None, "pairs_found_reverse": None, "pairs_total_reverse": None}
        )
        if context.truth is not None:
            sgf["purity"] = group_purity(self._groups)
            sgf["purity_online"] = online
            decisions, first = self._ranked
            sgf["own_group_ranked_first"] = {"decisions": decisions, "share": first / decisions if decisions else None}
            sgf["mixed_groups"] = sum(1 for g in self._groups if len(_instance_counts(g)[0]) > 1)
            loops.update(loop_pairs(self._groups, context.truth))
            assert online_pairs is not None
            loops["pairs_found_online"] = online_pairs["pairs_found"]


def _settled(groups: Iterable[SgfGroup]) -> tuple[SettledGroup, ...]:
    """The groups as the end of the run hands them on (members frozen as they are now)."""
    return tuple(SettledGroup(g.group_id, tuple(g.members), g.symmetric) for g in groups)


def _odometry_position(member: SgfDescriptor) -> np.ndarray:
    """Map position of a member's centroid under its own odometry pose (the frame of the session that saw it)."""
    pose = np.asarray(member.sgf.odometry, dtype=np.float64)
    return pose[:2, :2] @ np.asarray(member.centroid[:2], dtype=np.float64) + pose[:2, 3]


def _instance_counts(group: SgfGroup | SettledGroup) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth instances of a group's labelled members (sorted) and how many members show each."""
    return np.unique([m.sgf.instance_id for m in group.members if m.sgf.instance_id is not None], return_counts=True)


def _majority_instance(group: SgfGroup) -> int | None:
    """The ground-truth instance most of a group's labelled members show (None when none is labelled)."""
    values, counts = _instance_counts(group)
    return int(values[np.argmax(counts)]) if len(values) else None


def group_purity(groups: Iterable[SgfGroup | SettledGroup]) -> float | None:
    """Share of ground-truth-labelled members that carry their group's majority instance (None if no labels)."""
    majority = total = 0
    for group in groups:
        _, counts = _instance_counts(group)
        if len(counts):
            majority += int(counts.max())
            total += int(counts.sum())
    return majority / total if total else None


def loop_pairs(groups: Iterable[SgfGroup | SettledGroup], truth: SequenceTruth) -> dict[str, int]:
    """Revisit pairs found (Table 3): SGFs of the pair's instance from both passes share a group."""
    together: set[tuple[int, int, int]] = set()
    for group in groups:
        passes: set[MarkingPass] = set()
        for member in group.members:
            if member.sgf.instance_id is not None:
                drive_by = truth.drive_by(member.sgf.instance_id, member.sgf.frame_index)
                if drive_by is not None:
                    passes.add(drive_by)
        for pair in truth.revisits:
            if pair.first in passes and pair.second in passes:
                together.add((pair.instance_id, pair.first.number, pair.second.number))
    found = [(p, (p.instance_id, p.first.number, p.second.number) in together) for p in truth.revisits]
    return {
        "pairs_found": sum(1 for _, ok in found if ok),
        "pairs_total": len(found),
        "pairs_found_reverse": sum(1 for p, ok in found if ok and p.reverse),
        "pairs_total_reverse": sum(1 for p, _ in found if p.reverse),
    }


def groups_from_map(sgf_map: Any, columns: ColumnSet = "intersection") -> list[SgfGroup]:
    """SGF groups of a saved map, members anchored at their optimized map positions (for ``seed_groups``)."""
    groups = []
    for map_group in sgf_map.groups:
        group = SgfGroup(map_group.group_id)
        first = None
        for view in map_group.views:
            member = view.descriptor()
            offset = 0
            if first is None:
                first = member
            else:
                offset = best_shift(shifted_distances(member.matrix, first.matrix[None], columns)[0])
            anchor = (
                member.map_pose[:2, :2] @ np.asarray(member.centroid, dtype=np.float64)[:2] + member.map_pose[:2, 3]
            )
            group.add(member, offset, anchor)
        if group.members:
            groups.append(group)
    return groups


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the online SGF grouping."""
    registry.add(OnlineSgfGroups)
