"""Loop closing with SGF factors (paper Sec. III-D): ICP between an SGF and its group's closest member.

When a new SGF joins a group holding an SGF from an earlier pass (``GroupAssignment.matched``;
when the association matched a view of the same pass, the group's closest member from an earlier
pass), their point sets are aligned by 2-D ICP seeded by the relative yaw of the best column shift
(so reverse loops converge) and by the centroids. ``GroupAssignment.yaw`` is read as the
rotation (rad, counter-clockwise) that turns the new SGF's points about their centroid onto
the matched SGF's; with ``seed_both_signs`` the opposite sign is tried too, so the
association's sign convention does not matter (one more ICP of ~300 points, a few ms), and
``yaw_probe_deg`` either side of each seed as well: a long, thin marking fixes its heading weakly,
ICP stops on either wall of that shallow valley, and the loop takes the middle of its stops.
A converged alignment with a low RMS residual and a high two-way inlier ratio becomes a
relative-pose constraint between the two frames, unless the current estimate says it cannot
be the same place (the gate below). Symmetric groups (a round manhole) never give loop factors.

The gate: the relative pose predicted by the previous frame's estimate (odometry before the
back-end's first estimate) is compared with ICP's by a chi-square test whose covariance is
ICP's plus a drift term that grows with ``d``, the distance the estimate has travelled since a
loop closure last anchored the two poses: ``sigma_xy^2 = floor^2 + (scale d)^2 + sxy^2 d +
syaw^2 d^3 / 3 + (bias d^2 / 2)^2`` (translation random walk, heading random walk, scale error,
heading bias) and ``sigma_yaw^2 = floor^2 + syaw^2 d + (bias d)^2``. ``bias`` comes from the
back-end's model of the heading bias (``PoseEstimate.yaw_bias``, which the association's gate
shares): the uncertainty of the bias left where the back-end takes its estimate off the odometry
and the corrected drive spans all of ``d``, else the bias as the camera and the loops measured it
so far (before any measurement, the bias wheel odometry is expected to have), so the gate narrows
as much as the drift it predicts. ``d`` is the shortest odometry path between the two frames in a graph
where each accepted loop that the estimate satisfies (the back-end has absorbed it) joins its
two frames at no cost; a loop that the back-end did not absorb (``backend=none``, batch
optimisation only at the end, a loop down-weighted by the robust kernel) anchors nothing, so
the gate stays as loose as the dead-reckoned drift. This makes a look-alike marking elsewhere
fail the test once the estimate is better than the distance between the look-alikes.

Look-alike markings (the campus repeats standard ones) defeat eq. 10 and, while the drift is
larger than their spacing, the gate too. The association then reports the match as ambiguous with
the tied groups as ``alternatives``; each option is put through ICP and the gate, and then
through the neighbour consensus (:meth:`IcpLoopClosing._support`): the SGFs seen in the last
``consensus_window`` metres, carried by the locally accurate odometry and the option's ICP pose
into the earlier pass, must land on look-alike SGFs of that pass (with ``consensus_heading_deg``
set, look-alike at the heading the match predicts for them, and a neighbour that looks alike
turned half a turn too, a bar or a disc, fixes no heading and counts
``consensus_unoriented_weight``; off by default, see docs/measurements.md). A neighbour of a common
design (look-alikes in more than ``consensus_common_groups`` other groups, 3 by default) counts that
limit over their number: a wrong match finds copies of a common design where it predicts them by
chance, and at a crossing laid out like another one, several at once (it can also refuse a true
loop whose one agreeing neighbour is common; docs/measurements.md). The one option with at
least ``tie_support`` agreeing markings wins; none or several, and the match gives no factor.
``min_support`` asks the same of every loop, except a match into a distinct marking: one the
query looks like (eq. 10 within ``consensus_distance``) while no SGF of any other group comes within
``distinct_distance`` of it. Such a marking (a custom one, painted once) vouches for itself and
needs ``distinct_support`` agreeing neighbours (0 by default: ICP and the gate decide), so a route
that revisits one marking only (campus_delivery) can close its loop. The risk it takes is the
second copy of a repeated design met before any third copy made it look common; the gate is what
stands against that, and only while it predicts the match within ``distinct_gate_sigma`` metres (a
gate wider than the campus cannot). Once loops have anchored the estimate, the gate itself tells a
design's copies apart: a match the gate predicts within ``gate_support_sigma`` metres needs no
neighbours either, unless an SGF of another group that looks like the query was seen within the
gate's reach of the matched one and could be what the query saw: matched to it, the query would
pass ICP and the gate too (``gate_support_alternatives``), and it is not a round marking against a
shaped one (``gate_support_round``; :meth:`IcpLoopClosing._gate_decides`); a tie that the gate
leaves one option of is resolved the same way. With ``consensus_wait`` (the default), a match that has too few
agreeing neighbours so far waits while the robot drives ``consensus_window`` metres on, and the
SGFs seen after it count too: the first marking of a revisit (a reverse one above all, entered
from a stretch never driven before) has no neighbour behind it that both passes saw. A neighbour
tens of metres from its sighting lies off by the odometry's drift over that path; the consensus
tolerance grows with it, linearly (``consensus_drift``) and, for the heading bias that bends each
pass, quadratically (``consensus_heading_bias``: by the bias the back-end's model holds).

A match into an aliased group (a repeated pattern: dashes, chevrons, bars) may be with the wrong
copy, one period away, where the pattern's other copies agree with it too; it needs
``aliased_support`` agreeing markings that do not look like the query, each within half the
period of the copies seen around it (0: aliased groups never give loop factors). When ICP
finds several distinct near-equal fits (a twofold symmetric shape turned by 180 degrees, a row
laid on itself one period on), the gate must leave exactly one, else the match is
``not_unique`` (:meth:`IcpLoopClosing._fits`).

On a prior SGF map (``matched`` is a :class:`~sgf_pipeline.sgf_map.MapDescriptor`), a match is
an inter-session constraint (``from_map``). Before the run is anchored in the map frame there is
no prediction: the first ``map_anchor_matches`` matches of different map groups must agree with
each other (the map-implied relative pose between their frames against the run's own estimate,
same test); afterwards map matches are gated like loops, the map acting as one anchored node.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from pydantic import Field

from sgf_pipeline import Previous, RunContext, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.geometry import invert, wrap_angle, xy_yaw
from sgf_pipeline.sgf_map import MapDescriptor
from sgf_pipeline.stage import Settlement
from sgf_pipeline.types import (
    Frame,
    GroupAssignment,
    GroupAssignments,
    LoopConstraint,
    LoopConstraints,
    PoseEstimate,
    RevisitPair,
    SequenceTruth,
    SgfDescriptor,
)
from sgf_plugins.backend.heading_bias import EXPECTED_YAW_BIAS, corrected_yaw_bias, uncorrected_yaw_bias
from sgf_plugins.loop.consistency import (
    LoopEnds,
    bias_corrected_path,
    consistency_ratios,
    inconsistent_loops,
    loop_heading_bias,
)
from sgf_plugins.loop.icp import Icp2d, IcpResult, IcpSettings, centroid_seed, se2, se2_params
from sgf_plugins.odometry.anchoring import anchored_distances
from sgf_plugins.odometry.frame_log import FrameLog
from sgf_plugins.sgf.polar import best_shift, shift_to_yaw, shifted_distances, yaw_to_shift

_MAP = -1  # the prior map as one node of the anchoring graph
#: Two ICP fits that put the query's points further apart than this (RMS, m) are distinct fits of one match.
FIT_TOLERANCE_M = 0.25
#: ...and closer than this (RMS, m) they are the same stop of ICP, counted once.
SAME_FIT_M = 0.005
#: Look-alike SGFs nearer each other than this (m) are one marking seen twice, not two copies of a pattern.
COPY_MIN_SPACING_M = 0.5


class IcpLoopParams(StageParams):
    """Parameters of ICP loop closing, its acceptance tests and the uncertainty gate."""

    metric: Literal["point_to_point", "point_to_line"] = Field(
        "point_to_point", description="ICP error: point_to_point suits filled SGF regions, point_to_line outlines"
    )
    max_iterations: int = Field(100, ge=1, description="ICP iterations per round (coarse, then inliers only)")
    max_correspondence_distance: float = Field(0.5, gt=0.0, description="pairing distance of the coarse round (m)")
    inlier_distance: float = Field(0.1, gt=0.0, description="a point is an inlier within this distance (m)")
    tolerance: float = Field(1e-6, gt=0.0, description="converged when an ICP step is below this (m and rad)")
    normal_neighbours: int = Field(
        8, ge=3, description="neighbours of the target line normals (point_to_line, ICP covariance)"
    )
    min_points: int = Field(20, ge=3, description="fewer SGF points than this on either side: no ICP")
    max_fitness: float = Field(0.03, gt=0.0, description="reject when the RMS inlier residual exceeds this (m)")
    min_inlier_ratio: float = Field(
        0.85, gt=0.0, le=1.0, description="reject when fewer points of either set have a partner within inlier_distance"
    )
    degenerate_sigma: float = Field(
        0.05,
        gt=0.0,
        description="reject when ICP's Hessian leaves a direction this uncertain (m or rad): a bar, a line",
    )
    seed_both_signs: bool = Field(
        True, description="also seed ICP with the negated column-shift yaw (robust to the shift's sign convention)"
    )
    extra_yaw_seeds: int = Field(
        1, ge=0, le=16, description="further seeds evenly spaced in yaw around the first (1: its half-turn alternative)"
    )
    yaw_probe_deg: float = Field(
        5.0,
        ge=0.0,
        le=30.0,
        description="ICP is also seeded this far (deg) either side of each yaw seed; what it finds there only refines "
        "the seeds' own fits (the middle of a shallow valley in yaw, and its width in the covariance) (0: off)",
    )
    max_fit_spread_deg: float | None = Field(
        10.0,
        gt=0.0,
        description="ICP fits of one alignment (within FIT_TOLERANCE_M of each other on the marking) further apart "
        "in yaw than this: the marking fixes its place but not its heading, no factor (null: their mean, any spread)",
    )
    ambiguity_ratio: float = Field(
        1.25,
        ge=1.0,
        description="seeds within this factor of the best RMS are ambiguous; the one nearest the prediction wins",
    )
    min_separation_frames: int = Field(0, ge=0, description="the matched SGF must be at least this many frames earlier")
    min_separation_time: float = Field(0.0, ge=0.0, description="...and this many seconds earlier")
    min_separation_distance: float = Field(10.0, ge=0.0, description="...and this far back along the odometry path (m)")
    covariance_floor_xy: float = Field(0.025, gt=0.0, description="added to ICP's translation sigma (m): IPM, sampling")
    covariance_floor_yaw_deg: float = Field(1.5, gt=0.0, description="added to ICP's yaw sigma (deg)")
    covariance_range_xy: float = Field(
        0.0052,
        ge=0.0,
        description="added translation sigma per axis (m) per squared metre of each view's range from the robot: "
        "the BEV's ground error grows as the square of the distance (0 = the floor alone)",
    )
    gate: bool = Field(True, description="chi-square test of the ICP pose against the estimate's prediction")
    gate_probability: float = Field(0.999, gt=0.0, lt=1.0, description="chi-square (3 dof) acceptance probability")
    gate_floor_xy: float = Field(0.5, gt=0.0, description="prediction sigma when freshly anchored (m)")
    gate_floor_yaw_deg: float = Field(3.0, gt=0.0, description="prediction sigma when freshly anchored (deg)")
    gate_sigma_xy: float = Field(0.05, ge=0.0, description="translation random walk of the drift (m per sqrt(m))")
    gate_sigma_yaw_deg: float = Field(
        0.1,
        ge=0.0,
        description="heading random walk of the drift (deg per sqrt(m)); the campus robot's odometry, with margin "
        "(a robot whose heading wanders more sets its own)",
    )
    gate_scale_error: float = Field(0.02, ge=0.0, description="odometry scale error (fraction of distance)")
    gate_bias_from_backend: bool = Field(
        True,
        description="the gate counts the heading bias as the back-end's model holds it (the uncertainty left where "
        "it corrects the odometry, the measured bias elsewhere); false = the bias wheel odometry is expected to have",
    )
    gate_bridged_bias: bool = Field(
        True,
        description="a matched frame between the two frames of an absorbed loop has had the heading bias taken off "
        "by the pose graph: the gate's bias term counts only the drive since the newest absorbed loop",
    )
    consensus_window: float = Field(
        60.0, gt=0.0, description="m of travel: SGFs seen this far around each sighting are its neighbours"
    )
    consensus_radius: float = Field(
        0.75, gt=0.0, description="a neighbour agrees when the match puts it this close (m) to an earlier SGF..."
    )
    consensus_drift: float = Field(
        0.02, ge=0.0, description="...plus this much per metre travelled from either sighting (local odometry drift)"
    )
    consensus_heading_bias: bool = Field(
        True,
        description="...plus the odometry's heading bias (the back-end's model): 0.5 * bias * L**2 per sighting "
        "L m away",
    )
    consensus_exclude: float = Field(
        2.0, ge=0.0, description="neighbours this close (m) to the matched SGF are the same marking, not evidence"
    )
    consensus_distance: float = Field(
        0.15, gt=0.0, le=1.0, description="...and look like it: eq. 10 distance at most this"
    )
    consensus_heading_deg: float | None = Field(
        None,
        gt=0.0,
        le=180.0,
        description="a neighbour agrees only when it looks alike at the heading the match predicts for it, within "
        "this (deg); null: at any heading (rotation-invariant eq. 10)",
    )
    consensus_unoriented_weight: float = Field(
        0.5,
        ge=0.0,
        le=1.0,
        description="a neighbour that looks alike at the opposite heading too (a bar, a disc) fixes no heading: it "
        "counts this much of an agreeing marking",
    )
    consensus_common_groups: int | None = Field(
        3,
        ge=1,
        description="a neighbour whose design has look-alikes (eq. 10 at most consensus_distance) in more than this "
        "many other groups is common: it counts this many over their number, since a wrong match finds one of its "
        "copies where it predicts by chance (null = every neighbour counts fully)",
    )
    tie_support: int = Field(
        1,
        ge=0,
        description="look-alike groups tied by eq. 10: the one match with at least this many agreeing neighbours "
        "wins (0 = tied matches never give loop factors)",
    )
    min_support: int = Field(1, ge=0, description="agreeing neighbours every loop needs (0 = ICP and the gate only)")
    distinct_support: int | None = Field(
        0,
        ge=0,
        description="agreeing neighbours a loop into a distinct marking needs: one the query looks like (eq. 10 at "
        "most consensus_distance) and that no SGF of another group looks like (all farther than distinct_distance); "
        "null = min_support",
    )
    distinct_gate_sigma: float | None = Field(
        50.0,
        gt=0.0,
        description="m: a distinct marking vouches for itself only while the gate predicts the match this tightly "
        "(a wider gate cannot tell a copy never seen from the marking; null: at any sigma)",
    )
    distinct_distance: float = Field(
        0.15, ge=0.0, le=1.0, description="eq. 10: an SGF of another group this close makes a marking not distinct"
    )
    distinct_ratio: float | None = Field(
        None,
        gt=1.0,
        description="...unless it is this many times farther (eq. 10) than the match and farther than "
        "distinct_floor: the query is far more like its match than like anything else seen (null: off)",
    )
    distinct_floor: float = Field(
        0.05, ge=0.0, le=1.0, description="eq. 10: an SGF of another group this close always makes a marking common"
    )
    gate_support_sigma: float | None = Field(
        5.0,
        gt=0.0,
        description="a match the gate predicts within this position sigma (m) needs no agreeing neighbours, unless an "
        "SGF of another group that looks like the query (eq. 10 at most consensus_distance) was seen within the "
        "gate's reach of the matched one: ICP and the gate decide (null = min_support always)",
    )
    gate_support_alternatives: bool = Field(
        True,
        description="a look-alike within the gate's reach stands against the match only when the query matched to "
        "it would pass ICP and the gate too; false: any SGF alike by eq. 10 within the reach does",
    )
    gate_support_round: bool = Field(
        True,
        description="a look-alike in a symmetric group (a round manhole) never stands against a match into a "
        "shaped group",
    )
    symmetric_loops: bool = Field(
        True,
        description="a match into a symmetric group (a round manhole, whose heading cannot be read) gives a "
        "position-only loop: where the marking's centre lies from both poses, the turn left free; closed only when "
        "the gate alone decides (gate_support_sigma); false = no factor",
    )
    position_only_yaw_sigma_deg: float = Field(
        90.0, gt=0.0, description="a position-only loop's sigma of the turn about its marking (deg): nearly free"
    )
    consensus_wait: bool = Field(
        True,
        description="a match short of agreeing neighbours waits while the robot drives consensus_window metres on: "
        "SGFs seen after it count too (false = decide on the SGFs seen before it)",
    )
    consistency_threshold: float | None = Field(
        3.0,
        gt=0.0,
        description="at the end of the run, accepted loops outside the largest set whose pairwise cycles through "
        "the odometry (the heading bias the loops measure taken off) agree within this (position error over 1 m + "
        "5 % of the path between their ends) are listed in metrics.json as loops.consistency and, with "
        "drop_inconsistent, taken back (null: no test)",
    )
    consistency_yaw_bias_sigma_deg_per_m: float = Field(
        0.5,
        gt=0.0,
        description="the test's estimate of the odometry's heading bias, as the back-end's: its prior sigma "
        "(deg per metre; the config takes backend.odometry_yaw_bias_sigma_deg_per_m)",
    )
    consistency_yaw_bias_reading_sigma_deg_per_m: float = Field(
        0.1,
        gt=0.0,
        description="...the bias odometry is expected to have, which chooses between readings of the loops' turns "
        "(the config takes backend.odometry_yaw_bias_reading_sigma_deg_per_m)",
    )
    consistency_odometry_sigma_yaw_deg: float = Field(
        0.5,
        gt=0.0,
        description="...the odometry's heading sigma over one metre (the config takes backend.odometry_sigma_yaw_deg)",
    )
    consistency_kernel_width: float = Field(
        3.0,
        gt=0.0,
        description="...and its Cauchy kernel width in sigmas (the config takes backend.loop_kernel_width)",
    )
    drop_inconsistent: bool = Field(
        True,
        description="take the loops outside the largest consistent set back out of the estimate before the "
        "association's split and merge at the end (and the final pass's, before the last optimisation; "
        "false: only list them)",
    )
    final_pass: bool = Field(
        True,
        description="at the end of the run, match once more the members of each final SGF group (after the "
        "association's split and merge) from two drive-bys that no loop joins yet, against the final estimate; "
        "a match is closed when ICP passes and the gate alone decides it (gate_support_sigma)",
    )
    aliased_support: int = Field(
        2,
        ge=0,
        description="a match into an aliased group (a repeated pattern) needs this many agreeing neighbours that do "
        "not look like the query, so that no copy of the pattern vouches for another, each within half the pattern's "
        "period (0 = aliased groups never give loop factors)",
    )
    map_anchor_matches: int = Field(
        2, ge=1, description="consistent map matches (different groups) needed before a run is placed in the map"
    )
    map_pending: int = Field(16, ge=1, description="unconfirmed map matches kept while waiting for the anchor")
    truth_tolerance_xy: float = Field(0.5, gt=0.0, description="a loop off the ground truth by more (m) is false")
    truth_tolerance_yaw_deg: float = Field(5.0, gt=0.0, description="...or by more than this (deg)")


@dataclass(frozen=True)
class _GateReading:
    """What the gate saw of a match (``loop_candidates.csv``): distance since the anchor, sigma, chi-square."""

    distance: float  # m of travel since a loop last anchored the two frames (``d`` above)
    sigma_xy: float  # the prediction's position sigma (m) from the drift model
    chi2: float  # the best fit's squared Mahalanobis distance to the prediction


@dataclass(frozen=True)
class _Candidate:
    """A constraint that passed ICP, with what the gate and the map anchoring need."""

    constraint: LoopConstraint
    map_pose: np.ndarray | None
    map_truth: np.ndarray | None
    group_id: int
    anchored: bool = False  # a map match made once the run was placed in the map
    gate: _GateReading | None = None


@dataclass(frozen=True)
class _Waiting:
    """A match that passed ICP and the gate and waits for agreeing neighbours (``consensus_wait``).

    ``options`` are the candidates of the match (one, or the look-alikes of a tie that passed);
    the one with ``need`` agreeing neighbours wins. ``refused`` names the count of a match that
    expires, ``resolved`` the counter of one that is settled (ties, aliases).
    """

    options: tuple[tuple[GroupAssignment, _Candidate], ...]
    need: int
    unlike: bool
    refused: str
    resolved: str | None
    distance: float


def drift_covariance(
    distance: float, p: IcpLoopParams, yaw_bias: float = EXPECTED_YAW_BIAS, bias_distance: float | None = None
) -> np.ndarray:
    """Covariance (x, y, yaw) of a relative pose predicted across ``distance`` metres since the last anchor.

    ``yaw_bias`` (rad/m): the heading bias in the estimate's odometry (root mean square).
    ``bias_distance``: the part of ``distance`` the heading bias acts on (default: all of it).
    """
    d = max(distance, 0.0)
    s_yaw = math.radians(p.gate_sigma_yaw_deg)
    bias = abs(yaw_bias)
    b = d if bias_distance is None else min(max(bias_distance, 0.0), d)
    var_xy = (
        p.gate_floor_xy**2
        + (p.gate_scale_error * d) ** 2
        + p.gate_sigma_xy**2 * d
        + s_yaw**2 * d**3 / 3.0
        + (0.5 * bias * b**2) ** 2
    )
    var_yaw = math.radians(p.gate_floor_yaw_deg) ** 2 + s_yaw**2 * d + (bias * b) ** 2
    return np.diag([var_xy, var_xy, var_yaw])


def pose_error(predicted: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """``(x, y, yaw)`` of ``measured`` seen from ``predicted``."""
    x, y, yaw = xy_yaw(invert(predicted) @ measured)
    return np.array([x, y, wrap_angle(yaw)])


def mahalanobis2(error: np.ndarray, covariance: np.ndarray) -> float:
    """Squared Mahalanobis distance of an error under a covariance."""
    return float(error @ np.linalg.solve(covariance, error))


class IcpLoopClosing(Stage):
    """SGF loop constraints from ICP between group members, gated by the estimate's uncertainty (Sec. III-D)."""

    kind = "loop"
    name = "icp"
    output = "loops"
    Params = IcpLoopParams

    def __init__(self, params: IcpLoopParams) -> None:
        super().__init__(params)
        self.p = params
        self.settings = IcpSettings(
            metric=params.metric,
            max_iterations=params.max_iterations,
            max_correspondence_distance=params.max_correspondence_distance,
            inlier_distance=params.inlier_distance,
            tolerance=params.tolerance,
            normal_neighbours=params.normal_neighbours,
        )
        from scipy.stats import chi2  # imported here: scipy.stats takes seconds to import

        self.threshold = float(chi2.ppf(params.gate_probability, df=3))
        self.begin(RunContext(run_dir=None))

    def begin(self, context: RunContext) -> None:
        """Forget the previous sequence."""
        self.truth: SequenceTruth | None = context.truth
        self._reading: _GateReading | None = None  # what the gate saw of the match evaluated last
        self.frames = FrameLog(truth=True)  # every processed frame: loops may reach any earlier place
        self.accepted: list[_Candidate] = []
        # the absorbed constraints for one estimate (a snapshot: held, so its identity is not reused) and count
        self._absorbed_for: PoseEstimate | None = None
        self._absorbed_count = -1
        self._absorbed_cache: list[_Candidate] = []
        self.pending: list[_Candidate] = []
        self.waiting: list[_Waiting] = []
        self.assignments: list[GroupAssignment] = []
        self.counts = {
            "candidates": 0,
            "symmetric": 0,
            "ambiguous": 0,
            "separation": 0,
            "too_few_points": 0,
            "icp": 0,
            "gate": 0,
            "consensus": 0,
            "not_unique": 0,
            "map_unconfirmed": 0,
            "inconsistent": 0,
        }
        self.ties_resolved = 0
        self.aliases_resolved = 0
        self.distinct = 0
        self.gate_decided = 0
        self.position_only = 0
        self.earlier_members = 0
        self.decisions: list[dict[str, Any]] = []  # every candidate's outcome: loop_candidates.csv
        context.artifacts["loop_candidates"] = self.decisions  # grows as matches are decided: observers watch it
        self._icp_detail = ""  # what the last failed ICP missed
        self._sgf_group: list[int] = []
        self._sgf_xy: list[np.ndarray] = []
        self._sgf_distance: list[float] = []
        self._sgf_matrix: list[np.ndarray] = []
        self._sgf_yaw: list[float] = []
        self._sgf_frame: list[int] = []
        self._sgf_centroid: list[np.ndarray] = []
        self._sgf_track: list[int] = []
        self._sgf_descriptor: list[SgfDescriptor] = []
        self._sgf_symmetric: list[bool] = []
        self._gate_refusal = ""  # why the gate alone did not decide the last match
        self._estimate: PoseEstimate | None = None  # the newest estimate (for the final pass)
        self.final_tried = 0
        self._consistency_entry: dict[str, Any] | None = None  # the end-of-run consistency test, both rounds
        self._settled = False

    # -- per frame --------------------------------------------------------------------------

    def process(
        self, frame: Frame, assignments: GroupAssignments | None, estimate: Previous[PoseEstimate]
    ) -> LoopConstraints:
        """Loop constraints of the SGFs assigned to groups on this frame."""
        self.frames.append(frame)
        if estimate is not None:
            self._estimate = estimate
        if assignments is None:
            return LoopConstraints(tuple(self._settle_waiting(estimate, new_sgfs=False)))
        earlier, self.waiting = self.waiting, []  # this frame's matches were just decided: they wait untested
        out: list[LoopConstraint] = []
        for a in assignments.items:
            kept = replace(a, descriptor=a.descriptor.without_pixels())  # for the map and the gate: no pixels
            self.assignments.append(kept)
            if a.descriptor.sgf.frame_index in self.frames:
                self._remember(kept)
            out.extend(self._close(a, estimate))
        out.extend(self._settle_waiting(estimate, new_sgfs=bool(assignments.items), waiting=earlier))
        return LoopConstraints(tuple(out))

    def _known(self, frame_index: int) -> None:
        if frame_index not in self.frames:
            raise ValueError(
                f"an SGF of frame {frame_index} reached the loop stage, which never saw that frame; "
                "SGFs must come from frames processed earlier in this run"
            )

    def _close(self, a: GroupAssignment, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """ICP, acceptance tests, gate and neighbour consensus for one assignment; the constraints to emit now."""
        if a.new_group or a.matched is None:
            return []
        self.counts["candidates"] += 1
        if a.symmetric:
            if not self.p.symmetric_loops:
                self._refuse(a, "symmetric")
                return []
            return self._close_position_only(a, estimate)
        if a.ambiguous:
            return self._resolve_tie(a, estimate)
        a, candidate = self._evaluate_or_earlier(a, estimate)
        if candidate is None:
            return []
        need, basis = self.p.min_support, ""
        if (
            self.p.distinct_support is not None
            and need > self.p.distinct_support
            and self._gate_bounds_distinct(candidate)
            and self._distinct(a)
        ):
            need, basis = self.p.distinct_support, "distinct"
            self.distinct += 1
        if need > 0 and candidate.map_pose is None and self._gate_decides(a, candidate, estimate):
            need, basis = 0, "the gate decides"
            self.gate_decided += 1
        if need > 0 and candidate.map_pose is None:
            return self._consensus(((a, candidate),), need, False, "consensus", None, estimate)
        return self._accept(candidate, estimate, basis)

    def _evaluate_or_earlier(
        self, a: GroupAssignment, estimate: PoseEstimate | None
    ) -> tuple[GroupAssignment, _Candidate | None]:
        """:meth:`_evaluate`, redone with an earlier pass's member when the match is of one pass; None: refused."""
        candidate = self._evaluate(a, estimate)
        if candidate == "separation":
            earlier = self._earlier_member(a)
            if earlier is not None:
                a, candidate = earlier, self._evaluate(earlier, estimate)
                self.earlier_members += 1
        if isinstance(candidate, str):
            self._refuse(a, candidate, self._reading, self._icp_detail if candidate == "icp" else "")
            return a, None
        return a, candidate

    def _close_position_only(self, a: GroupAssignment, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """A match into a symmetric group (``symmetric_loops``): a position-only loop when the gate alone decides.

        Round markings are the campus's most repeated design, so no neighbour vouches for one: the
        gate must predict the match tightly (``gate_support_sigma``) with no look-alike seen within
        its reach. Such loops are not matched against a prior map, whose anchoring needs a heading.
        """
        if isinstance(a.matched, MapDescriptor):
            self._refuse(a, "symmetric", detail="no position-only loop into a prior map")
            return []
        if a.ambiguous:
            self._refuse(a, "ambiguous", detail="a tie of symmetric groups")
            return []
        a, candidate = self._evaluate_or_earlier(a, estimate)
        if candidate is None:
            return []
        if not self._gate_decides(a, candidate, estimate):
            self._refuse(a, "consensus", candidate.gate, f"position only: {self._gate_refusal}")
            return []
        self.gate_decided += 1
        self.position_only += 1
        return self._accept(candidate, estimate, "position only: the gate decides")

    def _gate_bounds_distinct(self, candidate: _Candidate) -> bool:
        """Whether the gate is tight enough for a distinct marking to vouch for itself (``distinct_gate_sigma``).

        "Distinct" means no copy was *seen*; a gate wider than the campus cannot tell a copy never
        seen from the marking itself, so a match there needs its neighbours like any other.
        """
        limit, gate = self.p.distinct_gate_sigma, candidate.gate
        return limit is None or candidate.map_pose is not None or (gate is not None and gate.sigma_xy <= limit)

    def _gate_decides(self, a: GroupAssignment, candidate: _Candidate, estimate: PoseEstimate | None) -> bool:
        """Whether the gate alone tells this match from every look-alike seen so far (``gate_support_sigma``).

        The neighbour consensus exists because the drift can be larger than the spacing of a design's
        copies. Once loops have anchored the estimate, the gate predicts the query's place within
        ``sigma`` metres: a copy farther from the matched SGF than the gate's reach
        (``sqrt(chi2 threshold) * sigma``, plus ``consensus_exclude`` for the markings' extent) would
        have failed it. So the match needs no neighbours when
        no SGF of another group that looks like the query lies within that reach of the matched SGF
        (positions in the current estimate). A copy never seen is the risk left, as for a distinct marking.
        """
        limit, gate = self.p.gate_support_sigma, candidate.gate
        if not self.p.gate or limit is None or gate is None or not (gate.sigma_xy <= limit):
            sigma = "none" if gate is None else f"{gate.sigma_xy:.2f} m"
            self._gate_refusal = f"the gate's sigma ({sigma}) above gate_support_sigma ({limit})"
            return False
        assert a.matched is not None
        others, distances = self._other_groups_distances(np.asarray(a.descriptor.matrix), a.group_id)
        alike = others[distances <= self.p.consensus_distance]
        query_frame, query_centroid = a.descriptor.sgf.frame_index, np.asarray(a.descriptor.centroid)[:2]
        reach = math.sqrt(self.threshold) * gate.sigma_xy + self.p.consensus_exclude
        matched = self._estimate_xy(a.matched.sgf.frame_index, np.asarray(a.matched.centroid), estimate)
        for k in alike:
            if self._sgf_frame[k] == query_frame and np.allclose(self._sgf_centroid[k], query_centroid):
                continue  # the query itself (remembered in the group it joined: another option's, in a tie)
            here = self._estimate_xy(self._sgf_frame[k], self._sgf_centroid[k], estimate)
            apart = float(np.hypot(*(here - matched)))
            if apart <= reach and self._stands_against(a, k, estimate):
                self._gate_refusal = (
                    f"a look-alike (frame {self._sgf_frame[k]}) {apart:.1f} m from the match, within the gate's "
                    f"reach ({reach:.1f} m)"
                )
                return False
        return True

    def _stands_against(self, a: GroupAssignment, k: int, estimate: PoseEstimate | None) -> bool:
        """Whether remembered SGF ``k``, a look-alike within the gate's reach, could be what the query saw.

        With ``gate_support_round``, a look-alike the association holds in a symmetric group (a round
        manhole, alike to a compact shape by eq. 10) cannot be a shaped marking's. With
        ``gate_support_alternatives``, the query matched to the look-alike is put through ICP and
        the gate as a loop would be: a look-alike whose shape ICP refuses, or that the gate refuses
        where the estimate puts it, is told apart already. A look-alike it cannot test (seen on the
        query's own pass, too few points) stands against the match.
        """
        if self.p.gate_support_round and self._sgf_symmetric[k] and not a.symmetric:
            return False
        if not self.p.gate_support_alternatives:
            return True
        other = self._sgf_descriptor[k]
        if other.sgf.frame_index < a.descriptor.sgf.frame_index:
            alternative = _match_closest(a, [other])
        else:  # seen after the query (the final pass): the same pairing, the earlier view matched
            alternative = _match_closest(replace(a, descriptor=other), [a.descriptor])
        alternative = replace(alternative, group_id=self._sgf_group[k], alternatives=(), ambiguous=False)
        saved = self._reading, self._icp_detail
        outcome = self._evaluate(alternative, estimate)
        self._reading, self._icp_detail = saved
        return outcome not in ("icp", "gate")

    def _estimate_xy(self, frame_index: int, centroid: np.ndarray, estimate: PoseEstimate | None) -> np.ndarray:
        """An SGF's centroid (x, y) in the current estimate (odometry before the first)."""
        pose = self._pose(frame_index, estimate)
        return pose[:2, :2] @ np.asarray(centroid, dtype=np.float64)[:2] + pose[:2, 3]

    def _distinct(self, a: GroupAssignment) -> bool:
        """Whether the query looks like its match (eq. 10) and like no SGF of any other group seen so far.

        The campus repeats standard markings; a marking whose copies have been seen elsewhere has
        them in other groups (the spatial gate keeps them apart), so its matches need neighbours
        that agree. A marking that looks like nothing else seen (a custom one, painted once) is
        its own evidence; so, with ``distinct_ratio`` set, is one far more like its match than like
        any SGF of another group (that many times: a ratio test; false pairs measured at most 1.2).
        The first copy of a repeated design met twice is the risk this takes.
        """
        assert a.matched is not None
        query = np.asarray(a.descriptor.matrix)
        match = float(shifted_distances(query, np.asarray(a.matched.matrix)).min())
        if match > self.p.consensus_distance:
            return False
        _, alike = self._other_groups_distances(query, a.group_id)
        if not len(alike):
            return False
        nearest, ratio = float(alike.min()), self.p.distinct_ratio
        if nearest > self.p.distinct_distance:
            return True
        return ratio is not None and nearest > self.p.distinct_floor and nearest >= ratio * match

    def _other_groups_distances(self, matrix: np.ndarray, group_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Every SGF seen so far outside ``group_id`` (its index), and eq. 10 of ``matrix`` to it (best shift)."""
        others = np.flatnonzero(np.asarray(self._sgf_group, dtype=np.int64) != group_id)
        if not len(others):
            return others, np.zeros(0)
        distances = shifted_distances(matrix, np.stack([self._sgf_matrix[m] for m in others])).min(axis=1)
        return others, distances

    def _resolve_tie(self, a: GroupAssignment, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """A match among look-alike groups: the one option whose neighbouring SGFs agree, else nothing."""
        options = [a] + [
            replace(a, group_id=alt.group_id, matched=alt.matched, shift=alt.shift, yaw=alt.yaw, alternatives=())
            for alt in a.alternatives
        ]
        if any(isinstance(o.matched, MapDescriptor) for o in options):
            self._refuse(a, "ambiguous", detail="tie with a map group")
            return []
        if a.aliased and not a.alternatives and self.p.aliased_support > 0:
            # a repeated pattern: only markings unlike the query may vouch for which copy it is
            candidate = self._evaluate(a, estimate)
            if isinstance(candidate, str):
                self._refuse(a, "ambiguous", detail=f"aliased: {self._failure(candidate)}")
                return []
            return self._consensus(((a, candidate),), self.p.aliased_support, True, "ambiguous", "aliases", estimate)
        if a.aliased or not a.alternatives or self.p.tie_support == 0:
            why = "aliased" if a.aliased else "tie with an aliased group" if not a.alternatives else "tie_support 0"
            self._refuse(a, "ambiguous", detail=why)
            return []
        passed, failed = [], []
        for option in options:
            candidate = self._evaluate(option, estimate)
            if isinstance(candidate, str):
                failed.append(self._failure(candidate))
            else:
                passed.append((option, candidate))
        if not passed:
            self._refuse(a, "ambiguous", detail="tie: every option failed (" + "; ".join(failed) + ")")
            return []
        if len(passed) == 1 and self._gate_decides(*passed[0], estimate):
            self.gate_decided += 1
            self.ties_resolved += 1
            return self._accept(passed[0][1], estimate, "the gate decides the tie")
        need = max(self.p.tie_support, self.p.min_support)
        return self._consensus(tuple(passed), need, False, "ambiguous", "ties", estimate)

    # -- waiting for the neighbour consensus --------------------------------------------------

    def _consensus(
        self,
        options: tuple[tuple[GroupAssignment, _Candidate], ...],
        need: int,
        unlike: bool,
        refused: str,
        resolved: str | None,
        estimate: PoseEstimate | None,
    ) -> list[LoopConstraint]:
        """Settle a match by its neighbours now, or let it wait for the SGFs of the next ``consensus_window`` metres."""
        distance = self.frames.distance(options[0][0].descriptor.sgf.frame_index)
        waiting = _Waiting(options, need, unlike, refused, resolved, distance)
        out = self._settle(waiting, estimate, final=not self.p.consensus_wait)
        if out is None:
            self.waiting.append(waiting)
            return []
        return out

    def _settle(self, w: _Waiting, estimate: PoseEstimate | None, final: bool) -> list[LoopConstraint] | None:
        """The constraint of the one option with enough agreeing neighbours, [] when refused, None to wait on."""
        support = [self._support(a, c.constraint, unlike=w.unlike) for a, c in w.options]
        supported = [c for (_, c), n in zip(w.options, support, strict=True) if n >= w.need]
        if len(supported) == 1:
            if w.resolved == "ties":
                self.ties_resolved += 1
            elif w.resolved == "aliases":
                self.aliases_resolved += 1
            return self._accept(supported[0], estimate, _support_detail(support, w.need))
        if len(supported) > 1 or final:
            outcome = "ambiguous" if len(supported) > 1 else w.refused
            self._refuse(w.options[0][0], outcome, w.options[0][1].gate, _support_detail(support, w.need))
            return []
        return None

    def _settle_waiting(
        self, estimate: PoseEstimate | None, new_sgfs: bool, waiting: list[_Waiting] | None = None
    ) -> list[LoopConstraint]:
        """Re-test waiting matches (all, or ``waiting`` taken out of the list) with the SGFs seen since.

        Those the robot has driven ``consensus_window`` past expire; the unsettled go back on the list.
        """
        if waiting is None:
            waiting, self.waiting = self.waiting, []
        here = self.frames.travelled
        out: list[LoopConstraint] = []
        for w in waiting:
            expired = here - w.distance > self.p.consensus_window
            settled = self._settle(w, estimate, final=expired) if new_sgfs or expired else None
            if settled is None:
                self.waiting.append(w)
            else:
                out.extend(settled)
        return out

    def _evaluate(self, a: GroupAssignment, estimate: PoseEstimate | None) -> _Candidate | str:
        """Separation, ICP and the gate for one match: the candidate, or the name of the test it failed."""
        matched, query = a.matched, a.descriptor
        assert matched is not None
        self._reading = None
        j = query.sgf.frame_index
        self._known(j)
        from_map = isinstance(matched, MapDescriptor)
        i = matched.sgf.frame_index
        if not from_map:
            self._known(i)
            if not self._separated(i, j):
                return "separation"
        if min(len(query.points), len(matched.points)) < self.p.min_points:
            return "too_few_points"
        position_only = a.symmetric and self.p.symmetric_loops
        results, probed = self._align(a, position_only)
        if not results:
            return "icp"
        map_pose = np.asarray(matched.map_pose, dtype=np.float64) if isinstance(matched, MapDescriptor) else None
        map_truth = matched.ground_truth if isinstance(matched, MapDescriptor) else None
        anchored = from_map and self._map_anchored(estimate)
        predicted = None
        distance = math.nan
        if not from_map:
            distance = self._anchored_distance(i, j, estimate)
            drift = self._drift(distance, j, estimate, self._bias_distance(i, j, distance, estimate))
            predicted = (invert(self._pose(i, estimate)) @ self._pose(j, estimate), drift)
        elif anchored:
            assert map_pose is not None
            distance = self._anchored_distance(_MAP, j, estimate)
            predicted = (invert(map_pose) @ self._pose(j, estimate), self._drift(distance, j, estimate))
        points = np.asarray(query.points, dtype=np.float64)
        fits = self._centred(results, query) if position_only else self._fits(results, points, probed)
        if not fits:
            return "icp"
        turn = None  # a position-only loop turns about its marking as the estimate predicts (ICP's heading when none)
        if position_only:
            turn = xy_yaw(predicted[0])[2] if predicted is not None else se2_params(fits[0].transform)[2]
        if predicted is not None:
            chi2 = [self._gate_chi2(a, r, from_map, predicted, turn) for r in fits]
            self._reading = _GateReading(distance, math.sqrt(predicted[1][0, 0]), min(chi2))
        if predicted is None or not self.p.gate:
            best = self._select(fits, predicted)
        else:
            # several distinct fits (a twofold symmetric shape, a row one period on): the gate must pick one
            passing = [r for r, value in zip(fits, chi2, strict=True) if value <= self.threshold]
            if len(passing) != 1:
                return "not_unique" if passing else "gate"
            best = passing[0]
        constraint = self._constraint(a, best, from_map, turn)
        return _Candidate(constraint, map_pose, map_truth, a.group_id, anchored, self._reading)

    def _separated(self, i: int, j: int) -> bool:
        """Whether frame ``i`` is far enough before frame ``j`` (frames, time, path) to be another pass."""
        p = self.p
        return (
            i < j
            and j - i >= p.min_separation_frames
            and self.frames.time(j) - self.frames.time(i) >= p.min_separation_time
            and self.frames.distance(j) - self.frames.distance(i) >= p.min_separation_distance
        )

    def _earlier_member(self, a: GroupAssignment) -> GroupAssignment | None:
        """The match redone with the group's closest member (eq. 10) from an earlier pass, when there is one.

        The association matches the query to its group's closest member; when that is a view of
        the same pass (the marking seen twice on the way), a member seen on an earlier pass may
        still be in the group, and that pair is the loop.
        """
        query = a.descriptor
        j = query.sgf.frame_index
        members = [
            m.descriptor
            for m in self.assignments
            if m.group_id == a.group_id
            and m.descriptor.sgf.frame_index in self.frames
            and self._separated(m.descriptor.sgf.frame_index, j)
        ]
        if not members:
            return None
        return _match_closest(a, members)

    def _gate_chi2(
        self,
        a: GroupAssignment,
        r: IcpResult,
        from_map: bool,
        predicted: tuple[np.ndarray, np.ndarray],
        turn: float | None = None,
    ) -> float:
        """A fit's squared Mahalanobis distance to the prediction (pose, drift covariance); the gate's test value."""
        c = self._constraint(a, r, from_map, turn)
        cov = c.covariance + predicted[1]
        return mahalanobis2(pose_error(predicted[0], c.relative), cov)

    def _accept(self, candidate: _Candidate, estimate: PoseEstimate | None, basis: str = "") -> list[LoopConstraint]:
        """Emit a candidate that passed every test (map matches wait for the run's anchoring in the map).

        ``basis`` says, in ``loop_candidates.csv``, what vouched for it beyond ICP and the gate.
        """
        if candidate.map_pose is not None and not candidate.anchored:
            return self._confirm_map(candidate, estimate)
        self.accepted.append(candidate)
        self._decided(candidate.constraint, candidate.group_id, "accepted", candidate.gate, basis)
        return [candidate.constraint]

    def _refuse(self, a: GroupAssignment, reason: str, gate: _GateReading | None = None, detail: str = "") -> None:
        """Count a refused candidate under ``reason`` and log it (with what the gate saw, and why, when known)."""
        assert a.matched is not None
        self.counts[reason] += 1
        ends = (a.matched.sgf.frame_index, a.descriptor.sgf.frame_index)
        ids = (a.matched.sgf.instance_id, a.descriptor.sgf.instance_id)
        self._log(ends, ids, a.group_id, isinstance(a.matched, MapDescriptor), reason, gate, detail)

    def _decided(
        self, k: LoopConstraint, group_id: int, outcome: str, gate: _GateReading | None, detail: str = ""
    ) -> None:
        self._log((k.frame_from, k.frame_to), k.instance_ids, group_id, k.from_map, outcome, gate, detail)

    def _log(
        self,
        ends: tuple[int, int],
        ids: tuple[int | None, int | None],
        group_id: int,
        from_map: bool,
        outcome: str,
        gate: _GateReading | None,
        detail: str = "",
    ) -> None:
        """One row of ``loop_candidates.csv``: a match the loop stage decided on, and the outcome."""
        self.decisions.append(
            {
                "frame_from": ends[0],
                "frame_to": ends[1],
                "time_from": None if from_map else self.frames.get_time(ends[0]),
                "time_to": self.frames.get_time(ends[1]),
                "group_id": group_id,
                "from_map": from_map,
                "outcome": outcome,
                "instance_from": ids[0],
                "instance_to": ids[1],
                "anchored_distance": None if gate is None else round(gate.distance, 2),
                "gate_sigma_xy": None if gate is None else round(gate.sigma_xy, 3),
                "gate_chi2": None if gate is None else round(gate.chi2, 3),
                "detail": detail,
            }
        )

    # -- neighbour consensus ----------------------------------------------------------------

    def _remember(self, a: GroupAssignment) -> None:
        """Keep an SGF's odometry-frame position, path distance and descriptor for the consensus test."""
        d = a.descriptor
        self._sgf_xy.append(_odometry_xy(d))
        self._sgf_distance.append(self.frames.distance(d.sgf.frame_index))
        self._sgf_matrix.append(np.asarray(d.matrix))
        self._sgf_yaw.append(_odometry_yaw(d))
        self._sgf_group.append(a.group_id)
        self._sgf_frame.append(d.sgf.frame_index)
        self._sgf_centroid.append(np.asarray(d.centroid, dtype=np.float64)[:2])
        self._sgf_track.append(d.sgf.track_id)
        self._sgf_descriptor.append(d)
        self._sgf_symmetric.append(a.symmetric)

    def _support(self, a: GroupAssignment, c: LoopConstraint, unlike: bool = False) -> float:
        """How many other markings near the query agree with the match: seen where it puts them, and alike.

        The match says the query's frame sits at ``c.relative`` in the matched frame; odometry is
        accurate over tens of metres, so it carries the SGFs seen within ``consensus_window`` before
        the query (and after it so far, with ``consensus_wait``) into the earlier pass's odometry
        frame. A neighbour agrees when an SGF of the earlier pass (within the window around the
        matched SGF, and at least ``min_separation_distance`` of path before the neighbour) lies
        within ``consensus_radius + consensus_drift * (path from the two sightings)`` of it (with
        ``consensus_heading_bias``, plus ``0.5 * bias * L**2`` for each sighting ``L`` m away:
        a heading bias bends each pass's odometry; the bias the back-end's model holds) and looks
        like it (eq. 10 distance at most ``consensus_distance``); with ``consensus_heading_deg`` set,
        at the heading the match predicts for it, within that many degrees, and a neighbour that
        looks alike at the opposite heading too (a bar, a disc) confirms the position but not the
        heading, and counts ``consensus_unoriented_weight``. Agreeing neighbours closer than
        ``consensus_exclude`` to each other, or to the query, are one marking; the count is of
        markings. A look-alike marking elsewhere on campus has other neighbours, so its match finds
        none. With ``unlike``, neighbours that look like the query (eq. 10 distance at most
        ``consensus_distance``) do not count: in a repeated pattern they are its other copies, which
        agree with a match shifted by a period; and the tolerance is capped at half the pattern's
        period (:meth:`_copy_spacing`), since a neighbour allowed more would agree with the match
        one period off too. A neighbour's weight is scaled by :meth:`_rarity`.
        """
        p = self.p
        assert a.matched is not None
        query, matched = a.descriptor, a.matched
        odo_j = np.asarray(query.sgf.odometry, dtype=np.float64)
        odo_i = np.asarray(matched.sgf.odometry, dtype=np.float64)
        x, y, yaw = xy_yaw(odo_i @ c.relative @ invert(odo_j))
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        xy = np.asarray(self._sgf_xy)
        dist = np.asarray(self._sgf_distance)
        headings = np.asarray(self._sgf_yaw)
        d_j, d_i = self.frames.distance(query.sgf.frame_index), self.frames.distance(matched.sgf.frame_index)
        q_xy, m_xy = _odometry_xy(query), _odometry_xy(matched)
        near_query = (dist >= d_j - p.consensus_window) & (
            dist <= d_j + (p.consensus_window if p.consensus_wait else 0.0)
        )
        near_query &= np.hypot(*(xy - q_xy).T) > p.consensus_exclude
        near_match = (np.abs(dist - d_i) <= p.consensus_window) & (np.hypot(*(xy - m_xy).T) > p.consensus_exclude)
        earlier = np.flatnonzero(near_match)
        if not len(earlier):
            return 0.0
        agreeing: list[tuple[np.ndarray, float]] = []
        neighbours = np.flatnonzero(near_query)
        if unlike and len(neighbours):
            alike = shifted_distances(query.matrix, np.stack([self._sgf_matrix[k] for k in neighbours])).min(axis=1)
            neighbours = neighbours[alike > p.consensus_distance]
        far = np.abs(dist[earlier] - d_i)  # path from the matched sighting to each earlier SGF
        bias = uncorrected_yaw_bias(self._estimate) if p.consensus_heading_bias else None
        cap = 0.5 * self._copy_spacing(a) if unlike else math.inf
        for k in neighbours:
            here = rot @ xy[k] + (x, y)
            near = abs(d_j - dist[k])
            tolerance = p.consensus_radius + p.consensus_drift * (near + far)
            if bias is not None:  # a heading bias bends each pass by 0.5 b L^2
                tolerance = tolerance + 0.5 * bias * (near**2 + far**2)
            tolerance = np.minimum(tolerance, cap)
            close = earlier[
                (np.hypot(*(xy[earlier] - here).T) <= tolerance)
                & (dist[earlier] <= dist[k] - p.min_separation_distance)
            ]
            if not len(close):
                continue
            profiles = shifted_distances(self._sgf_matrix[k], np.stack([self._sgf_matrix[m] for m in close]))
            # the neighbour's heading in each earlier SGF's frame, as the match predicts it (eq. 10's shift convention)
            predicted = headings[k] + yaw - headings[close]
            weight = _agreement(
                profiles, predicted, p.consensus_distance, p.consensus_heading_deg, p.consensus_unoriented_weight
            )
            if weight <= 0.0:
                continue
            weight *= self._rarity(int(k))
            same = [n for n, (g, _) in enumerate(agreeing) if np.hypot(*(xy[k] - g)) <= p.consensus_exclude]
            if same:
                agreeing[same[0]] = (agreeing[same[0]][0], max(agreeing[same[0]][1], weight))
            else:
                agreeing.append((xy[k], weight))
        return float(sum(w for _, w in agreeing))

    def _copy_spacing(self, a: GroupAssignment) -> float:
        """The period of a repeated pattern: the nearest copy of the query's design seen around either sighting.

        Copies are SGFs of other groups that look like the query (eq. 10 at most
        ``consensus_distance``), seen within ``consensus_window`` of path of the matched SGF or of
        the query, and farther than ``COPY_MIN_SPACING_M`` from it (nearer is the same marking seen
        again); distances in that pass's odometry frame, exact over such short paths. Infinite when
        no copy was seen.
        """
        assert a.matched is not None
        others, distances = self._other_groups_distances(np.asarray(a.descriptor.matrix), a.group_id)
        copies = others[distances <= self.p.consensus_distance]
        if not len(copies):
            return math.inf
        xy = np.asarray(self._sgf_xy)[copies]
        travelled = np.asarray(self._sgf_distance)[copies]
        spacing = math.inf
        for sighting in (a.matched, a.descriptor):
            around = np.abs(travelled - self.frames.distance(sighting.sgf.frame_index)) <= self.p.consensus_window
            gaps = np.hypot(*(xy[around] - _odometry_xy(sighting)).T)
            gaps = gaps[gaps > COPY_MIN_SPACING_M]
            if len(gaps):
                spacing = min(spacing, float(gaps.min()))
        return spacing

    def _rarity(self, k: int) -> float:
        """How much an agreeing neighbour (SGF ``k``) counts for its design's commonness (``consensus_common_groups``).

        A design with copies in many groups (a standard arrow, a crossing) is found near any place a
        wrong match predicts with some chance; a rare one is evidence. Counted by groups, not SGFs,
        since one marking seen from several frames is one group.
        """
        limit = self.p.consensus_common_groups
        if limit is None:
            return 1.0
        others, distances = self._other_groups_distances(self._sgf_matrix[k], self._sgf_group[k])
        groups = np.asarray(self._sgf_group, dtype=np.int64)[others]
        common = len(set(groups[distances <= self.p.consensus_distance].tolist()))
        return min(1.0, limit / common) if common else 1.0

    # -- ICP --------------------------------------------------------------------------------

    def _align(self, a: GroupAssignment, position_only: bool = False) -> tuple[list[IcpResult], list[IcpResult]]:
        """ICP from each yaw seed, then (when one passed) from its probes: the results of each that pass the tests.

        For a position-only loop the heading ICP cannot fix is no failure, and no probe refines it.
        """
        assert a.matched is not None
        query, matched = a.descriptor, a.matched
        yaws = [float(a.yaw)]
        if self.p.seed_both_signs:
            yaws.append(-float(a.yaw))
        n = self.p.extra_yaw_seeds
        yaws += [float(a.yaw) + 2.0 * math.pi * (k + 1) / (n + 1) for k in range(n)]
        seeds = _distinct_yaws(yaws, [])
        icp = Icp2d(np.asarray(matched.points, dtype=np.float64), self.settings)
        source = np.asarray(query.points, dtype=np.float64)

        def from_seeds(yaws: list[float]) -> tuple[list[IcpResult], list[IcpResult]]:
            tried = [icp.align(source, centroid_seed(query.centroid, matched.centroid, y)) for y in yaws]
            return [r for r in tried if self._passes(r, position_only)], tried

        good, tried = from_seeds(seeds)
        if not good:
            self._icp_detail = self._failed_fit(tried)
            return [], []
        probe = math.radians(self.p.yaw_probe_deg)
        if probe == 0.0 or position_only:
            return good, []
        # probes only refine the seeds' fits: without one to refine they are not run
        probed, _ = from_seeds(_distinct_yaws([y + d for y in seeds for d in (-probe, probe)], seeds))
        return good, probed

    def _passes(self, r: IcpResult, position_only: bool = False) -> bool:
        """Whether an ICP result passes the acceptance tests: converged, RMS, two-way inliers, not degenerate.

        A position-only fit may leave its heading degenerate (that is what a round marking does).
        """
        return (
            r.converged
            and r.fitness <= self.p.max_fitness
            and r.inlier_ratio >= self.p.min_inlier_ratio
            and (position_only or _largest_sigma(r) <= self.p.degenerate_sigma)
        )

    def _centred(self, results: list[IcpResult], query: SgfDescriptor) -> list[IcpResult]:
        """The best fit of a position-only match, when every fit puts the marking's centre within an inlier distance.

        Fits of a round marking differ in heading, not in where its centre lies; fits that disagree
        on the centre are two places, and the match gives no loop.
        """
        centre = np.asarray(query.centroid, dtype=np.float64)[:2]
        seen = np.array([r.transform[:2, :2] @ centre + r.transform[:2, 2] for r in results])
        apart = float(np.max(np.linalg.norm(seen - seen.mean(axis=0), axis=1))) * 2.0
        if apart > self.p.inlier_distance:
            self._icp_detail = f"fits put the marking's centre {apart:.2f} m apart ({self.p.inlier_distance:g} at most)"
            return []
        return [min(results, key=lambda r: r.fitness)]

    def _failure(self, test: str) -> str:
        """A failed test's name, with what ICP's best fit missed when it was ICP."""
        return f"icp, {self._icp_detail}" if test == "icp" else test

    def _failed_fit(self, tried: list[IcpResult]) -> str:
        """What the fit with the most inliers of a failed ICP missed, for ``loop_candidates.csv``."""
        r = max(tried, key=lambda r: r.inlier_ratio)
        sigma = _largest_sigma(r)
        return (
            f"best fit: inliers {r.inlier_ratio:.2f} ({self.p.min_inlier_ratio:g} needed), "
            f"rms {r.fitness:.3f} m ({self.p.max_fitness:g}), sigma {sigma:.3f} ({self.p.degenerate_sigma:g})"
            + ("" if r.converged else ", not converged")
        )

    def _fits(self, results: list[IcpResult], points: np.ndarray, probed: Sequence[IcpResult] = ()) -> list[IcpResult]:
        """The distinct near-equal fits of a match (RMS within ``ambiguity_ratio`` of the best), best first.

        Several come from a twofold symmetric shape turned by 180 degrees, or from a row of
        triangles or bars laid on itself one period on. Fits that lay the query's ``points`` within
        ``FIT_TOLERANCE_M`` (RMS) of each other are one (measured on the marking, not at the
        robot, where a few degrees of yaw about the marking move the pose by its lever arm): ICP
        seeded from either side of a shallow valley (an elongated marking turned a little) stops
        on both sides of the truth, so one fit is the middle of their stops (:func:`_merged`), its
        covariance widened by their spread. The ``probed`` fits (from seeds a few degrees either
        side) join the seeds' fits they lie within that tolerance of, and never make a fit of their
        own; the spread test (``max_fit_spread_deg``) is on the seeds' fits alone.
        """
        best = min(r.fitness for r in results)
        clusters: list[list[IcpResult]] = []
        for r in sorted(results, key=lambda r: r.fitness):
            if r.fitness > best * self.p.ambiguity_ratio:
                break
            for cluster in clusters:
                if _displacement(r.transform, cluster[0].transform, points) <= FIT_TOLERANCE_M:
                    cluster.append(r)
                    break
            else:
                clusters.append([r])
        limit = self.p.max_fit_spread_deg
        if limit is not None:
            apart = math.degrees(max(_yaw_spread(cluster) for cluster in clusters))
            if apart > limit:
                # a marking nearly round (a ring-framed pick-up marker): its fits agree on the place, not the heading
                self._icp_detail = f"fits of one alignment {apart:.1f} degrees apart ({limit:g} at most)"
                return []
        for r in probed:
            if r.fitness > best * self.p.ambiguity_ratio:
                continue
            joined = next(
                (c for c in clusters if _displacement(r.transform, c[0].transform, points) <= FIT_TOLERANCE_M), None
            )
            if joined is not None:
                joined.append(r)
        return [_merged(_distinct_fits(cluster, points)) for cluster in clusters]

    def _select(self, results: list[IcpResult], predicted: tuple[np.ndarray, np.ndarray] | None) -> IcpResult:
        """The first fit; among several (a twofold symmetric shape), the one nearest the prediction (gate off)."""
        if predicted is None or len(results) == 1:
            return results[0]
        target, cov = predicted
        return min(results, key=lambda r: mahalanobis2(pose_error(target, _pose4(r)), cov + r.covariance))

    def _constraint(
        self, a: GroupAssignment, r: IcpResult, from_map: bool, turn: float | None = None
    ) -> LoopConstraint:
        """The relative pose of the query's frame in the matched frame, with the floored ICP covariance.

        The floor adds the BEV's own error, which ICP cannot see: a constant, plus a term growing
        as the square of each view's range (a pitch error moves ground seen at distance d by about
        d^2 / h times it). With ``turn``, a position-only loop (:func:`position_only_loop`): the
        marking's centre where ICP puts it, known to the RMS residual over the inliers plus that floor.
        """
        assert a.matched is not None
        ranges = [float(np.hypot(*np.asarray(d.centroid, dtype=np.float64)[:2])) for d in (a.matched, a.descriptor)]
        xy2 = self.p.covariance_floor_xy**2 + self.p.covariance_range_xy**2 * sum(d**4 for d in ranges)
        floor = np.diag([xy2, xy2, math.radians(self.p.covariance_floor_yaw_deg) ** 2])
        relative, covariance, marking = _pose4(r), r.covariance + floor, None
        if turn is not None:
            centre = np.asarray(a.descriptor.centroid, dtype=np.float64)[:2]
            sigma2 = xy2 + r.fitness**2 / max(r.correspondences, 1)
            free = math.radians(self.p.position_only_yaw_sigma_deg)
            relative, covariance = position_only_loop(relative, centre, turn, sigma2, free)
            marking = (float(centre[0]), float(centre[1]))
        return LoopConstraint(
            frame_from=a.matched.sgf.frame_index,
            frame_to=a.descriptor.sgf.frame_index,
            relative=relative,
            covariance=covariance,
            marking=marking,
            group_id=a.group_id,
            reverse=abs(xy_yaw(relative)[2]) > math.pi / 2.0,
            fitness=r.fitness,
            inlier_ratio=r.inlier_ratio,
            instance_ids=(a.matched.sgf.instance_id, a.descriptor.sgf.instance_id),
            from_map=from_map,
        )

    # -- the estimate and the gate ------------------------------------------------------------

    def _pose(self, k: int, estimate: PoseEstimate | None) -> np.ndarray:
        """Frame ``k``'s pose in the estimate (dead-reckoned past its newest frame), or its odometry."""
        if estimate is None:
            return self.frames.odometry(k)
        if k in estimate.poses:
            return np.asarray(estimate.poses[k])
        last = estimate.frame_index
        return np.asarray(estimate.poses[last]) @ invert(self.frames.odometry(last)) @ self.frames.odometry(k)

    def _drift(
        self, distance: float, newest: int, estimate: PoseEstimate | None, bias_distance: float | None = None
    ) -> np.ndarray:
        """The gate's drift covariance across ``distance`` m since the last anchor up to frame ``newest``.

        The heading bias acts on ``bias_distance`` m of it (all, by default): the uncertainty of the
        bias left when the back-end corrected the odometry over all of that (the drive from its
        ``since`` frame to ``newest``), else the bias as the back-end's model holds it.
        """
        if not self.p.gate_bias_from_backend:
            return drift_covariance(distance, self.p, EXPECTED_YAW_BIAS, bias_distance)
        biased = distance if bias_distance is None else bias_distance
        bias = uncorrected_yaw_bias(estimate)
        corrected = corrected_yaw_bias(estimate)
        if corrected is not None:
            start = self.frames.get_distance(corrected[0])
            if start is not None and self.frames.distance(newest) - start >= biased:
                bias = corrected[1]
        return drift_covariance(distance, self.p, bias, bias_distance)

    def _bias_distance(self, i: int, j: int, distance: float, estimate: PoseEstimate | None) -> float | None:
        """The part of the path from frame ``i`` to the newer ``j`` that the odometry's heading bias bends.

        With ``loop.gate_bridged_bias``, when a loop the estimate has absorbed joins a frame at or
        before ``i`` to one at or after it, the pose graph has spread that loop's closure error over
        the drive between them, which takes a constant heading bias off it: only the drive from the
        newest absorbed loop frame to ``j`` keeps the bias. None (all of ``distance``) otherwise.
        """
        if not self.p.gate_bridged_bias or estimate is None:
            return None
        bridged = False
        last = -math.inf
        for c in self._absorbed_loops(estimate):
            k = c.constraint
            if k.from_map or k.frame_to > j:
                continue
            bridged |= k.frame_from <= i <= k.frame_to
            last = max(last, self.frames.distance(k.frame_to))
        if not bridged:
            return None
        return min(distance, self.frames.distance(j) - last)

    def _absorbed_loops(self, estimate: PoseEstimate | None) -> list[_Candidate]:
        """The accepted constraints the estimate satisfies; kept while the estimate and the accepted list stay."""
        if self._absorbed_for is not estimate or self._absorbed_count != len(self.accepted) or estimate is None:
            self._absorbed_for, self._absorbed_count = estimate, len(self.accepted)
            # a position-only loop fixes no heading: the drift since it is not reset
            self._absorbed_cache = [
                c for c in self.accepted if not c.constraint.position_only and self._absorbed(c, estimate)
            ]
        return self._absorbed_cache

    def _absorbed(self, c: _Candidate, estimate: PoseEstimate | None) -> bool:
        """Whether the estimate satisfies an accepted constraint (so it anchors its two frames)."""
        if estimate is None:
            return False
        k = c.constraint
        start = c.map_pose if k.from_map else self._pose(k.frame_from, estimate)
        assert start is not None
        predicted = invert(start) @ self._pose(k.frame_to, estimate)
        cov = k.covariance + drift_covariance(0.0, self.p)
        return mahalanobis2(pose_error(predicted, k.relative), cov) <= self.threshold

    def _map_anchored(self, estimate: PoseEstimate | None) -> bool:
        """Whether the estimate is in the map frame (it satisfies an accepted map constraint)."""
        return any(c.constraint.from_map for c in self._absorbed_loops(estimate))

    def _anchored_distance(self, a: int, b: int, estimate: PoseEstimate | None) -> float:
        """Path distance from ``a`` to ``b`` where absorbed loops (and the map) join frames at no cost."""
        shortcuts: list[tuple[float, float]] = []
        on_map: list[float] = []  # frames anchored in the map are all joined through it
        for c in self._absorbed_loops(estimate):
            k = c.constraint
            if k.from_map:
                on_map.append(self.frames.distance(k.frame_to))
            else:
                shortcuts.append((self.frames.distance(k.frame_from), self.frames.distance(k.frame_to)))
        on_map.sort()
        shortcuts.extend(itertools.pairwise(on_map))
        if a == _MAP:
            if not on_map:
                return math.inf
            start = on_map[0]
        else:
            start = self.frames.distance(a)
        return float(anchored_distances(start, np.array([self.frames.distance(b)]), shortcuts)[0])

    def _confirm_map(self, candidate: _Candidate, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """Hold map matches until enough of them (different groups) agree on where the run is in the map."""
        agreeing = [q for q in self.pending if q.group_id != candidate.group_id and self._agree(q, candidate, estimate)]
        if len(agreeing) + 1 < self.p.map_anchor_matches:
            self.counts["map_unconfirmed"] += 1
            self._decided(candidate.constraint, candidate.group_id, "map_unconfirmed", candidate.gate)
            self.pending = [*self.pending, candidate][-self.p.map_pending :]
            return []
        confirmed = [*agreeing, candidate]
        self.pending = [q for q in self.pending if all(q is not c for c in confirmed)]
        self.counts["map_unconfirmed"] -= len(agreeing)
        self.accepted.extend(confirmed)
        for c in confirmed:
            self._decided(c.constraint, c.group_id, "accepted", c.gate)
        return [c.constraint for c in confirmed]

    def _agree(self, first: _Candidate, second: _Candidate, estimate: PoseEstimate | None) -> bool:
        """Whether two map matches imply the run's relative pose between their frames, as the estimate has it."""
        a, b = first.constraint, second.constraint
        assert first.map_pose is not None and second.map_pose is not None
        from_map = invert(first.map_pose @ a.relative) @ (second.map_pose @ b.relative)
        own = invert(self._pose(a.frame_to, estimate)) @ self._pose(b.frame_to, estimate)
        distance = self._anchored_distance(a.frame_to, b.frame_to, estimate)
        cov = a.covariance + b.covariance + self._drift(distance, max(a.frame_to, b.frame_to), estimate)
        return mahalanobis2(pose_error(own, from_map), cov) <= self.threshold

    # -- evaluation ---------------------------------------------------------------------------

    def _truth_error(self, c: _Candidate) -> tuple[float, float] | None:
        """How far (m, rad) an accepted constraint's relative pose is from the ground truth's (None: unknown)."""
        k = c.constraint
        start = c.map_truth if k.from_map else self.frames.ground_truth(k.frame_from)
        end = self.frames.ground_truth(k.frame_to)
        if start is None or end is None:
            return None
        truth = invert(start) @ end
        if k.marking is not None:  # where the loop puts its marking, seen from frame_from; no heading to judge
            centre = np.array([*k.marking, 0.0, 1.0])
            return float(np.linalg.norm((truth @ centre - k.relative @ centre)[:2])), 0.0
        x, y, yaw = pose_error(truth, k.relative)
        return math.hypot(x, y), abs(yaw)

    def _true(self, c: _Candidate, error: tuple[float, float] | None) -> bool | None:
        """Whether an accepted constraint joins the same marking at the true relative pose (None: unknown).

        ``error`` is the constraint's :meth:`_truth_error`.
        """
        ids = c.constraint.instance_ids
        if ids[0] is not None and ids[1] is not None and ids[0] != ids[1]:
            return False
        if error is not None:
            return bool(
                error[0] <= self.p.truth_tolerance_xy and error[1] <= math.radians(self.p.truth_tolerance_yaw_deg)
            )
        if ids[0] is not None and ids[1] is not None:
            return True
        return None

    def settle(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Refuse the candidates still waiting, and take back the loops outside the largest consistent set.

        The back-end re-solves without them (``settlement.taken_back``) before the association
        regroups by its estimate and this stage's final pass matches against it.
        """
        for w in self.waiting:  # the run ended before they were settled
            support = [self._support(a, c.constraint, unlike=w.unlike) for a, c in w.options]
            detail = _support_detail(support, w.need) + " when the run ended"
            self._refuse(w.options[0][0], w.refused, w.options[0][1].gate, detail)
        self.waiting = []
        taken_back = self._take_back_inconsistent()
        self._settled = True
        return settlement if taken_back is None else replace(settlement, taken_back=taken_back)

    def conclude(self, context: RunContext, settlement: Settlement) -> Settlement:
        """The final pass, then the consistency test once more with its loops.

        The final pass matches within the association's final groups (``settlement.groups``) against
        the back-end's estimate without the loops taken back (``settlement.estimate``) when it
        re-solved one, else against the newest estimate. A caller that ends the run without
        :meth:`settle` gets it here first. Hands on the final pass's loops, those the second test
        took back, and every group assignment (for the SGF map).
        """
        if not self._settled:
            settlement = self.settle(context, settlement)
        estimate = settlement.estimate if settlement.estimate is not None else self._estimate
        final: list[LoopConstraint] = []
        if self.p.final_pass and settlement.groups is not None and estimate is not None:
            final = self._final_pass(list(settlement.groups), dict(settlement.group_of), estimate)
        self.final_accepted = len(final)
        taken_back = LoopConstraints(())  # those of settle are out of the graph already
        if final:
            taken_back = self._take_back_inconsistent() or taken_back  # the final pass's loops judged with the others
        return replace(
            settlement,
            final_loops=LoopConstraints(tuple(final)),
            taken_back=taken_back,
            assignments=tuple(self.assignments),
        )

    def finalize(self, context: RunContext) -> None:
        """The loop metrics (Table 3), the accepted loops and every candidate's outcome."""
        errors = [self._truth_error(c) for c in self.accepted]
        truths = [self._true(c, e) for c, e in zip(self.accepted, errors, strict=True)]
        known = [t for t in truths if t is not None]
        loops: dict[str, Any] = {
            "accepted": len(self.accepted),
            "accepted_reverse": sum(bool(c.constraint.reverse) for c in self.accepted),
            "accepted_map": sum(bool(c.constraint.from_map) for c in self.accepted),
            "false_closed": sum(not t for t in known) if known else None,
            "rejected": {k: v for k, v in self.counts.items() if k != "candidates"},
            "candidates": self.counts["candidates"],
            "ties_resolved": self.ties_resolved,
            "aliases_resolved": self.aliases_resolved,
            "distinct": self.distinct,
            "gate_decided": self.gate_decided,
            "position_only": self.position_only,
            "earlier_members": self.earlier_members,
            "final_pass": {"tried": self.final_tried, "accepted": self.final_accepted},
        }
        truth = context.truth if context.truth is not None else self.truth
        if not self.accepted and (truth is not None or self.frames.has_truth()):
            loops["false_closed"] = 0  # nothing accepted, and the truth to judge it by is known
        if truth is not None:
            closed = [r for r in truth.revisits if self._closes(r, truths, truth)]
            loops["closed"] = len(closed)
            loops["closed_reverse"] = sum(bool(r.reverse) for r in closed)
        if self._consistency_entry is not None:
            loops["consistency"] = self._consistency_entry
        context.metrics.setdefault("loops", {}).update(loops)
        context.artifacts["loops"] = [
            self._loop_entry(c, e, t) for c, e, t in zip(self.accepted, errors, truths, strict=True)
        ]
        context.artifacts["loop_candidates"] = list(self.decisions)

    def partial(self, context: RunContext, settlement: Settlement) -> Settlement:
        """The group assignments so far, for the SGF map of a run that stopped early."""
        return replace(settlement, assignments=tuple(self.assignments))

    def _take_back_inconsistent(self) -> LoopConstraints | None:
        """The consistency test over the accepted loops; with ``drop_inconsistent``, those outside are taken back.

        Returns the loops taken back, for the back-end (``None`` without the test). A second round
        (after the final pass) adds to the first round's record.
        """
        threshold = self.p.consistency_threshold
        if threshold is None:
            return None
        truths = [self._true(c, self._truth_error(c)) for c in self.accepted]
        entry, outside = self._consistency(threshold, truths)
        out = set(outside) if self.p.drop_inconsistent else set()
        dropped = [c for k, c in enumerate(self.accepted) if k in out]
        for c in dropped:
            self._taken_back(c, threshold)
        self.accepted = [c for k, c in enumerate(self.accepted) if k not in out]
        before = self._consistency_entry
        if before is not None and self.p.drop_inconsistent:  # the rounds judged different loops: add them up
            entry["outside_largest_set"] = before["outside_largest_set"] + entry["outside_largest_set"]
            counts = [n for n in (before["false_outside"], entry["false_outside"]) if n is not None]
            entry["false_outside"] = sum(counts) if counts else None
        self._consistency_entry = entry
        return LoopConstraints(tuple(c.constraint for c in dropped))

    def _consistency(self, threshold: float, truths: list[bool | None]) -> tuple[dict[str, Any], list[int]]:
        """Accepted loops outside the largest mutually consistent set (:mod:`sgf_plugins.loop.consistency`).

        Returns the metrics entry and those loops' places in ``self.accepted`` (map loops and position-only
        loops, whose cycles have no turn to close, are not judged).
        """
        own = [k for k, c in enumerate(self.accepted) if not (c.constraint.from_map or c.constraint.position_only)]
        constraints = [self.accepted[k].constraint for k in own]
        entry: dict[str, Any] = {"threshold": threshold, "dropped": self.p.drop_inconsistent}
        if not constraints:
            return entry | {"heading_bias_deg_per_m": None, "outside_largest_set": [], "false_outside": 0}, []
        frames, odometry, travelled = self.frames.path()
        measured = [(c.frame_from, c.frame_to, xy_yaw(c.relative)[2], float(c.covariance[2][2])) for c in constraints]
        r = math.radians
        bias = loop_heading_bias(  # taken off the odometry the cycles run through
            frames,
            odometry,
            measured,
            prior_sigma=r(self.p.consistency_yaw_bias_sigma_deg_per_m),
            odometry_sigma_yaw=r(self.p.consistency_odometry_sigma_yaw_deg),
            kernel_width=self.p.consistency_kernel_width,
            reading_sigma=r(self.p.consistency_yaw_bias_reading_sigma_deg_per_m),
        )
        path = bias_corrected_path(odometry, travelled, bias)
        row = {int(f): k for k, f in enumerate(frames)}
        ends = [
            LoopEnds(
                c.frame_from,
                c.frame_to,
                se2(*xy_yaw(c.relative)),
                path[row[c.frame_from]],
                path[row[c.frame_to]],
                float(travelled[row[c.frame_from]]),
                float(travelled[row[c.frame_to]]),
            )
            for c in constraints
        ]
        outside = [own[k] for k in inconsistent_loops(consistency_ratios(ends), threshold)]
        judged = any(truths[k] is not None for k in own)  # with ground truth: how many of them are false
        entry |= {
            "heading_bias_deg_per_m": math.degrees(bias),
            "outside_largest_set": [
                [self.accepted[k].constraint.frame_from, self.accepted[k].constraint.frame_to] for k in outside
            ],
            "false_outside": sum(truths[k] is False for k in outside) if judged else None,
        }
        return entry, outside

    def _taken_back(self, c: _Candidate, threshold: float) -> None:
        """Mark an accepted loop's row of ``loop_candidates.csv`` as taken back by the consistency test."""
        self.counts["inconsistent"] += 1
        k = c.constraint
        for row in reversed(self.decisions):
            if (row["frame_from"], row["frame_to"], row["outcome"]) == (k.frame_from, k.frame_to, "accepted"):
                row["outcome"] = "inconsistent"
                row["detail"] = (
                    f"{row['detail']}; " if row["detail"] else ""
                ) + f"taken back at the end: outside the largest set of loops agreeing within {threshold:g}"
                return

    def _final_pass(
        self, groups: list[Any], group_of: dict[tuple[int, int], int], estimate: PoseEstimate
    ) -> list[LoopConstraint]:
        """Close the drive-bys each final group joins that no loop joins yet, against the final estimate.

        The association's split and merge at the end (with the estimate the loops made) put some
        revisits into their marking's group only then: one seen before any loop, while the gate
        reached several look-alikes, may have joined another's group. For each group, each member
        and its closest earlier member (eq. 10) of another drive-by (``min_separation_distance``)
        are matched once more when no accepted loop between members of the group joins the two
        drive-bys (both ends within that distance of path); the match is closed when it passes
        ICP and the gate, and the gate alone decides it (:meth:`_gate_decides`, with every SGF
        counted in its final group).
        """
        # The run is over: every SGF counts in its final group from now on (the look-alike test).
        self._sgf_group = [
            group_of.get((f, t), g) for f, t, g in zip(self._sgf_frame, self._sgf_track, self._sgf_group, strict=True)
        ]
        out: list[LoopConstraint] = []
        for group in groups:
            if group.symmetric or len(group.members) < 2:
                continue
            members = sorted(
                (m for m in group.members if m.sgf.frame_index in self.frames), key=lambda m: m.sgf.frame_index
            )
            frames = {m.sgf.frame_index for m in members}
            for k, query in enumerate(members):
                j = query.sgf.frame_index
                earlier = [
                    m
                    for m in members[:k]
                    if self._separated(m.sgf.frame_index, j) and not self._joined(m.sgf.frame_index, j, frames)
                ]
                if not earlier:
                    continue
                a = _match_closest(GroupAssignment(query, group.group_id, False, 1.0, 0, 0.0, None, False), earlier)
                assert a.matched is not None
                self.final_tried += 1
                candidate = self._evaluate(a, estimate)
                ends = (a.matched.sgf.frame_index, j)
                ids = (a.matched.sgf.instance_id, query.sgf.instance_id)
                if isinstance(candidate, str):
                    detail = "final pass" + (f": {self._icp_detail}" if candidate == "icp" else "")
                    self._log(ends, ids, group.group_id, False, candidate, self._reading, detail)
                elif not self._gate_decides(a, candidate, estimate):
                    detail = f"final pass: {self._gate_refusal}"
                    self._log(ends, ids, group.group_id, False, "consensus", candidate.gate, detail)
                else:
                    self.accepted.append(candidate)
                    self._log(ends, ids, group.group_id, False, "accepted", candidate.gate, "final pass")
                    out.append(candidate.constraint)
        return out

    def _joined(self, i: int, j: int, frames: set[int]) -> bool:
        """Whether an accepted loop between two of ``frames`` (a group's) joins the drive-bys of ``i`` and ``j``."""
        near = self.p.min_separation_distance
        di, dj = self.frames.distance(i), self.frames.distance(j)
        for c in self.accepted:
            k = c.constraint
            if k.from_map or k.frame_from not in frames or k.frame_to not in frames:
                continue
            a, b = self.frames.distance(k.frame_from), self.frames.distance(k.frame_to)
            if (abs(a - di) < near and abs(b - dj) < near) or (abs(a - dj) < near and abs(b - di) < near):
                return True
        return False

    def _loop_entry(self, c: _Candidate, error: tuple[float, float] | None, true: bool | None) -> dict[str, Any]:
        """One accepted loop as the run reports it (``artifacts['loops']``, ``loops.csv``)."""
        k = c.constraint
        x, y, yaw = xy_yaw(k.relative)
        return {
            "frame_from": k.frame_from,
            "frame_to": k.frame_to,
            "time_from": None if k.from_map else self.frames.get_time(k.frame_from),
            "time_to": self.frames.get_time(k.frame_to),
            "relative_xy_yaw": [x, y, yaw],
            "group_id": c.group_id,
            "reverse": k.reverse,
            "from_map": k.from_map,
            "position_only": k.position_only,
            "fitness": k.fitness,
            "inlier_ratio": k.inlier_ratio,
            "instance_ids": list(k.instance_ids),
            "truth_error_m": None if error is None else error[0],
            "truth_error_deg": None if error is None else math.degrees(error[1]),
            "true": None if true is None else bool(true),
        }

    def _closes(self, pair: RevisitPair, truths: list[bool | None], truth: SequenceTruth) -> bool:
        """Whether an accepted, not false constraint joins the pair's two passes over its marking."""
        for c, t in zip(self.accepted, truths, strict=True):
            k = c.constraint
            if (
                not k.from_map
                and t is not False
                and k.instance_ids == (pair.instance_id, pair.instance_id)
                and pair.first == truth.drive_by(pair.instance_id, k.frame_from)
                and pair.second == truth.drive_by(pair.instance_id, k.frame_to)
            ):
                return True
        return False


def _match_closest(a: GroupAssignment, members: list[SgfDescriptor]) -> GroupAssignment:
    """The match redone with the closest of ``members`` (eq. 10 at its best shift) as the matched SGF."""
    query = np.asarray(a.descriptor.matrix)
    profiles = shifted_distances(query, np.stack([np.asarray(m.matrix) for m in members]))
    k = int(np.argmin(profiles.min(axis=1)))
    shift = best_shift(profiles[k])
    yaw = shift_to_yaw(shift, profiles.shape[1])
    return replace(a, matched=members[k], distance=float(profiles[k, shift]), shift=shift, yaw=yaw)


def _largest_sigma(r: IcpResult) -> float:
    """The largest standard deviation of an ICP fit's covariance (inf when it is not finite)."""
    if not np.all(np.isfinite(r.covariance)):
        return math.inf
    return math.sqrt(float(np.linalg.eigvalsh(r.covariance).max()))


def _support_detail(support: list[float], need: float) -> str:
    """The agreeing neighbours of each option (weighted) against the number needed, for ``loop_candidates.csv``."""
    return "support " + ", ".join(f"{n:.3g}" for n in support) + f" of {need:g} needed"


def _odometry_xy(descriptor: SgfDescriptor) -> np.ndarray:
    """An SGF's centroid (x, y) in the odometry frame of the run that saw it."""
    odometry = np.asarray(descriptor.sgf.odometry, dtype=np.float64)
    return odometry[:2, :2] @ np.asarray(descriptor.centroid, dtype=np.float64)[:2] + odometry[:2, 3]


def _odometry_yaw(descriptor: SgfDescriptor) -> float:
    """The heading (rad) of the frame that saw an SGF, in the odometry frame of its run."""
    return float(xy_yaw(np.asarray(descriptor.sgf.odometry, dtype=np.float64))[2])


def _agreement(
    profiles: np.ndarray, predicted: np.ndarray, distance: float, heading_deg: float | None, unoriented: float
) -> float:
    """How much a neighbour agrees with its best earlier look-alike: 1, ``unoriented``, or 0.

    ``profiles`` holds eq. 10 at every column shift against each earlier SGF, ``predicted`` the
    neighbour's heading in each one's frame. It agrees when some profile is at most ``distance``
    within ``heading_deg`` of the predicted heading (anywhere when ``None``: weight 1), and counts
    ``unoriented`` when that profile is as low at the opposite heading (the shape fixes no heading).
    """
    if heading_deg is None:
        return 1.0 if float(profiles.min()) <= distance else 0.0
    n_s = profiles.shape[1]
    shifts = np.arange(n_s)[None, :]
    width = heading_deg / 360.0 * n_s

    def lowest(yaws: np.ndarray) -> np.ndarray:
        centre = np.array([yaw_to_shift(float(y), n_s) for y in yaws])[:, None]
        gap = np.abs(np.mod(shifts - centre + n_s / 2.0, n_s) - n_s / 2.0)
        return np.where(gap <= width, profiles, np.inf).min(axis=1)

    at = lowest(predicted)
    opposite = lowest(predicted + math.pi)
    weights = np.where(at <= distance, np.where(opposite <= distance, unoriented, 1.0), 0.0)
    return float(weights.max())


def _merged(fits: list[IcpResult]) -> IcpResult:
    """One fit from ICP results of one alignment: the middle of their yaws, the best's covariance plus their spread.

    The middle is the SE(2) mean of the two fits furthest apart in yaw (ICP stops on both walls of a
    shallow valley; stops on one wall are not votes for it).
    """
    if len(fits) == 1:
        return fits[0]
    first = fits[0].transform
    offsets = np.array([se2_params(invert(first) @ r.transform) for r in fits])
    ends = offsets[[int(np.argmin(offsets[:, 2])), int(np.argmax(offsets[:, 2]))]]
    middle = first @ se2(*ends.mean(axis=0))
    spread = np.array([se2_params(invert(middle) @ r.transform) for r in fits])
    covariance = fits[0].covariance + spread.T @ spread / len(fits)
    return replace(fits[0], transform=middle, covariance=covariance)


def _distinct_yaws(yaws: list[float], taken: list[float]) -> list[float]:
    """``yaws`` without repeats (and without those in ``taken``), in order."""
    out: list[float] = []
    for y in yaws:
        if all(abs(wrap_angle(y - s)) > 1e-6 for s in taken + out):
            out.append(y)
    return out


def _distinct_fits(fits: list[IcpResult], points: np.ndarray) -> list[IcpResult]:
    """``fits`` without those laying ``points`` within ``SAME_FIT_M`` of an earlier one (the same stop of ICP)."""
    out: list[IcpResult] = []
    for r in fits:
        if all(_displacement(r.transform, o.transform, points) > SAME_FIT_M for o in out):
            out.append(r)
    return out


def _yaw_spread(fits: list[IcpResult]) -> float:
    """The largest yaw difference (rad) between ICP results of one alignment."""
    yaws = [se2_params(r.transform)[2] for r in fits]
    return max((abs(wrap_angle(a - b)) for a, b in itertools.combinations(yaws, 2)), default=0.0)


def _displacement(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float:
    """RMS distance (m) between ``points`` moved by the 2-D transforms ``a`` and ``b`` (3x3)."""
    delta = points @ (a[:2, :2] - b[:2, :2]).T + (a[:2, 2] - b[:2, 2])
    return float(np.sqrt(np.mean(np.sum(delta**2, axis=1))))


def position_only_loop(
    relative: np.ndarray, centre: np.ndarray, turn: float, sigma2: float, free_sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """A position-only loop: ``relative`` turned to ``turn`` about the marking at ``centre``, and its covariance.

    ``centre`` is the marking's (x, y) in the later frame; the loop keeps where ``relative`` puts
    it, with variance ``sigma2`` on that place and sigma ``free_sigma`` on the turn.
    ``relative = A(seen) Rot(turn) A(centre)^-1`` with ``A`` a translation; a perturbation of the
    turn about the marking, ``eta``, is the later frame's ``Ad(A(centre)) eta`` (GTSAM's Pose2 adjoint),
    so the covariance is that adjoint applied to ``diag(sigma2, sigma2, free_sigma^2)``. Where the two
    poses see the marking at one place, the factor's error is the turn alone, whitened by ``free_sigma``.
    """
    c = np.asarray(centre, dtype=np.float64)[:2]
    seen = relative[:2, :2] @ c + relative[:2, 3]
    out = np.eye(4)
    out[:2, :2] = [[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]]
    out[:2, 3] = seen - out[:2, :2] @ c
    adjoint = np.array([[1.0, 0.0, c[1]], [0.0, 1.0, -c[0]], [0.0, 0.0, 1.0]])
    return out, adjoint @ np.diag([sigma2, sigma2, free_sigma**2]) @ adjoint.T


def _pose4(r: IcpResult) -> np.ndarray:
    """The 4x4 planar pose of an ICP result."""
    x, y, yaw = se2_params(r.transform)
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:2, 3] = (x, y)
    return pose


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the loop-closing variants."""
    registry.add(IcpLoopClosing)
