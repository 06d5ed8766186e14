"""The parameters of the online SGF grouping, one model per concern: eq. 10, gate, repeated patterns, end of run."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from sgf_pipeline import StageParams
from sgf_pipeline.config import FROM_MAP_PRIOR


class MatchParams(StageParams):
    """Eq. 10: the distance, the threshold of a new group, the ranking of groups and shifts, the symmetry test."""

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
    position_weight: float = Field(
        0.3,
        ge=0.0,
        description="added to a group's eq. 10 distance times how far out in the spatial gate its nearest member lies "
        "(0 at the query's map position, this at the gate's edge): groups are ranked by both; 0 = eq. 10 alone",
    )
    yaw_tolerance: float = Field(
        0.02,
        ge=0.0,
        description="shifts within this eq. 10 distance of the best are ties, resolved by the pose estimate's yaw",
    )


class GateParams(StageParams):
    """The spatial gate: only groups with a member near the query on the map, the radius growing with drift."""

    enabled: bool = Field(True, description="only consider groups with a member near the SGF on the map")
    radius: float = Field(1.5, gt=0.0, description="gate radius (m) between SGF centroids seen from one place")
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
    prior_radius: float | None = Field(
        None, gt=0.0, description="gate (m) around members of groups seeded from a saved map; null = no gate"
    )
    anchored: bool = Field(
        True,
        description="count the gate's distance travelled from the loop closures the estimate satisfies (drift "
        "restarts at a closed loop); false = between the two sightings only",
    )
    anchor_tolerance: float = Field(
        0.5, gt=0.0, description="a loop anchors the gate when the estimate meets its relative pose within this (m)"
    )


class RepeatsParams(StageParams):
    """Repeated patterns: neighbouring copies of one marking seen moments ago elsewhere."""

    window: float = Field(
        15.0,
        ge=0.0,
        description="a group member seen within this many metres of travel, but away from the query, is another "
        "copy of a repeated pattern (give-way triangles, zebra bars, dashes): the query may not join it; 0 = no "
        "repeated-pattern test",
    )
    radius: float = Field(0.5, gt=0.0, description="...away means farther than this on the map (m)")
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
        description="a query whose best match is a neighbouring copy (ties it): joins the best "
        "other group (apart), or opens its own (new, aliased: no loop factors)",
    )


class EndParams(StageParams):
    """The end of the run: groups split and merged by the final estimate."""

    split: bool = Field(
        True,
        description="at the end of the run, split each group into the parts that the final estimate puts within "
        "the spatial gate of each other (identical markings joined while the gate was tens of metres wide)",
    )
    merge: bool = Field(
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


class OnlineGroupsParams(StageParams):
    """Eq. 10 grouping with the paper's 0.7 threshold, a spatial gate and the symmetry test."""

    match: MatchParams = Field(default_factory=MatchParams, description="eq. 10")
    gate: GateParams = Field(default_factory=GateParams, description="the spatial gate")
    repeats: RepeatsParams = Field(default_factory=RepeatsParams, description="repeated patterns")
    end: EndParams = Field(default_factory=EndParams, description="the end of the run")
    prior_map: str | None = Field(
        None,
        description="an SGF map (sgf_map.safetensors) whose groups seed the association: localization on it "
        "(set map.prior)",
        json_schema_extra=FROM_MAP_PRIOR,
    )
