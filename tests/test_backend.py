"""Back-ends of eq. 11: drift correction, online estimates, the robust kernel, gating, Pose3, outputs."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from backend_world import CALIBRATION, OracleAssociation, ate, make_world, run_stages
from sgf_plugins.backend.isam2 import Isam2Backend
from sgf_plugins.backend.lm import GtsamLmBackend
from sgf_plugins.backend.odometry_only import OdometryBackend
from sgf_plugins.backend.params import BackendParams, Isam2Params, LmParams
from sgf_plugins.loop.fitting import position_only_loop
from sgf_plugins.loop.params import ConsensusParams, GateParams, IcpLoopParams
from sgf_plugins.loop.stage import IcpLoopClosing

from sgf_pipeline.context import RunContext
from sgf_pipeline.geometry import invert, pose_from_xy_yaw, rpy_from_rotation, wrap_angle, xy_yaw
from sgf_pipeline.sgf_map import load_map
from sgf_pipeline.stage import Settlement
from sgf_pipeline.types import Frame, LoopConstraint, LoopConstraints

DRIFT = (0.02, math.radians(0.4), 0.015, math.radians(0.15))  # xy/sqrt(m), yaw/sqrt(m), scale, yaw bias/m
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def world():  # type: ignore[no-untyped-def]
    return make_world(seed=0, odometry_noise=DRIFT)


def true_loops(world, delay: int = 2, noise: float = 0.02) -> dict[int, list[LoopConstraint]]:  # type: ignore[no-untyped-def]
    """Loop constraints between the two frames of each revisit pair, measured from the ground truth."""
    rng = np.random.default_rng(11)
    cov = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])
    out: dict[int, list[LoopConstraint]] = {}
    for r in world.truth.revisits:
        a, b = (r.first.start_frame + r.first.end_frame) // 2, (r.second.start_frame + r.second.end_frame) // 2
        relative = invert(world.gt[a]) @ world.gt[b]
        x, y, yaw = xy_yaw(relative)
        noisy = pose_from_xy_yaw(x + rng.normal(0, noise), y + rng.normal(0, noise), yaw + rng.normal(0, 0.005))
        ids = (r.instance_id, r.instance_id)
        out.setdefault(b + delay, []).append(LoopConstraint(a, b, noisy, cov, 0, r.reverse, 0.01, 1.0, ids))
    return out


def feed(
    world,
    backend,
    loops: dict[int, list[LoopConstraint]],
    context: RunContext | None = None,
    settlement=None,
    between=None,
):  # type: ignore[no-untyped-def]
    """Stream the world's frames through the back-end and end the run (``between``: the settlement after settle)."""
    context = context or RunContext(run_dir=None, calibration=CALIBRATION)
    backend.begin(context)
    estimates = []
    for frame in world.frames:
        found = loops.get(frame.index)
        estimates.append(backend.process(frame=frame, loops=LoopConstraints(tuple(found)) if found else None))
    settled = backend.settle(context, settlement or Settlement())
    backend.conclude(context, between(settled) if between is not None else settled)
    backend.finalize(context)
    return context, estimates


@pytest.mark.parametrize(
    "backend",
    [
        GtsamLmBackend(LmParams(save_map=False)),
        Isam2Backend(Isam2Params(save_map=False)),
        GtsamLmBackend(LmParams(save_map=False, pose="pose3")),
        Isam2Backend(Isam2Params(save_map=False, pose="pose3")),
    ],
    ids=["lm-pose2", "isam2-pose2", "lm-pose3", "isam2-pose3"],
)
def test_loop_factors_correct_the_drift_of_odometry(world, backend) -> None:  # type: ignore[no-untyped-def]
    odometry_ate = ate(world.odometry, world.gt)
    assert odometry_ate > 8.0
    context, estimates = feed(world, backend, true_loops(world))
    trajectory = context.trajectories["sgf"]
    assert len(trajectory) == len(world.frames)
    np.testing.assert_array_equal(trajectory.timestamps, [f.timestamp for f in world.frames])
    sgf_ate = ate(trajectory.poses, world.gt)
    assert sgf_ate < 0.15 * odometry_ate
    assert context.metrics["backend"]["loop_factors"] == len(world.truth.revisits)
    # online: the estimate of the last frame is what the final optimisation gives, give or take
    assert ate(estimates[-1].poses.array(), world.gt) < 0.2 * odometry_ate


def test_every_frame_gets_an_estimate_of_every_processed_frame_that_later_frames_do_not_change(world) -> None:  # type: ignore[no-untyped-def]
    backend = GtsamLmBackend(LmParams(save_map=False))
    loops = true_loops(world)
    _, estimates = feed(world, backend, loops)
    first_loop_frame = min(loops)
    before = estimates[first_loop_frame - 1]
    kept = {k: before.poses[k] for k in before.poses}
    for k, estimate in enumerate(estimates):
        assert estimate.frame_index == world.frames[k].index
        assert len(estimate.poses) == k + 1
        assert list(estimate.poses)[-1] == world.frames[k].index
    assert world.frames[first_loop_frame].index not in before.poses
    # a later optimisation moved the trajectory, but not the earlier snapshot
    after = estimates[-1]
    assert max(np.abs(after.poses[k] - kept[k]).max() for k in kept) > 1.0
    assert all(np.array_equal(before.poses[k], kept[k]) for k in kept)
    # before any loop, the estimate is dead reckoning from the first pose
    np.testing.assert_allclose(before.poses[first_loop_frame - 1], world.odometry[first_loop_frame - 1], atol=1e-6)


def test_no_backend_is_odometry(world) -> None:  # type: ignore[no-untyped-def]
    context, estimates = feed(world, OdometryBackend(BackendParams(save_map=False)), true_loops(world))
    np.testing.assert_array_equal(context.trajectories["sgf"].poses, world.odometry)
    np.testing.assert_array_equal(estimates[10].poses[10], world.odometry[10])
    assert context.metrics["backend"]["loops_received"] == len(world.truth.revisits)


def look_alike_loop(world, a: int, b: int) -> LoopConstraint:  # type: ignore[no-untyped-def]
    """What ICP reports when frame ``a`` sees marking 1 and frame ``b`` its look-alike, marking 5, 40 m away."""
    markings = {m.instance_id: pose_from_xy_yaw(*m.pose) for m in world.markings}
    seen_a = invert(world.gt[a]) @ markings[1]
    seen_b = invert(world.gt[b]) @ markings[5]
    cov = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])
    return LoopConstraint(a, b, seen_a @ invert(seen_b), cov, 0, False, 0.01, 1.0, (1, 5))


@pytest.mark.parametrize(("kernel", "moves"), [("cauchy", False), ("huber", True), ("none", True)])
def test_the_cauchy_kernel_ignores_a_false_loop(world, kernel: str, moves: bool) -> None:  # type: ignore[no-untyped-def]
    loops = true_loops(world)
    clean, _ = feed(world, GtsamLmBackend(LmParams(save_map=False, loop={"kernel": kernel})), loops)  # type: ignore[arg-type]
    marking_5 = [r.second for r in world.truth.revisits if r.instance_id == 5][-1]
    marking_1 = next(r.second for r in world.truth.revisits if r.instance_id == 1)
    a, b = (marking_1.start_frame + marking_1.end_frame) // 2, (marking_5.start_frame + marking_5.end_frame) // 2
    false = look_alike_loop(world, a, b)
    assert np.linalg.norm((invert(world.gt[a]) @ world.gt[b])[:2, 3] - false.relative[:2, 3]) > 30.0
    polluted = {k: list(v) for k, v in loops.items()}
    polluted.setdefault(b + 3, []).append(false)
    dirty, _ = feed(world, GtsamLmBackend(LmParams(save_map=False, loop={"kernel": kernel})), polluted)  # type: ignore[arg-type]
    moved = np.linalg.norm(dirty.trajectories["sgf"].positions - clean.trajectories["sgf"].positions, axis=1).max()
    if moves:
        assert moved > 2.0
    else:
        # a few centimetres: below the loops' own sigma (5 cm) and the odometry's noise over 10 m (6 cm)
        assert moved < 0.05


def test_the_gate_alone_keeps_look_alikes_out_of_the_graph() -> None:
    world = make_world(seed=1, odometry_noise=(0.01, math.radians(0.3), 0.01, math.radians(0.05)))
    no_kernel = LmParams(save_map=False, loop={"kernel": "none"})
    alone = IcpLoopParams(consensus=ConsensusParams(min_support=0))  # no neighbour consensus: the gate alone
    reference = run_stages(
        world, IcpLoopClosing(alone), GtsamLmBackend(no_kernel), OracleAssociation(world, by="instance")
    )
    gated = run_stages(world, IcpLoopClosing(alone), GtsamLmBackend(no_kernel))
    no_gate = IcpLoopParams(gate=GateParams(enabled=False), consensus=ConsensusParams(min_support=0))
    ungated = run_stages(world, IcpLoopClosing(no_gate), GtsamLmBackend(no_kernel))
    ate_of = {
        name: ate(run.context.trajectories["sgf"].poses, world.gt)  # type: ignore[attr-defined]
        for name, run in (("reference", reference), ("gated", gated), ("ungated", ungated))
    }
    assert gated.context.metrics["loops"]["false_closed"] == 0  # type: ignore[attr-defined]
    assert ungated.context.metrics["loops"]["false_closed"] == 4  # type: ignore[attr-defined]
    assert ate_of["gated"] < 1.5 * ate_of["reference"]
    assert ate_of["ungated"] > 5.0 * ate_of["reference"]


def test_pose3_takes_roll_and_pitch_from_the_imu() -> None:
    frames = []
    for k in range(60):
        pose = pose_from_xy_yaw(float(k), 0.2 * k, 0.1 * k)
        frames.append(Frame(k, 0.1 * k, np.zeros((2, 2), np.uint8), pose, CALIBRATION, imu_roll_pitch=(0.05, -0.03)))
    backend = Isam2Backend(Isam2Params(save_map=False, pose="pose3"))
    backend.begin(RunContext(run_dir=None))
    estimate = None
    for f in frames:
        estimate = backend.process(frame=f, loops=None)
    assert estimate is not None
    for k in (0, 30, 59):
        roll, pitch, yaw = rpy_from_rotation(estimate.poses[k][:3, :3])
        assert roll == pytest.approx(0.05, abs=0.003)
        assert pitch == pytest.approx(-0.03, abs=0.003)
        assert yaw == pytest.approx(math.remainder(0.1 * k, 2 * math.pi), abs=0.01)


def test_bad_loop_constraints_are_clear_errors(world) -> None:  # type: ignore[no-untyped-def]
    backend = GtsamLmBackend(LmParams(save_map=False))
    backend.begin(RunContext(run_dir=None))
    for f in world.frames[:5]:
        backend.process(frame=f, loops=None)
    cov = np.eye(3) * 0.01

    def loop(a: int, b: int, covariance: np.ndarray = cov, from_map: bool = False) -> LoopConstraints:
        return LoopConstraints((LoopConstraint(a, b, np.eye(4), covariance, 0, False, 0.0, 1.0, from_map=from_map),))

    frame = world.frames[5]
    with pytest.raises(ValueError, match="loop constraint to frame 50, which is not a processed frame"):
        backend.process(frame=frame, loops=loop(0, 50))
    with pytest.raises(ValueError, match="positive definite"):
        backend.process(frame=world.frames[6], loops=loop(0, 3, np.zeros((3, 3))))
    with pytest.raises(ValueError, match="map frame 0, which the prior map does not hold"):
        backend.process(frame=world.frames[7], loops=loop(0, 3, from_map=True))


def test_finalize_writes_the_trajectory_metrics_and_a_loadable_map(tmp_path: Path) -> None:
    world = make_world(seed=2, laps=1.0)
    run = run_stages(world, IcpLoopClosing(IcpLoopParams()), Isam2Backend(Isam2Params()), run_dir=tmp_path)
    context = run.context
    metrics = context.metrics["backend"]  # type: ignore[attr-defined]
    assert metrics["variant"] == "isam2"
    assert metrics["nodes"] == len(world.frames)
    assert metrics["loop_factors"] == len(run.loops) > 0
    assert metrics["map"]["views"] == sum(len(v) for v in world.sgfs.values())
    sgf_map = load_map(tmp_path / "sgf_map.safetensors", calibration=CALIBRATION)
    final = context.trajectories["sgf"]  # type: ignore[attr-defined]
    by_frame = dict(zip([f.index for f in world.frames], final.poses, strict=True))
    for view in sgf_map.views:
        np.testing.assert_allclose(view.pose, by_frame[view.frame_index], atol=1e-9)
        np.testing.assert_array_equal(view.ground_truth, world.gt[view.frame_index])


def test_isam2_survives_a_long_straight_drive_and_anchors_in_a_map_at_its_end(tmp_path: Path) -> None:
    from backend_world import GRID, drifting_odometry

    from sgf_pipeline.sgf_map import MapGroup, MapView, SgfMap, save_map

    # A straight 2.5 km without a loop: the far end is so uncertain that iSAM2's Cholesky
    # factorization calls the system indeterminate after ~1.9 km (hence factorization: qr).
    n = 2500
    gt = np.stack([pose_from_xy_yaw(float(k), 0.0, 0.0) for k in range(n)])
    odometry = drifting_odometry(gt, np.random.default_rng(4), 0.01, math.radians(0.1), 0.0, 0.0)
    points = np.array([[2.0, 0.0], [2.5, 0.1], [3.0, -0.1], [2.2, 0.4]])
    view = MapView(7, 123, 0.0, gt[-1], points, points.mean(0), np.zeros((10, 90)), np.zeros(10), GRID)
    save_map(tmp_path / "map.safetensors", SgfMap((MapGroup(7, False, (view,)),), CALIBRATION))
    backend = Isam2Backend(Isam2Params(save_map=False, prior_map=str(tmp_path / "map.safetensors")))
    backend.begin(RunContext(run_dir=None, calibration=CALIBRATION))
    cov = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])
    anchor = LoopConstraints((LoopConstraint(123, n - 1, np.eye(4), cov, 7, False, 0.01, 1.0, from_map=True),))
    estimate = None
    for k in range(n):
        frame = Frame(k, 0.1 * k, np.zeros((1, 1), np.uint8), odometry[k], CALIBRATION)
        estimate = backend.process(frame=frame, loops=anchor if k == n - 1 else None)
    assert estimate is not None
    assert np.linalg.norm(odometry[-1][:2, 3] - gt[-1][:2, 3]) > 10.0
    # the run now sits in the map frame: its last pose on the map's view pose
    np.testing.assert_allclose(estimate.poses[n - 1][:2, 3], gt[-1][:2, 3], atol=0.1)
    assert backend.graph.anchored and backend.graph.map_factors == 1


def test_pose2_keeps_the_odometry_height_roll_and_pitch(world) -> None:  # type: ignore[no-untyped-def]
    from backend_world import World

    from sgf_pipeline.geometry import rotation_rpy

    frames = []
    for f in world.frames:
        tilt = np.eye(4)
        tilt[:3, :3] = rotation_rpy(0.01, 0.03, 0.0)
        tilt[2, 3] = 0.02 * f.index  # climbing
        frames.append(Frame(f.index, f.timestamp, f.image, f.odometry @ tilt, CALIBRATION, ground_truth=f.ground_truth))
    sloped = World(world.gt, np.stack([f.odometry for f in frames]), world.markings, frames, world.sgfs, world.truth)
    context, estimates = feed(
        sloped, GtsamLmBackend(LmParams(save_map=False, heading_bias={"hindsight": False})), true_loops(world)
    )
    poses = context.trajectories["sgf"].poses
    np.testing.assert_allclose(poses[:, 2, 3], 0.02 * np.arange(len(frames)), atol=1e-9)
    roll, pitch, _ = rpy_from_rotation(poses[100][:3, :3])
    assert (roll, pitch) == pytest.approx((0.01, 0.03), abs=1e-9)
    np.testing.assert_allclose(estimates[-1].poses[len(frames) - 1], poses[-1], atol=1e-4)  # before the final LM
    assert ate(poses, world.gt) < 0.15 * ate(world.odometry, world.gt)


def test_isam2_defaults_keep_the_loops_correction(world) -> None:  # type: ignore[no-untyped-def]
    """The partial relinearization check (on every update) ends where the full check does, near batch LM.

    Checking only every 10th update with the partial check loses part of a loop's correction (ATE +36 %
    here, 0.41 -> 0.99 m on the default run), which is why the default keeps ``solver.relinearize_skip: 1``.
    """
    loops = true_loops(world)
    online = {"save_map": False, "heading_bias": {"hindsight": False}}  # the solvers' own ends, no batch re-solve
    lm, _ = feed(world, GtsamLmBackend(LmParams(**online)), loops)
    partial, _ = feed(world, Isam2Backend(Isam2Params(**online)), loops)
    full, _ = feed(world, Isam2Backend(Isam2Params(**online, solver={"partial_relinearization_check": False})), loops)
    sparse, _ = feed(world, Isam2Backend(Isam2Params(**online, solver={"relinearize_skip": 10})), loops)
    errors = {
        k: ate(c.trajectories["sgf"].poses, world.gt)
        for k, c in [("lm", lm), ("partial", partial), ("full", full), ("sparse", sparse)]
    }
    assert errors["partial"] == pytest.approx(errors["full"], abs=0.01)
    assert errors["partial"] < 1.2 * errors["lm"]
    assert errors["sparse"] > 1.3 * errors["lm"]


@pytest.mark.parametrize("pose", ["pose2", "pose3"])
def test_a_translation_threshold_relinearizes_less_and_ends_at_the_same_trajectory(world, pose: str) -> None:  # type: ignore[no-untyped-def]
    loops = true_loops(world)
    default = Isam2Backend(Isam2Params(save_map=False, pose=pose))
    coarse = Isam2Backend(Isam2Params(save_map=False, pose=pose, solver={"relinearize_threshold_translation": 1.0}))
    a, _ = feed(world, default, loops)
    b, _ = feed(world, coarse, loops)
    # rotations still relinearize at 0.1 rad, translations only past 1 m: less than half the variables relinearized
    # (1,702 against 4,413 in Pose2)...
    assert sum(coarse.relinearized) < 0.5 * sum(default.relinearized)
    # ...for a trajectory about as good: ATE 0.575 against 0.526 m in Pose2 (odometry 12.7 m, batch LM 0.469)
    default_ate, coarse_ate = ate(a.trajectories["sgf"].poses, world.gt), ate(b.trajectories["sgf"].poses, world.gt)
    assert coarse_ate < 1.15 * default_ate and coarse_ate < 0.05 * ate(world.odometry, world.gt)


def test_a_pose_table_takes_many_frames_at_once_like_a_mapping() -> None:
    from sgf_plugins.backend.pose_graph import PoseStore

    from sgf_pipeline.types import PoseEstimate

    store = PoseStore(lifted=True)
    rng = np.random.default_rng(0)
    for k in range(0, 40, 2):
        lift = np.eye(4)
        lift[2, 3] = rng.normal()
        store.append(k, pose_from_xy_yaw(*rng.normal(size=3)), lift)
    table = store.snapshot()
    store.append(40, np.eye(4))  # after the snapshot: not in it
    frames = np.array([4, 5, 0, 38, 40, 4])
    fast, found = PoseEstimate(38, table).stack(frames)
    slow, found_slow = PoseEstimate(38, dict(table)).stack(frames)
    np.testing.assert_array_equal(found, [True, False, True, True, False, True])
    np.testing.assert_array_equal(found, found_slow)
    np.testing.assert_allclose(fast[found], slow[found])
    np.testing.assert_allclose(fast[0], table[4])
    assert table[4][2, 3] != 0.0  # the lift is applied
    assert np.isnan(fast[~found]).all() and np.isnan(slow[~found]).all()


@pytest.mark.parametrize("backend_class", [GtsamLmBackend, Isam2Backend])
@pytest.mark.parametrize("pose", ["pose2", "pose3"])
def test_pose_nodes_every_few_metres_give_the_node_per_frame_trajectory(world, backend_class, pose) -> None:  # type: ignore[no-untyped-def]
    """Frames between nodes ride on their node by odometry; loops reach frames between nodes (delay=2:
    the loop's newest frame is no longer the newest) through their nodes, covariance moved by the adjoint."""
    params = LmParams if backend_class is GtsamLmBackend else Isam2Params
    loops = true_loops(world, delay=2)
    dense, _ = feed(world, backend_class(params(save_map=False, pose=pose, node_distance=0.0)), loops)
    sparse, estimates = feed(world, backend_class(params(save_map=False, pose=pose, node_distance=2.5)), loops)
    nodes = sparse.metrics["backend"]["pose_nodes"]
    assert nodes < 0.45 * len(world.frames) and dense.metrics["backend"]["pose_nodes"] == len(world.frames)
    a, b = dense.trajectories["sgf"].poses, sparse.trajectories["sgf"].poses
    assert len(b) == len(world.frames)
    assert np.abs(a[:, :2, 3] - b[:, :2, 3]).max() < 0.15
    assert ate(b, world.gt) == pytest.approx(ate(a, world.gt), rel=0.05)
    assert sparse.metrics["backend"]["loop_factors"] == len(world.truth.revisits)
    # online: every processed frame has an estimate, frames between nodes included
    assert [len(e.poses) for e in estimates] == list(range(1, len(world.frames) + 1))


def test_a_loop_to_a_frame_between_nodes_moves_by_the_adjoint() -> None:
    """One loop whose newest end lies between two nodes: the sparse graph lands where the dense one does.

    The nodes' odometry factors sum the steps' variances (about 5 cm apart from the dense graph here);
    a loop covariance left in the frame's axes instead of the node's puts it 35 cm off.
    """
    rng = np.random.default_rng(4)
    gt, odometry = [np.eye(4)], [np.eye(4)]
    for _ in range(1, 80):  # a 0.5 m-step drive that turns back on itself
        step = pose_from_xy_yaw(0.5, 0.0, math.radians(2.5))
        gt.append(gt[-1] @ step)
        noisy = pose_from_xy_yaw(0.5 * 1.02, rng.normal(0, 0.01), math.radians(2.5) + 0.01)
        odometry.append(odometry[-1] @ noisy)
    frames = [Frame(k, 0.1 * k, None, odometry[k], CALIBRATION, None, None, None) for k in range(80)]
    cov = np.diag([0.02**2, 0.05**2, math.radians(2.0) ** 2])  # anisotropic: a wrong frame would show
    loop = LoopConstraint(3, 74, invert(gt[3]) @ gt[74], cov, 0, False, 0.01, 1.0, (1, 1))
    results = []
    for node_distance in (0.0, 2.2):
        backend = GtsamLmBackend(LmParams(save_map=False, node_distance=node_distance, loop={"kernel": "none"}))
        backend.begin(RunContext(run_dir=None, calibration=CALIBRATION))
        for frame in frames:
            backend.process(frame, LoopConstraints((loop,)) if frame.index == 78 else None)
        assert backend.graph.is_node(74) == (node_distance == 0.0)
        results.append(backend.poses()[1])
    dense, sparse = results
    assert np.abs(dense[:, :2, 3] - sparse[:, :2, 3]).max() < 0.12

    def loop_error(poses: np.ndarray) -> float:
        return float(np.linalg.norm((invert(invert(poses[3]) @ poses[74]) @ loop.relative)[:2, 3]))

    assert loop_error(np.stack(odometry)) > 0.5 and loop_error(dense) < 0.05


def test_isam2_reports_how_much_each_update_reeliminates_and_a_contradicted_graph_shows(world) -> None:  # type: ignore[no-untyped-def]
    """``backend.isam2`` in metrics.json: a graph whose loops contradict its odometry (a jump the odometry
    missed, like a soak's lap ends without the carry back to the start) keeps re-eliminating much of itself."""
    loops = true_loops(world)
    consistent, _ = feed(world, Isam2Backend(Isam2Params(save_map=False)), loops)
    from backend_world import World

    half = world.frames[len(world.frames) // 2].odometry
    jump = half @ pose_from_xy_yaw(5.0, 0.0, 0.5) @ invert(half)  # the odometry misses 5 m and 0.5 rad halfway
    frames = [
        Frame(
            f.index,
            f.timestamp,
            f.image,
            jump @ f.odometry if k >= len(world.frames) // 2 else f.odometry,
            CALIBRATION,
            ground_truth=f.ground_truth,
        )
        for k, f in enumerate(world.frames)
    ]
    jumped = World(world.gt, np.stack([f.odometry for f in frames]), world.markings, frames, world.sgfs, world.truth)
    contradicted, _ = feed(jumped, Isam2Backend(Isam2Params(save_map=False)), loops)
    a = consistent.metrics["backend"]["isam2"]
    b = contradicted.metrics["backend"]["isam2"]
    for run, counts in ((consistent, a), (contradicted, b)):  # an update per pose node, and per loop landing on one
        backend = run.metrics["backend"]
        assert backend["pose_nodes"] <= counts["updates"] <= backend["pose_nodes"] + backend["loop_factors"]
    assert a["reeliminated_median"] <= 10 and a["relinearized_median"] <= 10
    assert b["reeliminated_p90"] > 5 * a["reeliminated_p90"]


BIASED = (0.005, math.radians(0.05), 0.0, math.radians(0.2))  # small noise, a 0.2 deg/m heading bias


@pytest.mark.parametrize(
    ("backend_class", "params_class", "pose"),
    [
        (GtsamLmBackend, LmParams, "pose2"),
        (Isam2Backend, Isam2Params, "pose2"),
        (GtsamLmBackend, LmParams, "pose3"),
        (Isam2Backend, Isam2Params, "pose3"),
    ],
    ids=["lm-pose2", "isam2-pose2", "lm-pose3", "isam2-pose3"],
)
def test_the_odometry_heading_bias_is_estimated_from_loops_and_corrects_the_drive_after_them(
    backend_class, params_class, pose
) -> None:  # type: ignore[no-untyped-def]
    # Loops on the first laps only: the last lap (reverse) has none, and drifts by the bias unless it is known.
    biased = make_world(seed=4, laps=2.0, odometry_noise=BIASED)
    lap = len(biased.frames) // 3
    loops = {k: v for k, v in true_loops(biased).items() if k < 2 * lap}
    assert loops and max(loops) < 2 * lap
    results = {}
    for estimate_bias in (False, True):
        backend = backend_class(params_class(save_map=False, pose=pose, heading_bias={"enabled": estimate_bias}))
        context, estimates = feed(biased, backend, loops)
        tail = context.trajectories["sgf"].poses[2 * lap :]
        results[estimate_bias] = (rmse_xy(tail, biased.gt[2 * lap :]), context.metrics["backend"])
        # the published estimates say from which frame the odometry is corrected, and how well the bias is known
        models = [e.yaw_bias for e in estimates if e.yaw_bias is not None]
        if not estimate_bias:
            assert models == []
            continue
        # a model from the first frame: before any loop the bias wheel odometry is expected to have
        assert len(models) == len(estimates) and models[0].since is None
        assert models[0].uncorrected == pytest.approx(math.radians(0.1))
        corrected = [c for c in models if c.since is not None]
        loop_frames = sorted(loops)
        first = next(k for k, e in enumerate(estimates) if e.yaw_bias is not None and e.yaw_bias.since is not None)
        assert first in loop_frames[1:]  # applied on a loop, once a second one agrees
        assert {c.since for c in corrected} == {first}
        # once loops measured it, the bias on uncorrected odometry is theirs: 0.2 deg/m
        assert math.degrees(corrected[-1].uncorrected) == pytest.approx(0.2, abs=0.02)
        sigma = corrected[-1].sigma
        assert sigma == pytest.approx(math.radians(context.metrics["backend"]["odometry_yaw_bias"]["sigma_deg_per_m"]))
        assert 0.0 < sigma < math.radians(0.1)
    plain, with_bias = results[False], results[True]
    assert "odometry_yaw_bias" not in plain[1]
    assert with_bias[1]["odometry_yaw_bias"]["deg_per_m"] == pytest.approx(0.2, abs=0.02)
    assert with_bias[1]["odometry_yaw_bias"]["loops"] == sum(len(v) for v in loops.values())
    assert with_bias[0] < 0.3 * plain[0]  # the unlooped lap, placed by the corrected odometry


@pytest.mark.parametrize("solver", ["gtsam_lm", "isam2"])
def test_the_final_heading_bias_straightens_the_drive_before_the_loops_that_measured_it(solver: str) -> None:
    """Loops only from the middle lap on: online the bias corrects the drive after them; at the end, all of it."""
    biased = make_world(seed=4, laps=2.0, odometry_noise=BIASED)
    lap = len(biased.frames) // 3
    loops = {k: v for k, v in true_loops(biased).items() if k >= 3 * lap // 2}
    assert min(loops) >= 3 * lap // 2
    errors, metrics = {}, {}
    for hindsight in (False, True):
        settings = {"save_map": False, "heading_bias": {"hindsight": hindsight}}
        backend = (
            GtsamLmBackend(LmParams(**settings)) if solver == "gtsam_lm" else Isam2Backend(Isam2Params(**settings))
        )  # type: ignore[arg-type]
        context, _ = feed(biased, backend, loops)
        errors[hindsight] = rmse_xy(context.trajectories["sgf"].poses, biased.gt)
        metrics[hindsight] = context.metrics["backend"]["odometry_yaw_bias"]
    assert metrics[True]["hindsight"] and not metrics[False]["hindsight"]
    assert metrics[True]["deg_per_m"] == pytest.approx(0.2, abs=0.01)  # the same estimate both times
    assert metrics[True]["deg_per_m"] == metrics[False]["deg_per_m"]
    assert errors[False] > 10.0 * errors[True]  # measured: 11.8 m against 0.52 m (odometry 30.7 m)
    assert errors[True] < 1.0


def rmse_xy(poses: np.ndarray, gt: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2, 3] - gt[:, :2, 3]) ** 2, axis=1))))


@pytest.mark.parametrize(
    "backend",
    [GtsamLmBackend(LmParams(save_map=False)), Isam2Backend(Isam2Params(save_map=False))],
    ids=["lm", "isam2"],
)
def test_loops_closed_at_the_end_of_the_run_enter_the_final_optimisation(world, backend) -> None:  # type: ignore[no-untyped-def]
    context = RunContext(run_dir=None, calibration=CALIBRATION)
    final = [loop for loops in true_loops(world).values() for loop in loops]
    context, _ = feed(world, backend, {}, context, Settlement(final_loops=LoopConstraints(tuple(final))))
    assert context.metrics["backend"]["loop_factors"] == len(world.truth.revisits) == backend.loops_received
    assert ate(context.trajectories["sgf"].poses, world.gt) < 0.15 * ate(world.odometry, world.gt)


@pytest.mark.parametrize(
    "backend",
    [
        GtsamLmBackend(LmParams(save_map=False, heading_bias={"enabled": True})),
        Isam2Backend(Isam2Params(save_map=False, heading_bias={"enabled": True})),
        GtsamLmBackend(LmParams(save_map=False, pose="pose3", heading_bias={"enabled": True})),
        Isam2Backend(Isam2Params(save_map=False, pose="pose3", heading_bias={"enabled": True})),
    ],
    ids=["lm-pose2", "isam2-pose2", "lm-pose3", "isam2-pose3"],
)
def test_position_only_loops_join_their_markings_and_leave_the_turn_to_the_odometry(world, backend) -> None:  # type: ignore[no-untyped-def]
    # every revisit as a round marking 3 m ahead of the later view, each loop's turn 20 degrees off the truth
    centre = np.array([3.0, 0.4])
    loops: dict[int, list[LoopConstraint]] = {}
    for k, (at, items) in enumerate(sorted(true_loops(world).items())):
        c = items[0]
        turn = xy_yaw(c.relative)[2] + math.radians(20.0 if k % 2 else -20.0)
        relative, cov = position_only_loop(c.relative, centre, turn, 0.03**2, math.radians(90.0))
        loops[at] = [replace(c, relative=relative, covariance=cov, marking=(float(centre[0]), float(centre[1])))]
    context, _ = feed(world, backend, loops)
    poses = context.trajectories["sgf"].poses
    odometry_ate = ate(world.odometry, world.gt)
    assert ate(poses, world.gt) < 0.06 * odometry_ate  # the places alone take out the drift (full loops: 3.6 %)
    marking = np.array([*centre, 0.0, 1.0])
    for items in loops.values():
        c = items[0]
        estimated = invert(poses[c.frame_from]) @ poses[c.frame_to]
        truth = invert(world.gt[c.frame_from]) @ world.gt[c.frame_to]
        assert np.linalg.norm((estimated @ marking - truth @ marking)[:2]) < 0.08  # the marking where both saw it
        turn_error = abs(math.degrees(wrap_angle(xy_yaw(estimated)[2] - xy_yaw(truth)[2])))
        assert turn_error < 6.0  # not the loop's 20 degrees
    # the heading bias is read from loops' turns: position-only loops have none to give
    assert context.metrics["backend"]["odometry_yaw_bias"]["loops"] == 0


def test_a_robust_factor_s_g2o_information_carries_the_kernel_s_weight():
    """Cauchy(k=3) at a whitened error of 3: the weight k^2 / (k^2 + e^2) = 1/2 scales the information."""
    import gtsam
    from sgf_plugins.backend.pose_graph import _information

    gaussian = gtsam.noiseModel.Gaussian.Covariance(np.diag([0.01, 0.01, 0.001]))
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(3.0), gaussian)
    values = gtsam.Values()
    values.insert(1, gtsam.Pose2(0.0, 0.0, 0.0))
    values.insert(2, gtsam.Pose2(0.3, 0.0, 0.0))  # 0.3 m off the measured identity: 3 sigmas
    np.testing.assert_allclose(
        _information(gtsam.BetweenFactorPose2(1, 2, gtsam.Pose2(), robust), values),
        0.5 * np.diag([100.0, 100.0, 1000.0]),
        rtol=1e-12,
    )
    np.testing.assert_allclose(
        _information(gtsam.BetweenFactorPose2(1, 2, gtsam.Pose2(), gaussian), values),
        np.diag([100.0, 100.0, 1000.0]),
        rtol=1e-12,
    )
