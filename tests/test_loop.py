"""Loop closing with SGF factors: constraints from ICP, rejection, the uncertainty gate, and Table 3 metrics."""

from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
from backend_world import (
    CALIBRATION,
    SHAPES,
    Marking,
    OracleAssociation,
    arrow_points,
    descriptor,
    make_world,
    run_stages,
)
from sgf_plugins.backend.lm import GtsamLmBackend
from sgf_plugins.backend.params import LmParams
from sgf_plugins.loop.fitting import position_only_loop
from sgf_plugins.loop.icp import Icp2d, IcpResult, IcpSettings
from sgf_plugins.loop.params import (
    ConsensusParams,
    DistinctParams,
    FinalPassParams,
    FitParams,
    GateParams,
    IcpLoopParams,
    SeparationParams,
    SymmetricParams,
)
from sgf_plugins.loop.stage import IcpLoopClosing
from sgf_plugins.sgf.association.stage import SgfGroup
from sgf_plugins.shared.drift import EXPECTED_YAW_BIAS, drift_covariance, measured_sigmas
from sgf_plugins.shared.polar import shifted_distances
from sgf_plugins.shared.se2 import se2

from sgf_pipeline import RunContext
from sgf_pipeline.geometry import invert, pose_from_xy_yaw, wrap_angle, xy_yaw
from sgf_pipeline.stage import Settlement
from sgf_pipeline.types import (
    Frame,
    GroupAssignment,
    GroupAssignments,
    LookAlike,
    LoopConstraint,
    OdometryDrift,
    OdometryScale,
    PoseEstimate,
)


@pytest.fixture(scope="module")
def world():  # type: ignore[no-untyped-def]
    return make_world(seed=1)


def test_true_revisits_become_constraints_at_the_true_relative_pose(world) -> None:  # type: ignore[no-untyped-def]
    # ICP and the gate only (the consensus is tested below); round markings give no loop (position-only loops below)
    stage = IcpLoopClosing(
        IcpLoopParams(consensus=ConsensusParams(min_support=0), symmetric=SymmetricParams(position_only=False))
    )
    run = run_stages(world, loop=stage, association=OracleAssociation(world, by="instance"))
    asymmetric = [r for r in world.truth.revisits if not world.truth.markings[r.instance_id].symmetric]
    assert len(run.loops) == len(asymmetric) == 8
    floor = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])
    for c in run.loops:
        assert c.instance_ids[0] == c.instance_ids[1]
        assert c.frame_from < c.frame_to and not c.from_map
        truth = invert(world.gt[c.frame_from]) @ world.gt[c.frame_to]
        x, y, yaw = xy_yaw(invert(truth) @ c.relative)
        # within 7 cm and 1.5 deg (a yaw error moves the robot by its lever arm), and well inside the
        # constraint's own covariance (ICP's yaw probes widen it where the fit's heading is shallow)
        assert math.hypot(x, y) < 0.07
        assert abs(math.degrees(yaw)) < 1.5
        error = np.array([x, y, yaw])
        assert float(error @ np.linalg.solve(c.covariance, error)) < 2.0
        assert c.reverse == (abs(xy_yaw(truth)[2]) > math.pi / 2)
        assert np.all(np.diag(c.covariance) >= np.diag(floor))
        assert np.allclose(c.covariance, c.covariance.T)
        assert c.fitness < 0.025 and c.inlier_ratio > 0.85
    loops = run.context.metrics["loops"]
    assert loops["closed"] == 8
    assert loops["closed_reverse"] == 4
    assert loops["false_closed"] == 0
    assert loops["rejected"]["symmetric"] == 2  # the manhole's two revisits
    # every decision is logged (loop_candidates.csv): the outcomes tally with the counts, frames and truth included
    decisions = run.context.artifacts["loop_candidates"]
    outcomes = [d["outcome"] for d in decisions]
    assert outcomes.count("accepted") == 8 and outcomes.count("symmetric") == 2
    assert {k: outcomes.count(k) for k in loops["rejected"]} == loops["rejected"]
    assert len(decisions) == loops["candidates"]
    symmetric = [d for d in decisions if d["outcome"] == "symmetric"]
    assert all(world.truth.markings[d["instance_to"]].symmetric for d in symmetric)
    accepted = [(d["frame_from"], d["frame_to"]) for d in decisions if d["outcome"] == "accepted"]
    assert accepted == [(c.frame_from, c.frame_to) for c in run.loops]
    assert len(run.context.artifacts["loops"]) == 8
    assert all(entry["true"] is True for entry in run.context.artifacts["loops"])
    assert len(run.settlement.assignments) == sum(len(v) for v in world.sgfs.values())
    # a loop also needs a neighbouring marking that agrees: the toy world's first two revisits of a stretch
    # have none behind them, and lose their loops when only earlier SGFs may vouch for them, but keep them
    # when they wait for the markings seen after them (the default); a distinct marking (like nothing else
    # seen) vouches for itself
    cases = [
        (False, None, (6, 0, 2, 0)),
        (True, None, (8, 0, 0, 0)),
        (False, 0, (7, 0, 1, 5)),
    ]
    for wait, distinct, expected in cases:
        params = IcpLoopParams(
            consensus=ConsensusParams(wait=wait),
            distinct=DistinctParams(support=distinct),
            symmetric=SymmetricParams(position_only=False),
        )
        consensus = run_stages(world, loop=IcpLoopClosing(params), association=OracleAssociation(world, by="instance"))
        metrics = consensus.context.metrics["loops"]
        got = (metrics["closed"], metrics["false_closed"], metrics["rejected"]["consensus"], metrics["distinct"])
        assert got == expected


def test_the_gate_rejects_look_alike_markings_and_can_be_turned_off(world) -> None:  # type: ignore[no-untyped-def]
    # Grouped by design, the two arrows (30 m and 40 m apart in the world) share a group.
    gated = run_stages(world, loop=IcpLoopClosing(IcpLoopParams(consensus=ConsensusParams(min_support=0))))
    assert all(c.instance_ids[0] == c.instance_ids[1] for c in gated.loops)
    assert gated.context.metrics["loops"]["false_closed"] == 0
    assert gated.context.metrics["loops"]["rejected"]["gate"] == 4
    # loop_candidates.csv says what the gate saw: the look-alikes' chi-square above its threshold, the loops' under
    threshold = IcpLoopClosing(IcpLoopParams()).threshold
    decisions = gated.context.artifacts["loop_candidates"]
    refused = [d for d in decisions if d["outcome"] == "gate"]
    accepted = [d for d in decisions if d["outcome"] == "accepted"]
    assert len(refused) == 4 and all(d["gate_chi2"] > threshold for d in refused)
    assert accepted and all(d["gate_chi2"] <= threshold for d in accepted)
    for d in refused + accepted:  # the prediction's sigma: the 0.5 m floor, grown with the travel since an anchor
        assert d["anchored_distance"] >= 0.0
        expected = math.sqrt(drift_covariance(d["anchored_distance"], IcpLoopParams().gate)[0, 0])
        assert d["gate_sigma_xy"] == pytest.approx(expected, abs=0.01)  # distance rounded to cm
    assert all(d["gate_chi2"] is None for d in decisions if d["outcome"] in ("symmetric", "separation"))
    ungated_params = IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(min_support=0))
    ungated = run_stages(world, loop=IcpLoopClosing(ungated_params))
    look_alikes = [c for c in ungated.loops if c.instance_ids[0] != c.instance_ids[1]]
    assert len(look_alikes) == 4
    assert ungated.context.metrics["loops"]["false_closed"] == 4
    # look-alikes take the place of true loops in the arrow group: fewer pairs closed
    assert ungated.context.metrics["loops"]["closed"] < 8
    # the neighbour consensus alone (min_support = 1, asked of every match) also keeps the look-alikes out
    params = IcpLoopParams(
        gate=GateParams(enabled=False),
        distinct=DistinctParams(support=None),
        symmetric=SymmetricParams(position_only=False),
    )
    consensus = run_stages(world, loop=IcpLoopClosing(params))
    assert consensus.context.metrics["loops"]["false_closed"] == 0
    assert consensus.context.metrics["loops"]["rejected"]["consensus"] == 4
    refused = [d for d in consensus.context.artifacts["loop_candidates"] if d["outcome"] == "consensus"]
    assert len(refused) == 4 and all(d["instance_from"] != d["instance_to"] for d in refused)  # the look-alikes
    assert [d["detail"] for d in refused] == ["support 0 of 1 needed"] * 3 + [
        "support 0 of 1 needed when the run ended"
    ]
    assert consensus.context.metrics["loops"]["closed"] == 5
    # ...but not when a distinct marking vouches for itself: the two arrows share their group, so nothing in
    # another group looks like them; that default leans on the gate, which keeps them out (above)
    lenient = run_stages(world, loop=IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False))))
    assert lenient.context.metrics["loops"]["false_closed"] == 3
    # a caller that ends the run without settle gets the same (conclude settles first)
    unsettled = run_stages(
        world, loop=IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False))), settle=False
    ).context.metrics
    assert unsettled["loops"] == lenient.context.metrics["loops"]
    default = run_stages(world, loop=IcpLoopClosing(IcpLoopParams()))  # five, and one manhole's, position only
    assert default.context.metrics["loops"]["false_closed"] == 0 and default.context.metrics["loops"]["closed"] == 6
    assert default.context.metrics["loops"]["position_only"] == 1
    # with the heading test and a manhole worth half a marking, the tee's revisit (only the manhole behind it)
    # is refused too
    headed = run_stages(
        world,
        loop=IcpLoopClosing(
            IcpLoopParams(
                gate=GateParams(enabled=False),
                consensus=ConsensusParams(heading_deg=15.0, wait=False),
                distinct=DistinctParams(support=None),
                symmetric=SymmetricParams(position_only=False),
            )
        ),
    )
    assert headed.context.metrics["loops"]["false_closed"] == 0
    assert headed.context.metrics["loops"]["rejected"]["consensus"] == 5
    assert headed.context.metrics["loops"]["closed"] == 4


def _straight_run(n: int, yaw_at_end: float) -> list[Frame]:
    """Frames 1 m apart along x, and a last frame back at the origin turned by ``yaw_at_end``."""
    poses = [pose_from_xy_yaw(float(k), 0.0, 0.0) for k in range(n)] + [pose_from_xy_yaw(0.3, 0.1, yaw_at_end)]
    return [Frame(k, 0.5 * k, np.zeros((2, 2), np.uint8), p, CALIBRATION, ground_truth=p) for k, p in enumerate(poses)]


def _view(frame: Frame, marking: Marking) -> object:
    inv = invert(frame.odometry)
    return descriptor(frame, marking, marking.world_points() @ inv[:2, :2].T + inv[:2, 3])


@pytest.mark.parametrize(("both_signs", "expected"), [(True, 1), (False, 0)])
def test_the_column_shift_yaw_is_tried_with_both_signs(both_signs: bool, expected: int) -> None:
    frames = _straight_run(20, math.radians(100))
    marking = Marking(1, "arrow", (2.5, 0.0, 0.3))
    first, last = _view(frames[0], marking), _view(frames[-1], marking)
    # the association's shift convention is the opposite of ours: it reports -100 degrees
    assignment = GroupAssignment(last, 0, False, 0.1, -25, math.radians(-100), first, False)  # type: ignore[arg-type]
    stage = IcpLoopClosing(
        IcpLoopParams(
            fit=FitParams(seed_both_signs=both_signs, extra_yaw_seeds=0),
            separation=SeparationParams(min_distance=5.0),
            consensus=ConsensusParams(min_support=0),
        )
    )
    out = [stage.process(frame=f, assignments=None, estimate=None) for f in frames[:-1]]
    out.append(stage.process(frame=frames[-1], assignments=GroupAssignments((assignment,)), estimate=None))
    loops = [c for o in out for c in o.items]
    assert len(loops) == expected
    if loops:
        truth = invert(frames[0].odometry) @ frames[-1].odometry
        assert np.allclose(xy_yaw(loops[0].relative), xy_yaw(truth), atol=0.01)


def test_an_sgf_matched_within_the_same_pass_is_not_a_loop() -> None:
    frames = _straight_run(6, 0.0)
    marking = Marking(1, "arrow", (4.0, 0.0, 0.0))
    a, b = _view(frames[1], marking), _view(frames[3], marking)
    assignment = GroupAssignment(b, 0, False, 0.1, 0, 0.0, a, False)  # type: ignore[arg-type]
    for min_distance, expected in ((10.0, 0), (1.0, 1)):
        stage = IcpLoopClosing(
            IcpLoopParams(
                separation=SeparationParams(min_distance=min_distance), consensus=ConsensusParams(min_support=0)
            )
        )
        found = []
        for f in frames[:4]:
            items = GroupAssignments((assignment,)) if f.index == 3 else None
            found += stage.process(frame=f, assignments=items, estimate=None).items
        assert len(found) == expected
        assert stage.counts["separation"] == 1 - expected


def test_sgfs_with_fewer_points_than_icp_needs_are_counted_and_give_no_factor() -> None:
    frames = _straight_run(20, 0.0)
    marking = Marking(1, "arrow", (2.5, 0.0, 0.0))
    a, b = _view(frames[0], marking), _view(frames[-1], marking)
    two = replace(b, points=b.points[:2])  # type: ignore[type-var]
    for query, expected in ((two, 0), (b, 1)):
        stage = IcpLoopClosing(
            IcpLoopParams(separation=SeparationParams(min_distance=5.0), consensus=ConsensusParams(min_support=0))
        )
        for f in frames[:-1]:
            stage.process(frame=f, assignments=None, estimate=None)
        assignment = GroupAssignment(query, 0, False, 0.1, 0, 0.0, a, False)  # type: ignore[arg-type]
        found = stage.process(frame=frames[-1], assignments=GroupAssignments((assignment,)), estimate=None).items
        assert len(found) == expected
        assert stage.counts["too_few_points"] == 1 - expected
    # ICP itself refuses fewer than 3 points with a message, never a numpy error deep inside
    with pytest.raises(ValueError, match=r"N>=3"):
        Icp2d(b.points[:2], IcpSettings())
    with pytest.raises(ValueError, match=r"N>=3"):
        Icp2d(b.points, IcpSettings()).align(b.points[:2], np.eye(3))


def test_without_symmetric_loops_symmetric_groups_give_no_loop_factors() -> None:
    frames = _straight_run(20, 0.0)
    marking = Marking(1, "arrow", (2.5, 0.0, 0.0))
    a, b = _view(frames[0], marking), _view(frames[-1], marking)
    stage = IcpLoopClosing(IcpLoopParams(symmetric=SymmetricParams(position_only=False)))
    found = [c for f in frames[:-1] for c in stage.process(frame=f, assignments=None, estimate=None).items]
    symmetric = GroupAssignment(b, 0, False, 0.1, 0, 0.0, a, True)  # type: ignore[arg-type]
    found += stage.process(frame=frames[-1], assignments=GroupAssignments((symmetric,)), estimate=None).items
    assert found == []
    assert stage.counts["symmetric"] == 1


def test_anchored_distance_shrinks_once_the_estimate_has_absorbed_a_loop(world) -> None:  # type: ignore[no-untyped-def]
    stage = IcpLoopClosing(IcpLoopParams())
    run = run_stages(world, loop=stage, backend=GtsamLmBackend(LmParams(save_map=False)))
    estimate = run.estimates[-1]
    first = min(run.loops, key=lambda c: c.frame_to)
    a, b = first.frame_from + 3, first.frame_to + 4  # next to the loop's two frames
    path = stage.frames.distance(b) - stage.frames.distance(a)
    assert stage.anchoring.anchored_distance(a, b, None) == pytest.approx(path)
    assert path > 150.0
    assert stage.anchoring.anchored_distance(a, b, estimate) == pytest.approx(7.0, abs=0.5)
    # an estimate that ignores the loop (odometry) anchors nothing
    from sgf_pipeline.types import PoseEstimate

    odometry = PoseEstimate(world.frames[-1].index, {f.index: f.odometry for f in world.frames})
    assert stage.anchoring.anchored_distance(a, b, odometry) == pytest.approx(path)


def test_the_prediction_covariance_starts_at_the_floors_and_grows_with_distance() -> None:
    p = IcpLoopParams(gate=GateParams(sigma_yaw_deg=0.5, scale_error=0.02))
    zero = drift_covariance(0.0, p.gate, 0.0)
    assert np.allclose(np.sqrt(np.diag(zero)), [0.5, 0.5, math.radians(3.0)])
    sigmas = [np.sqrt(np.diag(drift_covariance(d, p.gate, 0.0))) for d in (10.0, 100.0, 1000.0)]
    assert all(np.all(b > a) for a, b in itertools.pairwise(sigmas))
    # after 1 km without an anchor, the heading is known to about 16 degrees, the position to ~160 m
    assert math.degrees(sigmas[2][2]) == pytest.approx(15.9, abs=0.2)
    assert sigmas[2][0] == pytest.approx(161.0, abs=2.0)
    # a heading bias of 0.07 deg/m adds 70 degrees of heading and 0.5 * bias * d^2 = 611 m after 1 km
    biased = np.sqrt(np.diag(drift_covariance(1000.0, p.gate, math.radians(0.07))))
    assert math.degrees(biased[2]) == pytest.approx(math.hypot(15.9, 70.0), abs=0.3)
    assert biased[0] == pytest.approx(math.hypot(161.0, 0.5 * math.radians(0.07) * 1000.0**2), abs=3.0)


def test_the_gate_sizes_its_drift_by_the_odometrys_errors_as_measured_and_by_its_priors_before() -> None:
    prior = GateParams()
    assert measured_sigmas(prior, None) is prior
    assert measured_sigmas(prior, PoseEstimate(0, {})) is prior  # a back-end that measured nothing
    drift = OdometryDrift(scale_error=0.001, sigma_xy=0.01, sigma_yaw=math.radians(0.04))
    measured = measured_sigmas(prior, PoseEstimate(0, {}, drift=drift))
    assert (measured.scale_error, measured.sigma_xy) == (0.001, 0.01)
    assert measured.sigma_yaw_deg == pytest.approx(0.04, rel=1e-12)
    assert (measured.floor_xy, measured.floor_yaw_deg) == (
        prior.floor_xy,
        prior.floor_yaw_deg,
    )  # the fit's, not the robot's
    # the scale measured, the walks not yet: the priors for the walks
    partly = measured_sigmas(prior, PoseEstimate(0, {}, drift=OdometryDrift(scale_error=0.001)))
    assert (partly.scale_error, partly.sigma_xy, partly.sigma_yaw_deg) == (0.001, prior.sigma_xy, prior.sigma_yaw_deg)
    # 100 m from the last anchor, no bias: the variance is the floor's plus each measured term's
    d = 100.0
    expected = 0.5**2 + (0.001 * d) ** 2 + 0.01**2 * d + math.radians(0.04) ** 2 * d**3 / 3.0
    assert drift_covariance(d, measured, 0.0)[0, 0] == pytest.approx(expected, rel=1e-12)


def test_the_graph_back_end_hands_the_cameras_measurements_to_the_gates() -> None:
    backend = GtsamLmBackend(LmParams(save_map=False))
    backend.begin(RunContext(run_dir=None))
    assert backend._drift() is None  # no camera
    backend.camera = OdometryScale(1.0, math.inf, 3)
    assert backend._drift() is None  # the camera has not measured yet
    backend.camera = OdometryScale(0.99, 0.002, 40, 0.001, 0.0005)
    assert backend._drift() == OdometryDrift(0.002, None, None)  # the scale measured, the walks not
    backend.camera = OdometryScale(0.99, 0.002, 40, 0.001, 0.0005, 0.01, 0.0007)
    assert backend._drift() == OdometryDrift(0.002, 0.01, 0.0007)


def test_the_gate_counts_the_back_ends_bias_uncertainty_over_the_drive_it_corrected() -> None:
    p = IcpLoopParams()
    measured = math.radians(0.07)  # the bias the camera measured on the odometry, which nothing was taken off
    uncorrected = np.sqrt(np.diag(drift_covariance(300.0, p.gate, measured)))
    residual = math.radians(0.01)
    corrected = np.sqrt(np.diag(drift_covariance(300.0, p.gate, residual)))
    # after 300 m the heading bias alone adds 0.5 * 0.07 deg/m * 300^2 m^2 = 55 m; 0.01 deg/m of it only 7.9 m
    no_bias = np.sqrt(np.diag(drift_covariance(300.0, p.gate, 0.0)))
    assert uncorrected[0] == pytest.approx(math.hypot(no_bias[0], 0.5 * measured * 300.0**2), rel=1e-6)
    assert corrected[0] == pytest.approx(math.hypot(no_bias[0], 0.5 * residual * 300.0**2), rel=1e-6)
    assert corrected[2] == pytest.approx(math.hypot(no_bias[2], residual * 300.0), rel=1e-6)
    # the stage takes the estimate's uncertainty only when the corrected drive spans the whole distance,
    # the bias measured on the uncorrected odometry elsewhere, and the bias odometry is expected to have
    # while the back-end publishes no model (or the option is off)
    from sgf_pipeline.types import PoseEstimate, YawBiasCorrection

    frames = _straight_run(40, 0.0)[:-1]  # 1 m per frame
    stage = IcpLoopClosing(p)
    for f in frames:
        stage.process(frame=f, assignments=None, estimate=None)
    poses = {f.index: f.odometry for f in frames}
    since = frames[10].index
    estimate = PoseEstimate(frames[-1].index, poses, YawBiasCorrection(since, residual, measured))
    newest = frames[-1].index
    span = stage.frames.distance(newest) - stage.frames.distance(since)
    assert span == pytest.approx(29.0)
    assert np.allclose(stage.anchoring.drift(span, newest, estimate), drift_covariance(span, p.gate, residual))
    assert np.allclose(
        stage.anchoring.drift(span + 1.0, newest, estimate), drift_covariance(span + 1.0, p.gate, measured)
    )
    unknown = PoseEstimate(newest, poses)
    assert np.allclose(stage.anchoring.drift(span, newest, unknown), drift_covariance(span, p.gate, EXPECTED_YAW_BIAS))
    # a residual larger than the bias measured elsewhere never widens the gate
    loose = PoseEstimate(newest, poses, YawBiasCorrection(since, math.radians(0.5), measured))
    assert np.allclose(stage.anchoring.drift(span, newest, loose), drift_covariance(span, p.gate, measured))
    stage.anchoring.p = GateParams(bias_from_backend=False)
    assert np.allclose(stage.anchoring.drift(span, newest, estimate), drift_covariance(span, p.gate, EXPECTED_YAW_BIAS))
    # so a look-alike 150 m from where the estimate puts the robot, 300 m after the last anchor, passes the
    # gate on the measured bias and fails it on the corrected one
    error = np.array([150.0, 0.0, math.radians(5.0)])
    chi2 = stage.threshold
    assert error @ np.linalg.solve(drift_covariance(300.0, p.gate, measured), error) < chi2
    assert error @ np.linalg.solve(drift_covariance(300.0, p.gate, residual), error) > chi2


def test_an_sgf_of_an_unseen_frame_is_a_clear_error() -> None:
    frames = _straight_run(3, 0.0)
    marking = Marking(1, "arrow", (2.5, 0.0, 0.0))
    ghost = Frame(99, 60.0, np.zeros((2, 2), np.uint8), np.eye(4), CALIBRATION)
    a, b = _view(frames[0], marking), _view(ghost, marking)
    stage = IcpLoopClosing(IcpLoopParams())
    stage.process(frame=frames[0], assignments=None, estimate=None)
    bad = GroupAssignment(b, 0, False, 0.1, 0, 0.0, a, False)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="frame 99 reached the loop stage, which never saw that frame"):
        stage.process(frame=frames[1], assignments=GroupAssignments((bad,)), estimate=None)


def test_two_different_shapes_in_one_group_give_no_factor() -> None:
    frames = _straight_run(20, 0.4)
    a = _view(frames[0], Marking(1, "arrow", (2.5, 0.0, 0.0)))
    b = _view(frames[-1], Marking(2, "tee", (2.5, 0.0, 0.0)))
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), fit=FitParams(extra_yaw_seeds=7)))
    found = [c for f in frames[:-1] for c in stage.process(frame=f, assignments=None, estimate=None).items]
    mixed = GroupAssignment(b, 0, False, 0.6, 0, 0.4, a, False)  # type: ignore[arg-type]
    found += stage.process(frame=frames[-1], assignments=GroupAssignments((mixed,)), estimate=None).items
    assert found == []
    assert stage.counts["icp"] == 1
    # loop_candidates.csv says what the fit with the most inliers missed, against each threshold
    detail = stage.decisions[-1]["detail"]
    m = re.fullmatch(
        r"best fit: inliers ([\d.]+) \(0.85 needed\), rms ([\d.]+) m \(0.03\), sigma ([\d.]+) \(0.05\)", detail
    )
    assert m is not None, detail
    inliers, rms, sigma = map(float, m.groups())
    # an arrow laid on a tee (measured: 71 % of the points within 10 cm at an RMS of 3.3 cm): two shapes, so the
    # best fit misses the inlier or the RMS test, and the detail says by how much
    assert 0.0 < inliers <= 1.0 and rms > 0.0 and sigma >= 0.0
    assert inliers < 0.85 or rms > 0.03


@pytest.mark.parametrize(("extra", "expected"), [(0, 0), (3, 1)])
def test_extra_yaw_seeds_recover_from_a_wrong_column_shift(extra: int, expected: int) -> None:
    frames = _straight_run(20, math.radians(100))
    marking = Marking(1, "arrow", (2.5, 0.0, 0.3))
    first, last = _view(frames[0], marking), _view(frames[-1], marking)
    wrong = math.radians(100 - 90)  # a shift one quarter turn off
    assignment = GroupAssignment(last, 0, False, 0.3, 2, wrong, first, False)  # type: ignore[arg-type]
    stage = IcpLoopClosing(
        IcpLoopParams(
            fit=FitParams(extra_yaw_seeds=extra, seed_both_signs=False),
            separation=SeparationParams(min_distance=5.0),
            consensus=ConsensusParams(min_support=0),
        )
    )
    for f in frames[:-1]:
        stage.process(frame=f, assignments=None, estimate=None)
    loops = stage.process(frame=frames[-1], assignments=GroupAssignments((assignment,)), estimate=None).items
    assert len(loops) == expected


def test_ambiguous_matches_never_give_loop_factors() -> None:
    frames = _straight_run(20, 0.0)
    marking = Marking(1, "arrow", (2.5, 0.0, 0.0))
    a, b = _view(frames[0], marking), _view(frames[-1], marking)
    stage = IcpLoopClosing(IcpLoopParams())
    found = [c for f in frames[:-1] for c in stage.process(frame=f, assignments=None, estimate=None).items]
    ambiguous = GroupAssignment(b, 0, False, 0.1, 0, 0.0, a, False, ambiguous=True)  # type: ignore[arg-type]
    found += stage.process(frame=frames[-1], assignments=GroupAssignments((ambiguous,)), estimate=None).items
    assert found == []
    assert stage.counts["ambiguous"] == 1 and stage.counts["icp"] == 0
    assert stage.decisions[-1]["detail"] == "tie with an aliased group"  # ambiguous, and nothing handed on


def _two_passes(n: int) -> list[Frame]:
    """Frames 1 m apart along x from 0 to n - 1, then the same line driven again (a second pass)."""
    poses = [pose_from_xy_yaw(float(k % n), 0.0, 0.0) for k in range(2 * n)]
    return [Frame(k, 0.5 * k, np.zeros((2, 2), np.uint8), p, CALIBRATION, ground_truth=p) for k, p in enumerate(poses)]


def _tied_arrows(n: int = 40, neighbour: bool = True):  # type: ignore[no-untyped-def]
    """Two passes over identical arrows at x = 10 (B) and x = 30 (A), with an L at x = 22 when ``neighbour``.

    On the second pass the view of A is assigned to B's group (the nearest of two look-alikes that
    eq. 10 cannot tell apart), with A's group as the alternative. Returns the frames and the
    assignments per frame, and the first-pass views of A and B.
    """
    frames = _two_passes(n)
    arrow_a, arrow_b = Marking(1, "arrow", (30.0, 0.5, 0.3)), Marking(2, "arrow", (10.0, 0.5, 0.3))
    ell = Marking(3, "ell", (22.0, -1.0, 0.0))
    views = {8: arrow_b, 28: arrow_a, **({20: ell} if neighbour else {})}
    seen = {k: _view(frames[k], m) for k, m in views.items()}
    by_frame: dict[int, GroupAssignments] = {}
    for k, m in views.items():
        by_frame[k] = GroupAssignments((GroupAssignment(seen[k], m.instance_id, True, 1.0, 0, 0.0, None, False),))  # type: ignore[arg-type]
        if k != 28:  # second-pass views of B and the L open groups of their own here (no loop): neighbours only
            again = _view(frames[n + k], m)
            by_frame[n + k] = GroupAssignments(
                (GroupAssignment(again, 10 + m.instance_id, True, 1.0, 0, 0.0, None, False),)
            )  # type: ignore[arg-type]
    query = _view(frames[n + 28], arrow_a)
    tied = GroupAssignment(
        query,  # type: ignore[arg-type]
        2,
        False,
        0.01,
        0,
        0.0,
        seen[8],  # type: ignore[arg-type]
        False,
        ambiguous=True,
        alternatives=(LookAlike(1, seen[28], 0, 0.0),),  # type: ignore[arg-type]
    )
    by_frame[n + 28] = GroupAssignments((tied,))
    return frames, by_frame, seen


def _run_loop(  # type: ignore[type-arg]
    stage: IcpLoopClosing,
    frames: list[Frame],
    by_frame: dict[int, GroupAssignments],
    estimates: Callable[[Frame], PoseEstimate] | None = None,
) -> list:
    """The loops of a run; matches still waiting for neighbours at its end are refused by ``settle``.

    ``estimates`` gives each frame the back-end's estimate of the frame before (none by default).
    """
    out: list[LoopConstraint] = []
    previous: Frame | None = None
    for f in frames:
        estimate = None if estimates is None or previous is None else estimates(previous)
        out.extend(stage.process(frame=f, assignments=by_frame.get(f.index), estimate=estimate).items)
        previous = f
    context = RunContext(None)
    stage.conclude(context, stage.settle(context, Settlement()))
    stage.finalize(context)
    return out


def test_a_tie_between_look_alikes_is_resolved_by_the_neighbouring_markings() -> None:
    frames, by_frame, seen = _tied_arrows()
    # the gate is off: with the odometry exact, it alone would also refuse B; the consensus is under test here
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False)))
    loops = _run_loop(stage, frames, by_frame)
    # the L seen 8 m before the query lands on its first-pass view only if the query is A: A wins
    assert len(loops) == 1 and stage.ties_resolved == 1
    (c,) = loops
    assert (c.frame_from, c.frame_to, c.group_id) == (28, 68, 1) and c.instance_ids == (1, 1)
    assert np.allclose(xy_yaw(c.relative), (0.0, 0.0, 0.0), atol=0.02)
    # under the wrong hypothesis (B) the L would sit 20 m from anything seen: no support; under A, the L (and B) agree
    a_option = replace(by_frame[68].items[0], group_id=1, matched=seen[28], alternatives=())
    assert stage.consensus.support(a_option, c) == 2
    # tie_support = 0: ties never give loop factors
    strict = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(tie_support=0)))
    assert _run_loop(strict, frames, by_frame) == [] and strict.counts["ambiguous"] == 1


def test_a_tie_without_neighbours_stays_ambiguous() -> None:
    frames, by_frame, _ = _tied_arrows(neighbour=False)
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(window=15.0)))
    # within 15 m before the query nothing else was seen (B is 20 m back): both options have no support
    assert _run_loop(stage, frames, by_frame) == []
    assert stage.counts["ambiguous"] == 1 and stage.ties_resolved == 0
    assert stage.decisions[-1]["detail"] == "support 0, 0 of 1 needed when the run ended"


def test_min_support_refuses_a_lone_match_that_no_neighbour_confirms() -> None:
    frames, by_frame, seen = _tied_arrows()
    wrong = replace(by_frame[68].items[0], ambiguous=False, alternatives=())  # A's view matched to B, unambiguous
    by_frame[68] = GroupAssignments((wrong,))
    plain = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(min_support=0)))
    (false_loop,) = _run_loop(plain, frames, by_frame)
    assert false_loop.instance_ids == (2, 1)  # without the consensus: a false loop
    confirmed = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(min_support=1)))
    assert _run_loop(confirmed, frames, by_frame) == [] and confirmed.counts["consensus"] == 1
    right = replace(wrong, group_id=1, matched=seen[28])
    by_frame[68] = GroupAssignments((right,))
    (loop,) = _run_loop(
        IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(min_support=1))),
        frames,
        by_frame,
    )
    assert loop.instance_ids == (1, 1)


#: the heading bias (deg/m) the back-end's model measured on the toy robots' odometry (:func:`_measured`)
MEASURED_BIAS = 0.07
#: the gate's position sigma at the revisit of :func:`_revisit_with_neighbours`: 78 m of travel since frame 28
#: (11 m to the end of the first pass, 39 m back to its start, 28 m to the arrow), by the drift model with the
#: measured heading bias (4.14 m)
#: The odometry's noise as these scenarios' camera measured it (scale error, m/sqrt(m), rad/sqrt(m)).
MEASURED_DRIFT = OdometryDrift(0.02, 0.05, math.radians(0.1))
REVISIT_GATE_SIGMA = math.sqrt(
    drift_covariance(
        78.0,
        measured_sigmas(IcpLoopParams().gate, PoseEstimate(0, {}, drift=MEASURED_DRIFT)),
        math.radians(MEASURED_BIAS),
    )[0, 0]
)


def _measured(frames: list[Frame]) -> Callable[[Frame], PoseEstimate]:
    """Estimates at the (exact) odometry whose back-end model measured ``MEASURED_BIAS`` and took none of it off."""
    return _bias_model(frames, MEASURED_BIAS)


def _revisit_with_neighbours(first: list[Marking], second: list[Marking], turn: float = 0.0):  # type: ignore[no-untyped-def]
    """Two passes along x; the second pass's view of an arrow (x = 30) is matched to its first-pass view.

    ``first`` and ``second`` are the neighbouring markings seen on each pass (frames 2 m behind them);
    on the second pass they open groups of their own: evidence only. ``turn`` (rad) turns the arrow's
    second view, so that its descriptor differs from the first's by a sector's fraction.
    """
    n = 40
    frames = _two_passes(n)
    arrow = Marking(1, "arrow", (30.0, 0.5, 0.3))
    by_frame: dict[int, GroupAssignments] = {}
    seen = _view(frames[28], arrow)
    by_frame[28] = GroupAssignments((GroupAssignment(seen, 1, True, 1.0, 0, 0.0, None, False),))  # type: ignore[arg-type]
    for offset, markings in ((0, first), (n, second)):
        for m in markings:
            k = offset + int(m.pose[0]) - 2
            view = _view(frames[k], m)
            by_frame[k] = GroupAssignments(
                (GroupAssignment(view, offset + m.instance_id, True, 1.0, 0, 0.0, None, False),)
            )  # type: ignore[arg-type]
    query = _view(frames[n + 28], replace(arrow, pose=(30.0, 0.5, 0.3 + turn)))
    by_frame[n + 28] = GroupAssignments((GroupAssignment(query, 1, False, 0.01, 0, 0.0, seen, False),))  # type: ignore[arg-type]
    return frames, by_frame


def test_a_distinct_marking_vouches_for_itself_unless_another_group_looks_like_it() -> None:
    # one revisit and nothing seen on both passes (campus_delivery's single reverse pair): no neighbour can agree
    ell = Marking(3, "ell", (22.0, -1.0, 0.0))
    frames, by_frame = _revisit_with_neighbours([ell], [])
    lone = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False)))
    (loop,) = _run_loop(lone, frames, by_frame)  # the arrow looks like its match and like nothing else seen
    assert loop.instance_ids == (1, 1) and lone.distinct == 1 and lone.counts["consensus"] == 0
    strict = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(enabled=False), distinct=DistinctParams(support=None))
    )  # min_support for every match
    assert _run_loop(strict, frames, by_frame) == [] and strict.counts["consensus"] == 1 and strict.distinct == 0
    # an arrow in another group (a copy elsewhere): the marking is common, and the consensus decides again
    other = Marking(4, "arrow", (12.0, 1.5, 0.0))
    frames, by_frame = _revisit_with_neighbours([other], [])
    common = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False)))
    assert _run_loop(common, frames, by_frame) == [] and common.counts["consensus"] == 1 and common.distinct == 0


@pytest.mark.parametrize(
    ("head", "turn", "ratio", "distinct"),
    [
        (0.45, 0.0, 3.0, True),  # the other design 0.058 from the query, the match 0: far more like its match
        (0.45, 0.0, None, False),  # the ratio test off: 0.058 is within distinct_distance, so the marking is common
        (0.45, 0.02, 3.0, False),  # the query's match 0.030 off: the other design is not 3 times farther
        (0.35, 0.0, 3.0, False),  # the arrow's own shape, 0.032 off: within distinct_floor, common whatever the ratio
    ],
)
def test_a_marking_far_more_like_its_match_than_like_any_other_group_is_distinct(
    monkeypatch: pytest.MonkeyPatch, head: float, turn: float, ratio: float | None, distinct: bool
) -> None:
    monkeypatch.setitem(SHAPES, "other_arrow", functools.partial(arrow_points, head=head))  # in another group
    frames, by_frame = _revisit_with_neighbours([Marking(4, "other_arrow", (22.0, -1.0, 0.0))], [], turn=turn)
    query, other = by_frame[68].items[0], by_frame[20].items[0]
    match = shifted_distances(np.asarray(query.descriptor.matrix), np.asarray(query.matched.matrix)).min()
    nearest = shifted_distances(np.asarray(query.descriptor.matrix), np.asarray(other.descriptor.matrix)).min()
    expected = {(0.45, 0.0): (0.0, 0.058), (0.45, 0.02): (0.030, 0.069), (0.35, 0.0): (0.0, 0.032)}[(head, turn)]
    assert (match, nearest) == pytest.approx(expected, abs=0.0015)
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), distinct=DistinctParams(ratio=ratio)))
    loops = _run_loop(stage, frames, by_frame)
    assert stage.distinct == int(distinct) and stage.counts["consensus"] == int(not distinct)
    assert [c.instance_ids for c in loops] == ([(1, 1)] if distinct else [])


def test_a_neighbour_agrees_only_at_the_heading_the_match_predicts() -> None:
    ell = Marking(3, "ell", (22.0, -1.0, 0.0))
    turned = Marking(3, "ell", (22.0, -1.0, math.pi / 2))  # the same shape, lying a quarter turn round
    headed = IcpLoopParams(
        gate=GateParams(enabled=False),
        distinct=DistinctParams(support=None),
        consensus=ConsensusParams(heading_deg=15.0),
    )
    frames, by_frame = _revisit_with_neighbours([ell], [ell])
    (loop,) = _run_loop(IcpLoopClosing(headed), frames, by_frame)
    assert loop.instance_ids == (1, 1)
    # a look-alike where the match puts it but turned: eq. 10 alone (any heading, the default) takes it as the
    # same marking
    frames, by_frame = _revisit_with_neighbours([ell], [turned])
    stage = IcpLoopClosing(headed)
    assert _run_loop(stage, frames, by_frame) == [] and stage.counts["consensus"] == 1
    (loop,) = _run_loop(
        IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), distinct=DistinctParams(support=None))),
        frames,
        by_frame,
    )
    assert loop.instance_ids == (1, 1)


def test_a_neighbour_that_fixes_no_heading_counts_half() -> None:
    discs = [
        Marking(3, "disc", (22.0, -1.0, 0.0), symmetric=True),
        Marking(4, "disc", (16.0, 1.0, 0.0), symmetric=True),
    ]
    headed = IcpLoopParams(
        gate=GateParams(enabled=False),
        distinct=DistinctParams(support=None),
        consensus=ConsensusParams(heading_deg=15.0),
    )
    frames, by_frame = _revisit_with_neighbours(discs[:1], discs[:1])
    stage = IcpLoopClosing(headed)
    assert _run_loop(stage, frames, by_frame) == [] and stage.counts["consensus"] == 1
    for params in (
        headed.model_copy(update={"consensus": ConsensusParams(heading_deg=15.0, unoriented_weight=1.0)}),
        IcpLoopParams(gate=GateParams(enabled=False), distinct=DistinctParams(support=None)),
    ):
        (loop,) = _run_loop(IcpLoopClosing(params), frames, by_frame)
        assert loop.instance_ids == (1, 1)
    frames, by_frame = _revisit_with_neighbours(discs, discs)  # two manholes: one marking's worth
    stage = IcpLoopClosing(headed)
    (loop,) = _run_loop(stage, frames, by_frame)
    assert stage.consensus.support(by_frame[68].items[0], loop) == pytest.approx(1.0)
    stage = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(enabled=False), distinct=DistinctParams(support=None))
    )  # at any heading each manhole is a whole marking
    (loop,) = _run_loop(stage, frames, by_frame)
    assert stage.consensus.support(by_frame[68].items[0], loop) == pytest.approx(2.0)


def _bias_model(frames: list[Frame], uncorrected_deg_per_m: float) -> Callable[[Frame], PoseEstimate]:
    """Estimates at the odometry whose back-end model measured a heading bias and took none of it off.

    The camera measured the odometry's noise at ``MEASURED_DRIFT``.
    """
    from sgf_pipeline.types import PoseEstimate, YawBiasCorrection

    model = YawBiasCorrection(None, math.inf, math.radians(uncorrected_deg_per_m))
    poses = {f.index: f.odometry for f in frames}
    return lambda f: PoseEstimate(f.index, {k: v for k, v in poses.items() if k <= f.index}, model, MEASURED_DRIFT)


def _repeated_arrows(matched_x: float):  # type: ignore[no-untyped-def]
    """Two passes along x over an L (x = 8), a T (x = 12) and a pattern of arrows every 4 m (x = 16 ... 28).

    On the second pass the view of the arrow at x = 28 joins the aliased pattern's group, matched to
    the first-pass view of the arrow at ``matched_x``. Frames sit 2 m behind what they see.
    """
    n = 40
    frames = _two_passes(n)
    markings = [Marking(1, "ell", (8.0, -0.5, 0.0)), Marking(2, "tee", (12.0, 0.5, 0.0))]
    markings += [Marking(10 + k, "arrow", (16.0 + 4.0 * k, 0.3, 0.2)) for k in range(4)]
    by_frame: dict[int, GroupAssignments] = {}
    first: dict[float, object] = {}
    for m in markings:
        k = int(m.pose[0]) - 2
        first[m.pose[0]] = view = _view(frames[k], m)
        by_frame[k] = GroupAssignments((GroupAssignment(view, m.instance_id, True, 1.0, 0, 0.0, None, False),))  # type: ignore[arg-type]
        if m.pose[0] < 28.0:  # second-pass neighbours open groups of their own here: evidence only
            again = _view(frames[n + k], m)
            by_frame[n + k] = GroupAssignments(
                (GroupAssignment(again, 100 + m.instance_id, True, 1.0, 0, 0.0, None, False),)
            )  # type: ignore[arg-type]
    query = _view(frames[n + 26], markings[-1])
    match = GroupAssignment(query, 13, False, 0.01, 0, 0.0, first[matched_x], False, ambiguous=True, aliased=True)  # type: ignore[arg-type]
    by_frame[n + 26] = GroupAssignments((match,))
    return frames, by_frame


def test_a_match_into_a_repeated_pattern_needs_neighbours_unlike_it() -> None:
    # the right copy: the L and the T (unlike an arrow) land on their first-pass views
    frames, by_frame = _repeated_arrows(28.0)
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(aliased_support=2)))
    (loop,) = _run_loop(stage, frames, by_frame)
    assert stage.aliases_resolved == 1 and (loop.frame_from, loop.frame_to) == (26, 66)
    assert np.allclose(xy_yaw(loop.relative), (0.0, 0.0, 0.0), atol=0.02)
    # the copy one period back: ICP puts the robot 4 m off, where the other arrows agree with it (the pattern
    # repeats) but the L and the T do not; counted without them, the false loop would pass
    frames, by_frame = _repeated_arrows(24.0)
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(aliased_support=2)))
    assert _run_loop(stage, frames, by_frame) == [] and stage.counts["ambiguous"] == 1
    wrong = replace(by_frame[66].items[0], aliased=False, ambiguous=False)
    c = stage.gate.evaluate(wrong, None)
    # frame 66 stands where frame 22 stood, says ICP: truly it stands 4 m further on, where frame 26 stood
    assert not isinstance(c, str) and np.allclose(xy_yaw(c.constraint.relative), (0.0, 0.0, 0.0), atol=0.05)
    assert stage.consensus.support(wrong, c.constraint, unlike=True) == 0
    # the arrows one period on agree (two of them)
    assert stage.consensus.support(wrong, c.constraint) == pytest.approx(2.0)
    # aliased_support = 0: a repeated pattern never gives loop factors
    frames, by_frame = _repeated_arrows(28.0)
    strict = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(aliased_support=0)))
    assert _run_loop(strict, frames, by_frame) == [] and strict.counts["ambiguous"] == 1
    assert strict.decisions[-1]["detail"] == "aliased"


def test_unlike_neighbours_are_held_to_half_the_patterns_period() -> None:
    # with a 5 m consensus radius the L and the T would agree with the copy one period (4 m) back as well;
    # held to half the period (2 m), they vouch for the right copy only
    frames, by_frame = _repeated_arrows(24.0)
    stage = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(aliased_support=2, radius=5.0))
    )
    assert _run_loop(stage, frames, by_frame) == [] and stage.counts["ambiguous"] == 1
    assert stage.decisions[-1]["detail"] == "support 0 of 2 needed when the run ended"
    wrong = by_frame[66].items[0]
    # the arrows' period, seen on either pass
    assert stage.consensus.copy_spacing(wrong) == pytest.approx(4.0, abs=0.05)
    c = stage.gate.evaluate(wrong, None)
    assert not isinstance(c, str)
    uncapped = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(aliased_support=2, radius=5.0))
    )
    _run_loop(uncapped, frames, by_frame)
    uncapped.consensus.copy_spacing = lambda a: math.inf  # type: ignore[method-assign]
    # the L and the T, 4 m off
    assert uncapped.consensus.support(wrong, c.constraint, unlike=True) == pytest.approx(2.0)
    frames, by_frame = _repeated_arrows(28.0)
    right = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(aliased_support=2, radius=5.0))
    )
    (loop,) = _run_loop(right, frames, by_frame)
    assert right.aliases_resolved == 1 and (loop.frame_from, loop.frame_to) == (26, 66)


def test_a_match_waits_for_the_neighbours_seen_after_it() -> None:
    # an arrow at x = 10 opens the second pass; its only neighbour, an L at x = 24, comes 14 m after it
    n = 40
    frames = _two_passes(n)
    arrow, ell = Marking(1, "arrow", (10.0, 0.5, 0.3)), Marking(2, "ell", (24.0, -1.0, 0.0))
    first = {m.instance_id: _view(frames[int(m.pose[0]) - 2], m) for m in (arrow, ell)}
    by_frame = {
        int(m.pose[0]) - 2: GroupAssignments(
            (GroupAssignment(first[m.instance_id], m.instance_id, True, 1.0, 0, 0.0, None, False),)
        )  # type: ignore[arg-type]
        for m in (arrow, ell)
    }
    match = GroupAssignment(_view(frames[n + 8], arrow), 1, False, 0.01, 0, 0.0, first[1], False)  # type: ignore[arg-type]
    by_frame[n + 8] = GroupAssignments((match,))
    again = _view(frames[n + 22], ell)
    by_frame[n + 22] = GroupAssignments((GroupAssignment(again, 12, True, 1.0, 0, 0.0, None, False),))  # type: ignore[arg-type]
    at_once = IcpLoopClosing(
        IcpLoopParams(
            gate=GateParams(enabled=False), distinct=DistinctParams(support=None), consensus=ConsensusParams(wait=False)
        )
    )  # decide on the SGFs seen before
    assert _run_loop(at_once, frames, by_frame) == [] and at_once.counts["consensus"] == 1
    waits = IcpLoopClosing(
        IcpLoopParams(
            gate=GateParams(enabled=False), distinct=DistinctParams(support=None), consensus=ConsensusParams(wait=True)
        )
    )
    emitted = {f.index: waits.process(frame=f, assignments=by_frame.get(f.index), estimate=None).items for f in frames}
    (loop,) = [c for items in emitted.values() for c in items]
    assert (loop.frame_from, loop.frame_to) == (8, n + 8) and loop.instance_ids == (1, 1)
    assert emitted[n + 22] == (loop,)  # emitted when the L lands on its first-pass view, 14 m later
    # nothing agrees within consensus_window (10 m): the match expires, refused, once the robot has driven past
    short = IcpLoopClosing(
        IcpLoopParams(
            gate=GateParams(enabled=False),
            distinct=DistinctParams(support=None),
            consensus=ConsensusParams(window=10.0, wait=True),
        )
    )
    assert _run_loop(short, frames, by_frame) == [] and short.counts["consensus"] == 1 and short.waiting == []


def _bar_match(frames: list[Frame], shift: int, yaw: float) -> GroupAssignment:
    """A bar (twofold symmetric, 1.2 x 0.18 m at (12, 0.3), turned 0.4 rad) seen at frames 9 and 49, matched."""
    bar = Marking(7, "disc", (12.0, 0.3, 0.4))
    points = np.array([(x, y) for x in np.linspace(-0.6, 0.6, 41) for y in np.linspace(-0.09, 0.09, 7)])
    rng = np.random.default_rng(5)

    def view(frame: Frame) -> object:
        c, s = math.cos(0.4), math.sin(0.4)
        world = points @ np.array([[c, -s], [s, c]]).T + (12.0, 0.3) + rng.normal(0.0, 0.004, points.shape)
        inv = invert(frame.odometry)
        return descriptor(frame, bar, world @ inv[:2, :2].T + inv[:2, 3])

    return GroupAssignment(view(frames[49]), 7, False, 0.01, shift, yaw, view(frames[9]), False)  # type: ignore[arg-type]


def test_twofold_symmetric_fits_need_a_prediction_that_picks_one() -> None:
    # a bar (twofold symmetric) fits itself turned by 180 degrees as well: two distinct near-equal fits
    frames = _two_passes(40)
    match = _bar_match(frames, 0, 0.0)
    # a second yaw seed half a turn on (the association's shift of a bar could be either)
    loose = IcpLoopClosing(
        IcpLoopParams(fit=FitParams(extra_yaw_seeds=1), gate=GateParams(floor_yaw_deg=120.0))
    )  # heading too uncertain
    tight = IcpLoopClosing(IcpLoopParams(fit=FitParams(extra_yaw_seeds=1)))  # the default floors: 3 degrees
    for f in frames[:50]:
        loose.process(frame=f, assignments=None, estimate=None)
        tight.process(frame=f, assignments=None, estimate=None)
    fits = loose.fitting.fits(loose.fitting.align(match), np.asarray(match.descriptor.points))
    assert len(fits) == 2 and abs(abs(wrap_angle(fits[0].pose[2] - fits[1].pose[2])) - math.pi) < 0.02
    assert loose.gate.evaluate(match, None) == "not_unique"
    c = tight.gate.evaluate(match, None)
    assert not isinstance(c, str) and np.allclose(xy_yaw(c.constraint.relative), (0.0, 0.0, 0.0), atol=0.02)
    # an arrow has one fit
    arrow = Marking(1, "arrow", (12.0, 0.3, 0.2))
    single = GroupAssignment(_view(frames[49], arrow), 1, False, 0.01, 0, 0.0, _view(frames[9], arrow), False)  # type: ignore[arg-type]
    assert len(tight.fitting.fits(tight.fitting.align(single), np.asarray(single.descriptor.points))) == 1


@pytest.mark.parametrize("extra", [None, 0])
def test_a_twofold_marking_whose_shift_came_out_half_a_turn_off_is_still_closed(extra: int | None) -> None:
    # a zebra's stripes look the same turned by 180 degrees, so eq. 10's best shift may be half a turn
    # off; both column-shift seeds then lead ICP to the flipped fit, which the gate refuses
    frames = _two_passes(40)
    match = _bar_match(frames, 45, math.pi)
    stage = IcpLoopClosing(IcpLoopParams() if extra is None else IcpLoopParams(fit=FitParams(extra_yaw_seeds=extra)))
    for f in frames[:50]:
        stage.process(frame=f, assignments=None, estimate=None)
    c = stage.gate.evaluate(match, None)
    if extra == 0:
        assert c == "gate"
    else:  # the default seeds also try the shift's half-turn alternative
        assert not isinstance(c, str) and np.allclose(xy_yaw(c.constraint.relative), (0.0, 0.0, 0.0), atol=0.02)


def test_fits_are_told_apart_on_the_marking_not_at_the_robot() -> None:
    # a marking 3 m ahead of the robot: ICP's yaw wanders by 5 degrees about it (campus_delivery's reverse
    # pair did), which moves the robot's pose by 0.27 m but the marking's points by 4 cm: one fit
    rng = np.random.default_rng(2)
    points = rng.uniform(-0.4, 0.4, (200, 2)) + np.array([3.0, 0.0])

    def about_marking(yaw: float, shift: float = 0.0) -> np.ndarray:
        turn = se2(0.0, 0.0, yaw)
        t = se2(3.0 + shift, 0.0, 0.0) @ turn @ se2(-3.0, 0.0, 0.0)
        return t

    def result(transform: np.ndarray, fitness: float) -> IcpResult:
        return IcpResult(transform, True, 10, fitness, 1.0, np.eye(3) * 1e-4, len(points))

    loop = IcpLoopClosing(IcpLoopParams())
    best, wobble = result(about_marking(0.0), 0.0096), result(about_marking(math.radians(5.2)), 0.0100)
    assert math.hypot(*(wobble.transform[:2, 2] - best.transform[:2, 2])) > 0.25  # apart at the robot
    (one,) = loop.fitting.fits([wobble, best], points)
    # ...whose pose is their mean (ICP stops on either side of a shallow valley) and whose covariance
    # widens by their spread (2.6 degrees each side), far beyond ICP's own
    assert np.allclose(one.transform, about_marking(math.radians(2.6)), atol=0.005)
    assert one.fitness == best.fitness and one.covariance[2, 2] == pytest.approx(1e-4 + math.radians(2.6) ** 2)
    # a period on (0.5 m) and half a turn about the marking: distinct fits of a row, of a twofold shape
    period, turned = result(about_marking(0.0, 0.5), 0.0098), result(about_marking(math.pi), 0.0099)
    fits = loop.fitting.fits([turned, best, period, wobble], points)
    assert [f.fitness for f in fits] == [best.fitness, period.fitness, turned.fitness]
    assert fits[1] is period and fits[2] is turned
    # a fit much worse than the best is no alternative
    assert loop.fitting.fits([best, result(about_marking(math.pi), 0.02)], points) == [best]


def test_fits_of_one_alignment_become_their_mean() -> None:
    # a ring-framed marker: ICP from two seeds stopped 35 degrees apart about it, both near-equal, both within
    # 0.25 m (RMS) on the marking's points: one fit, the middle of their yaws, its covariance widened by the spread
    angles = np.linspace(0.0, 2 * math.pi, 120, endpoint=False)
    ring = np.stack([0.4 * np.cos(angles), 0.4 * np.sin(angles)], axis=1)

    def result(yaw: float, fitness: float) -> IcpResult:
        return IcpResult(se2(0.0, 0.0, yaw), True, 10, fitness, 1.0, np.eye(3) * 1e-4, len(ring))

    loop = IcpLoopClosing(IcpLoopParams())
    (fit,) = loop.fitting.fits([result(math.radians(-17.5), 0.018), result(math.radians(17.5), 0.020)], ring)
    assert np.allclose(fit.transform, np.eye(3), atol=1e-9)
    assert fit.covariance[2, 2] == pytest.approx(1e-4 + math.radians(17.5) ** 2, rel=1e-9)
    # 5 degrees apart (an elongated marking's shallow valley): the middle, 2.5 degrees
    (one,) = loop.fitting.fits([result(0.0, 0.018), result(math.radians(5.0), 0.019)], ring)
    assert math.degrees(math.atan2(one.transform[1, 0], one.transform[0, 0])) == pytest.approx(2.5)


@pytest.mark.parametrize(
    ("copy_x", "sigma_limit", "closed"),
    [(5.0, 5.0, True), (26.0, 5.0, False), (5.0, None, False), (5.0, 4.0, False)],
)
def test_a_match_the_gate_predicts_tightly_needs_no_neighbours(
    copy_x: float, sigma_limit: float | None, closed: bool
) -> None:
    # the arrow is revisited after 78 m of exact odometry: the gate's sigma is 4.14 m, and nothing seen on both
    # passes can agree. A copy of the arrow in another group makes it common (not distinct): 25 m from the
    # matched arrow the gate would have refused it, 4 m from it (within 4.03 sigma + 2 m = 18.7 m) it could pass.
    copy = Marking(4, "arrow", (copy_x, 1.5, 0.0))
    frames, by_frame = _revisit_with_neighbours([copy], [])
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(support_sigma=sigma_limit)))
    loops = _run_loop(stage, frames, by_frame, _measured(frames))
    assert [c.instance_ids for c in loops] == ([(1, 1)] if closed else [])
    assert stage.distinct == 0 and stage.gate_decided == int(closed)
    assert stage.counts["consensus"] == (0 if closed else 1)
    (row,) = [d for d in stage.decisions if d["frame_to"] == 68]
    assert row["gate_sigma_xy"] == pytest.approx(REVISIT_GATE_SIGMA, abs=1e-3) and row["gate_chi2"] < 0.01
    if closed:
        assert np.allclose(xy_yaw(loops[0].relative), (0.0, 0.0, 0.0), atol=0.02)
    # with the gate off, the gate decides nothing
    if closed:
        off = IcpLoopClosing(IcpLoopParams(gate=GateParams(enabled=False, support_sigma=sigma_limit)))
        assert _run_loop(off, frames, by_frame, _measured(frames)) == [] and off.gate_decided == 0


def test_a_look_alike_within_the_gates_reach_stands_against_it(monkeypatch: pytest.MonkeyPatch) -> None:
    # 4 m from the matched arrow, well within the gate's reach (18.7 m), lies an arrow with a head 0.9 m wide:
    # eq. 10 calls it alike (0.122, within consensus_distance), so the gate does not decide the match alone
    monkeypatch.setitem(SHAPES, "wide_arrow", functools.partial(arrow_points, head=0.9))
    frames, by_frame = _revisit_with_neighbours([Marking(4, "wide_arrow", (26.0, 1.5, 0.0))], [])
    query, other = by_frame[68].items[0], by_frame[24].items[0]
    alike = shifted_distances(np.asarray(query.descriptor.matrix), np.asarray(other.descriptor.matrix)).min()
    assert alike == pytest.approx(0.122, abs=0.002)
    stage = IcpLoopClosing(IcpLoopParams(gate=GateParams(support_sigma=5.0)))
    assert _run_loop(stage, frames, by_frame, _measured(frames)) == []
    assert stage.gate_decided == 0 and stage.counts["consensus"] == 1
    (row,) = [d for d in stage.decisions if d["frame_to"] == 68]
    assert row["detail"] == "support 0 of 1 needed when the run ended"
    # without it the gate decides, and the loop closes
    alone = IcpLoopClosing(IcpLoopParams(gate=GateParams(support_sigma=5.0)))
    frames, by_frame = _revisit_with_neighbours([], [])
    assert [c.instance_ids for c in _run_loop(alone, frames, by_frame, _measured(frames))] == [(1, 1)]
    assert alone.gate_decided == 1


def test_a_tie_the_gate_leaves_one_option_of_is_resolved_without_neighbours() -> None:
    # B is 20 m from A. With the gate at 90 % (chi-square 6.25) only A passes (B: 10.1 at 6.3 m sigma), and B
    # lies beyond the gate's reach from A (2.5 x 4.14 m + 2 m = 12.4 m): the gate alone tells them apart
    frames, by_frame, _ = _tied_arrows(neighbour=False)
    stage = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(probability=0.9, support_sigma=5.0), consensus=ConsensusParams(window=15.0))
    )
    (loop,) = _run_loop(stage, frames, by_frame, _measured(frames))
    assert loop.instance_ids == (1, 1) and loop.group_id == 1
    assert stage.gate_decided == 1 and stage.ties_resolved == 1 and stage.counts["ambiguous"] == 0
    strict = IcpLoopClosing(
        IcpLoopParams(gate=GateParams(probability=0.9, support_sigma=None), consensus=ConsensusParams(window=15.0))
    )
    assert _run_loop(strict, frames, by_frame, _measured(frames)) == [] and strict.counts["ambiguous"] == 1
    # at 99 % B passes the gate too: two options, and no neighbour to choose between them
    loose = IcpLoopClosing(IcpLoopParams(gate=GateParams(support_sigma=5.0), consensus=ConsensusParams(window=15.0)))
    assert (
        _run_loop(loose, frames, by_frame, _measured(frames)) == []
        and loose.counts["ambiguous"] == 1
        and loose.gate_decided == 0
    )


def test_a_match_into_a_view_of_the_same_pass_is_redone_with_the_groups_earlier_pass() -> None:
    frames = _two_passes(40)
    arrow = Marking(1, "arrow", (30.0, 0.5, 0.3))
    first, again, query = (_view(frames[k], arrow) for k in (28, 66, 68))
    by_frame = {
        28: GroupAssignments((GroupAssignment(first, 1, True, 1.0, 0, 0.0, None, False),)),  # type: ignore[arg-type]
        66: GroupAssignments((GroupAssignment(again, 1, False, 0.01, 0, 0.0, None, False),)),  # type: ignore[arg-type]
        # the association matched the query to the group's closest member: the view 2 m back on this pass
        68: GroupAssignments((GroupAssignment(query, 1, False, 0.01, 0, 0.0, again, False),)),  # type: ignore[arg-type]
    }
    stage = IcpLoopClosing(IcpLoopParams(consensus=ConsensusParams(min_support=0)))
    (loop,) = _run_loop(stage, frames, by_frame)
    assert (loop.frame_from, loop.frame_to, loop.instance_ids) == (28, 68, (1, 1))
    assert np.allclose(xy_yaw(loop.relative), xy_yaw(invert(frames[28].odometry) @ frames[68].odometry), atol=0.02)
    assert stage.earlier_members == 1 and stage.counts["separation"] == 0
    # without an earlier pass in the group, the same-pass match is refused
    del by_frame[28]
    alone = IcpLoopClosing(IcpLoopParams(consensus=ConsensusParams(min_support=0)))
    assert _run_loop(alone, frames, by_frame) == [] and alone.counts["separation"] == 1 and alone.earlier_members == 0


def _final_groups(seen: dict[int, object], query: object, merged: bool) -> list[SgfGroup]:
    """The groups the association ends with: A's revisit back in A's group (merged) or still in B's."""
    a, b = SgfGroup(1), SgfGroup(2)
    a.add(seen[28], 0)  # type: ignore[arg-type]
    b.add(seen[8], 0)  # type: ignore[arg-type]
    (a if merged else b).add(query, 0)  # type: ignore[arg-type]
    return [a, b]


@pytest.mark.parametrize(("merged", "final_pass", "closed"), [(True, True, 1), (False, True, 0), (True, False, 0)])
def test_a_revisit_the_association_regrouped_at_the_end_is_closed_by_the_final_pass(
    merged: bool, final_pass: bool, closed: int
) -> None:
    # Online, the revisit of arrow A ties with its look-alike B 20 m away (no estimate yet: the odometry's
    # gate passes both) and no neighbour tells them apart: refused. The final estimate (exact here, 78 m
    # of path from the first pass: sigma 4.14 m) puts B beyond the gate's reach of A (4.03 x 4.14 + 2 m =
    # 18.7 m), so once the association's merge has put the revisit in A's group, the final pass closes it;
    # left in B's group, ICP against B fails the gate.
    frames, by_frame, seen = _tied_arrows(neighbour=False)
    stage = IcpLoopClosing(
        IcpLoopParams(
            consensus=ConsensusParams(window=15.0),
            gate=GateParams(support_sigma=5.0),
            final_pass=FinalPassParams(enabled=final_pass),
        )
    )
    exact = _measured(frames)(frames[-1])
    online = [
        c
        for f in frames
        for c in stage.process(
            frame=f, assignments=by_frame.get(f.index), estimate=exact if f is frames[-1] else None
        ).items
    ]
    assert online == []
    query = by_frame[68].items[0].descriptor
    context = RunContext(None)
    tracks = {k: v.sgf.track_id for k, v in seen.items()} | {68: query.sgf.track_id}
    group_of = {(8, tracks[8]): 2, (28, tracks[28]): 1, (68, tracks[68]): 1 if merged else 2}
    groups = tuple(_final_groups(seen, query, merged))
    settlement = stage.conclude(context, stage.settle(context, Settlement(groups=groups, group_of=group_of)))  # type: ignore[arg-type]
    stage.finalize(context)
    assert stage.counts["ambiguous"] == 1  # the online match, refused when the run ended
    final = settlement.final_loops.items
    assert len(final) == closed and context.metrics["loops"]["final_pass"]["accepted"] == closed
    assert context.metrics["loops"]["accepted"] == closed
    if closed:
        (loop,) = final
        assert (loop.frame_from, loop.frame_to, loop.instance_ids, loop.group_id) == (28, 68, (1, 1), 1)
        assert np.allclose(xy_yaw(loop.relative), (0.0, 0.0, 0.0), atol=0.02)
        (row,) = [d for d in stage.decisions if d["outcome"] == "accepted"]
        assert row["detail"] == "final pass" and row["gate_sigma_xy"] == pytest.approx(REVISIT_GATE_SIGMA, abs=1e-3)
    # Not tried twice: a pair of drive-bys that a loop joins is left alone.
    assert context.metrics["loops"]["final_pass"]["tried"] == (1 if final_pass else 0)


def test_symmetric_loops_fix_where_a_round_marking_lies_and_leave_the_turn_to_the_estimate(world) -> None:  # type: ignore[no-untyped-def]
    stage = IcpLoopClosing(
        IcpLoopParams(consensus=ConsensusParams(min_support=0), symmetric=SymmetricParams(position_only=True))
    )
    run = run_stages(world, loop=stage, association=OracleAssociation(world, by="instance"))
    loops = run.context.metrics["loops"]
    # the manhole's two revisits are refused as symmetric by default; here the second is closed, position
    # only, once the loops before it anchored the estimate; the first came while the gate's sigma was wider
    assert (loops["closed"], loops["false_closed"], loops["position_only"]) == (9, 0, 1)
    assert loops["rejected"]["symmetric"] == 0 and loops["rejected"]["consensus"] == 1
    refused = [d for d in run.context.artifacts["loop_candidates"] if d["outcome"] == "consensus"]
    wide = re.match(
        r"position only: the gate's sigma \(([0-9.]+) m\) above gate_support_sigma \(5.0\)", refused[0]["detail"]
    )
    assert wide is not None and float(wide.group(1)) > 5.0
    round_loops = [c for c in run.loops if c.position_only]
    assert len(round_loops) == 1
    assert all(world.truth.markings[c.instance_ids[1]].symmetric for c in round_loops)
    for c in round_loops:
        assert c.marking is not None
        centre = np.array([*c.marking, 0.0, 1.0])
        truth = invert(world.gt[c.frame_from]) @ world.gt[c.frame_to]
        # the manhole where both views put it, within 5 cm of the truth
        assert np.linalg.norm((truth @ centre - c.relative @ centre)[:2]) < 0.05
        # the turn is the odometry's (no estimate here), not ICP's guess at a disc's heading
        odometry = invert(world.frames[c.frame_from].odometry) @ world.frames[c.frame_to].odometry
        assert wrap_angle(xy_yaw(c.relative)[2] - xy_yaw(odometry)[2]) == pytest.approx(0.0, abs=1e-9)
    entries = [e for e in run.context.artifacts["loops"] if e["position_only"]]
    assert len(entries) == 1 and all(e["true"] is True and e["truth_error_deg"] == 0.0 for e in entries)
    details = [d["detail"] for d in run.context.artifacts["loop_candidates"] if d["outcome"] == "accepted"]
    assert details.count("position only: the gate decides") == 1


def test_a_position_only_loop_whitens_its_turn_by_the_free_sigma_and_its_place_by_the_marking_sigma() -> None:
    relative = pose_from_xy_yaw(-0.4, 0.2, 2.9)
    centre = np.array([3.0, -0.5])
    out, cov = position_only_loop(relative, centre, 2.5, 0.03**2, math.radians(90.0))
    marking = np.array([*centre, 0.0, 1.0])
    assert np.allclose(out @ marking, relative @ marking)  # the marking stays where ICP put it
    assert xy_yaw(out)[2] == pytest.approx(2.5)

    def whitened(measured: np.ndarray) -> float:  # as the back-end's between factor sees it: GTSAM's Pose2 Logmap
        import gtsam

        error = gtsam.Pose2.Logmap(gtsam.Pose2(*xy_yaw(out)).between(gtsam.Pose2(*xy_yaw(measured))))
        return float(error @ np.linalg.solve(cov, error))

    about = pose_from_xy_yaw(*centre, 0.0)
    turned = out @ about @ pose_from_xy_yaw(0.0, 0.0, 0.3) @ invert(about)  # 0.3 rad more, about the marking
    assert whitened(turned) == pytest.approx((0.3 / math.radians(90.0)) ** 2, rel=1e-9)
    moved = out @ about @ pose_from_xy_yaw(0.06, 0.0, 0.0) @ invert(about)  # the marking 6 cm off
    assert whitened(moved) == pytest.approx((0.06 / 0.03) ** 2, rel=1e-9)


def _leaves(node: object, prefix: str = "") -> dict[str, object]:
    if isinstance(node, dict):
        return {k: v for key, value in node.items() for k, v in _leaves(value, f"{prefix}{key}.").items()}
    return {prefix[:-1]: node}


@pytest.mark.parametrize(
    ("values", "expected"),
    [
        ({"consensus": {"min_support": -1}}, "loop.consensus.min_support: Input should be greater than or equal to 0"),
        ({"gate": {"enabled": "often"}}, "loop.gate.enabled: Input should be a valid boolean"),
        (
            {"consensus": {"min_suport": 1}},
            "loop.consensus.min_suport: unknown parameter (parameters of loop.consensus: ",
        ),
        ({"min_support": 1}, "loop.min_support: unknown parameter (parameters of this variant: icp, fit, "),
    ],
)
def test_a_bad_nested_key_is_named_in_full(values: dict[str, object], expected: str) -> None:
    from pydantic import ValidationError

    from sgf_pipeline.config import format_validation_error

    with pytest.raises(ValidationError) as err:
        IcpLoopParams.model_validate(values)
    message = format_validation_error("loop", IcpLoopParams, err.value)
    assert expected in message
    if "unknown" in expected and "consensus." in expected:
        assert "window, radius, drift" in message  # the keys of loop.consensus, not of loop
    if "min_support: Input" in expected:
        assert "expected int" in message


def test_the_plugin_listing_names_every_nested_key() -> None:
    from sgf_pipeline.registry import describe_params

    rows = {name: default for name, _, default, _ in describe_params(IcpLoopParams)}
    assert set(rows) == set(_leaves(IcpLoopParams().model_dump()))
    assert rows["consensus.min_support"] == 1 and rows["gate.enabled"] is True
