"""Parameters of ICP loop closing, one model per concern: ``loop.<concern>.<key>``."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from sgf_pipeline import StageParams


class IcpParams(StageParams):
    """ICP between a new SGF and its match, and the tests a fit must pass (``loop.icp``)."""

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


class FitParams(StageParams):
    """ICP's yaw seeds and how its fits of one alignment become one (``loop.fit``)."""

    seed_both_signs: bool = Field(
        True, description="also seed ICP with the negated column-shift yaw (robust to the shift's sign convention)"
    )
    extra_yaw_seeds: int = Field(
        1, ge=0, le=16, description="further seeds evenly spaced in yaw around the first (1: its half-turn alternative)"
    )
    ambiguity_ratio: float = Field(
        1.25,
        ge=1.0,
        description="seeds within this factor of the best RMS are ambiguous; the one nearest the prediction wins",
    )


class SeparationParams(StageParams):
    """How far before the query a matched SGF must lie to be another pass (``loop.separation``)."""

    min_frames: int = Field(0, ge=0, description="the matched SGF must be at least this many frames earlier")
    min_time: float = Field(0.0, ge=0.0, description="...and this many seconds earlier")
    min_distance: float = Field(10.0, ge=0.0, description="...and this far back along the odometry path (m)")


class CovarianceParams(StageParams):
    """A loop's covariance: ICP's, plus floors for what it cannot see (``loop.covariance``)."""

    floor_xy: float = Field(0.05, gt=0.0, description="added to ICP's translation sigma (m): IPM, sampling")
    floor_yaw_deg: float = Field(1.0, gt=0.0, description="added to ICP's yaw sigma (deg)")


class GateParams(StageParams):
    """The chi-square gate, its drift model, and when it decides a match alone (``loop.gate``)."""

    enabled: bool = Field(True, description="chi-square test of the ICP pose against the estimate's prediction")
    probability: float = Field(0.999, gt=0.0, lt=1.0, description="chi-square (3 dof) acceptance probability")
    floor_xy: float = Field(0.5, gt=0.0, description="prediction sigma when freshly anchored (m)")
    floor_yaw_deg: float = Field(3.0, gt=0.0, description="prediction sigma when freshly anchored (deg)")
    sigma_xy: float = Field(
        0.05,
        ge=0.0,
        description="translation random walk of the drift (m per sqrt(m)) until the camera measures it "
        "(odometry_scale, PoseEstimate.drift); a wide prior for wheel odometry",
    )
    sigma_yaw_deg: float = Field(
        0.5,
        ge=0.0,
        description="heading random walk of the drift (deg per sqrt(m)) until the camera measures it; a wide prior",
    )
    scale_error: float = Field(
        0.05, ge=0.0, description="odometry scale error (fraction of distance) until the camera measures it; wide prior"
    )
    bias_from_backend: bool = Field(
        True,
        description="the gate counts the heading bias as the back-end's model holds it (the uncertainty left where "
        "it corrects the odometry, the measured bias elsewhere); false = the bias wheel odometry is expected to have",
    )
    support_sigma: float | None = Field(
        5.0,
        gt=0.0,
        description="a match the gate predicts within this position sigma (m) needs no agreeing neighbours, unless an "
        "SGF of another group that looks like the query (eq. 10 at most consensus.distance) was seen within the "
        "gate's reach of the matched one: ICP and the gate decide (null = consensus.min_support always)",
    )


class ConsensusParams(StageParams):
    """The neighbour consensus: agreeing markings around both sightings (``loop.consensus``)."""

    window: float = Field(
        60.0, gt=0.0, description="m of travel: SGFs seen this far around each sighting are its neighbours"
    )
    radius: float = Field(
        0.75, gt=0.0, description="a neighbour agrees when the match puts it this close (m) to an earlier SGF..."
    )
    drift: float = Field(
        0.02, ge=0.0, description="...plus this much per metre travelled from either sighting (local odometry drift)"
    )
    exclude: float = Field(
        2.0, ge=0.0, description="neighbours this close (m) to the matched SGF are the same marking, not evidence"
    )
    distance: float = Field(0.15, gt=0.0, le=1.0, description="...and look like it: eq. 10 distance at most this")
    heading_deg: float | None = Field(
        None,
        gt=0.0,
        le=180.0,
        description="a neighbour agrees only when it looks alike at the heading the match predicts for it, within "
        "this (deg); null: at any heading (rotation-invariant eq. 10)",
    )
    unoriented_weight: float = Field(
        0.5,
        ge=0.0,
        le=1.0,
        description="a neighbour that looks alike at the opposite heading too (a bar, a disc) fixes no heading: it "
        "counts this much of an agreeing marking",
    )
    tie_support: int = Field(
        1,
        ge=0,
        description="look-alike groups tied by eq. 10: the one match with at least this many agreeing neighbours "
        "wins (0 = tied matches never give loop factors)",
    )
    min_support: int = Field(1, ge=0, description="agreeing neighbours every loop needs (0 = ICP and the gate only)")
    aliased_support: int = Field(
        2,
        ge=0,
        description="a match into an aliased group (a repeated pattern) needs this many agreeing neighbours that do "
        "not look like the query, so that no copy of the pattern vouches for another, each within half the pattern's "
        "period (0 = aliased groups never give loop factors)",
    )
    wait: bool = Field(
        True,
        description="a match short of agreeing neighbours waits while the robot drives consensus.window metres on: "
        "SGFs seen after it count too (false = decide on the SGFs seen before it)",
    )


class DistinctParams(StageParams):
    """A match into a distinct marking, like no SGF of another group (``loop.distinct``)."""

    support: int | None = Field(
        0,
        ge=0,
        description="agreeing neighbours a loop into a distinct marking needs: one the query looks like (eq. 10 at "
        "most consensus.distance) and that no SGF of another group looks like (all farther than distinct.distance); "
        "null = consensus.min_support",
    )
    distance: float = Field(
        0.15, ge=0.0, le=1.0, description="eq. 10: an SGF of another group this close makes a marking not distinct"
    )
    ratio: float | None = Field(
        None,
        gt=1.0,
        description="...unless it is this many times farther (eq. 10) than the match and farther than "
        "distinct.floor: the query is far more like its match than like anything else seen (null: off)",
    )
    floor: float = Field(
        0.05, ge=0.0, le=1.0, description="eq. 10: an SGF of another group this close always makes a marking common"
    )


class SymmetricParams(StageParams):
    """A match into a symmetric group, a round manhole (``loop.symmetric``)."""

    position_only: bool = Field(
        True,
        description="a match into a symmetric group (a round manhole, whose heading cannot be read) gives a "
        "position-only loop: where the marking's centre lies from both poses, the turn left free; closed only when "
        "the gate alone decides (gate.support_sigma); false = no factor",
    )
    yaw_sigma_deg: float = Field(
        90.0, gt=0.0, description="a position-only loop's sigma of the turn about its marking (deg): nearly free"
    )


class FinalPassParams(StageParams):
    """The end-of-run pass over the final groups (``loop.final_pass``)."""

    enabled: bool = Field(
        True,
        description="at the end of the run, match once more the members of each final SGF group (after the "
        "association's split and merge) from two drive-bys that no loop joins yet, against the final estimate; "
        "a match is closed when ICP passes and the gate alone decides it (gate.support_sigma)",
    )


class MapParams(StageParams):
    """Matches into a prior SGF map before the run is placed in it (``loop.map``)."""

    anchor_matches: int = Field(
        2, ge=1, description="consistent map matches (different groups) needed before a run is placed in the map"
    )
    pending: int = Field(16, ge=1, description="unconfirmed map matches kept while waiting for the anchor")


class EvaluationParams(StageParams):
    """Scoring the loops against the ground truth: never used to decide one (``loop.evaluation``)."""

    truth_tolerance_xy: float = Field(0.5, gt=0.0, description="a loop off the ground truth by more (m) is false")
    truth_tolerance_yaw_deg: float = Field(5.0, gt=0.0, description="...or by more than this (deg)")


class IcpLoopParams(StageParams):
    """Parameters of ICP loop closing, its acceptance tests and the uncertainty gate."""

    icp: IcpParams = Field(default_factory=IcpParams, description="ICP between two SGFs and the tests of one fit")
    fit: FitParams = Field(default_factory=FitParams, description="ICP's yaw seeds and the choice among its fits")
    separation: SeparationParams = Field(
        default_factory=SeparationParams, description="how far back a matched SGF must lie to be another pass"
    )
    covariance: CovarianceParams = Field(default_factory=CovarianceParams, description="a loop's covariance")
    gate: GateParams = Field(
        default_factory=GateParams, description="the chi-square gate against the estimate's prediction, its drift model"
    )
    consensus: ConsensusParams = Field(
        default_factory=ConsensusParams, description="the neighbour consensus that tells look-alike markings apart"
    )
    distinct: DistinctParams = Field(
        default_factory=DistinctParams, description="a match into a distinct marking, which vouches for itself"
    )
    symmetric: SymmetricParams = Field(
        default_factory=SymmetricParams, description="a match into a symmetric group (a round manhole)"
    )
    final_pass: FinalPassParams = Field(
        default_factory=FinalPassParams, description="the end-of-run pass over the final groups"
    )
    map: MapParams = Field(default_factory=MapParams, description="matches into a prior SGF map")
    evaluation: EvaluationParams = Field(
        default_factory=EvaluationParams, description="scoring the loops against the ground truth"
    )
