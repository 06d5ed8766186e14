"""loop=icp and the back-ends inside the runner: wiring (Previous[PoseEstimate]), run directory, second session."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from backend_world import CALIBRATION, OracleAssociation, World, make_world

from sgf_pipeline import Dataset, Pipeline, RunContext, Stage, StageParams, StageRegistry, hookimpl, load_plugins
from sgf_pipeline.sgf_map import MapDescriptor, load_map
from sgf_pipeline.trajectory import read_tum
from sgf_pipeline.types import Frame, GroupAssignments

WORLDS: dict[int, World] = {}


class ToyParams(StageParams):
    """Which toy world."""

    seed: int = 1
    laps: float = 2.0
    reverse_lap: bool = True


class ToyWorld(Dataset):
    """The synthetic world of the back-end tests, as a dataset."""

    name = "toy_world"
    Params = ToyParams

    def world(self) -> World:
        p = self.params
        assert isinstance(p, ToyParams)
        key = hash((p.seed, p.laps, p.reverse_lap))
        if key not in WORLDS:
            WORLDS[key] = make_world(
                seed=p.seed,
                laps=p.laps,
                reverse_lap=p.reverse_lap,
                odometry_noise=(0.01, math.radians(0.3), 0.01, math.radians(0.05)),
            )
        return WORLDS[key]

    def frames(self):  # type: ignore[no-untyped-def]
        yield from self.world().frames

    def __len__(self) -> int:
        return len(self.world().frames)

    def begin(self, context: RunContext) -> None:
        context.calibration = CALIBRATION
        context.truth = self.world().truth


class OracleParams(StageParams):
    """A prior SGF map to seed the groups with."""

    prior_map: str | None = None


class OracleGroups(Stage):
    """Association by design, from the world's ground truth (what the real association will output)."""

    kind = "association"
    name = "oracle"
    output = "assignments"
    Params = OracleParams

    def begin(self, context: RunContext) -> None:
        world = next(iter(WORLDS.values()))
        p = self.params
        assert isinstance(p, OracleParams)
        prior = load_map(p.prior_map).descriptors() if p.prior_map else None
        self.oracle = OracleAssociation(world, prior=prior)  # type: ignore[arg-type]

    def process(self, frame: Frame) -> GroupAssignments | None:
        """The frame's SGFs in their groups."""
        return self.oracle.assign(frame)


class ToyPlugin:
    """Registers the toy dataset and association."""

    @hookimpl
    def sgf_register_stages(self, registry: StageRegistry) -> None:
        registry.add(ToyWorld)
        registry.add(OracleGroups)


def config(backend: dict[str, Any], association: dict[str, Any] | None = None, plots: bool = False) -> dict[str, Any]:
    return {
        "pipeline": ["dataset", "association", "loop", "backend"],
        "dataset": {"name": "toy_world"},
        "association": {"name": "oracle", **(association or {})},
        # the toy robot has no camera to measure its odometry's noise: its datasheet's (backend_world.make_world)
        "loop": {"name": "icp", "gate": {"sigma_xy": 0.01, "sigma_yaw_deg": 0.3, "scale_error": 0.01}},
        "backend": backend,
        "run": {"progress": False, "plots": plots},
    }


@pytest.fixture(scope="module")
def plugins():  # type: ignore[no-untyped-def]
    return load_plugins(allow=["loop", "backend"], extra=[("toy", ToyPlugin())])


def test_a_run_closes_loops_and_writes_trajectory_metrics_and_map(tmp_path: Path, plugins) -> None:  # type: ignore[no-untyped-def]
    WORLDS.clear()
    pipeline = Pipeline.from_config(config({"name": "isam2"}, plots=True), run_dir=tmp_path, plugins=plugins)
    metrics = pipeline.run()
    saved = json.loads((tmp_path / "metrics.json").read_text())
    # five loops, and the toy manhole's two revisits as position-only loops
    assert saved["loops"]["closed"] == metrics["loops"]["closed"] == 7
    assert saved["loops"]["position_only"] == 2
    assert saved["loops"]["closed_reverse"] == 4  # one of the manhole's revisits is a reverse one
    assert saved["loops"]["false_closed"] == 0
    assert saved["backend"]["loop_factors"] == 7
    assert saved["ate_rmse_m"]["sgf"] < 0.4 * saved["ate_rmse_m"]["odometry"]
    trajectory = read_tum(tmp_path / "trajectory_sgf.tum")
    assert len(trajectory) == len(next(iter(WORLDS.values())).frames)
    sgf_map = load_map(tmp_path / "sgf_map.safetensors", calibration=CALIBRATION)
    assert len(sgf_map.views) == saved["backend"]["map"]["views"] == 15
    # every accepted loop is listed, where the plot and the report can show it
    with open(tmp_path / "loops.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == saved["loops"]["accepted"] == 7
    gt = read_tum(tmp_path / "trajectory_gt.tum")
    for row in rows:
        assert row["true"] == "True" and row["from_map"] == "False"
        assert float(row["truth_error_m"]) < 0.05 and float(row["truth_error_deg"]) < 1.0
        assert row["instance_from"] == row["instance_to"] != ""
        assert float(row["time_from"]) < float(row["time_to"])
        assert min(abs(gt.timestamps - float(row["time_to"]))) < 1e-6  # the stamps are the frames' own
    assert sum(row["reverse"] == "True" for row in rows) == 4
    assert sum(row["position_only"] == "True" for row in rows) == 2
    # ...and every match the loop stage decided on, with the test that refused it
    with open(tmp_path / "loop_candidates.csv", newline="") as f:
        decided = list(csv.DictReader(f))
    assert len(decided) == saved["loops"]["candidates"]
    refused = {k: v for k, v in saved["loops"]["rejected"].items() if v}
    assert {k: sum(r["outcome"] == k for r in decided) for k in refused} == refused
    assert [(r["frame_from"], r["frame_to"]) for r in decided if r["outcome"] == "accepted"] == [
        (r["frame_from"], r["frame_to"]) for r in rows
    ]
    assert all(
        float(r["gate_chi2"]) <= 16.27 and float(r["gate_sigma_xy"]) >= 0.5
        for r in decided
        if r["outcome"] == "accepted"
    )
    report = (tmp_path / "report.md").read_text()
    assert "## Accepted loops (7; all in `loops.csv`)" in report
    assert report.count("| True |") == 7 and report.count("at its marking | True |") == 2
    assert (tmp_path / "trajectory.png").stat().st_size > 10_000


def test_a_second_session_through_the_runner_localizes_on_the_first_ones_map(tmp_path: Path, plugins) -> None:  # type: ignore[no-untyped-def]
    WORLDS.clear()
    Pipeline.from_config(config({"name": "gtsam_lm"}), run_dir=tmp_path / "first", plugins=plugins).run()
    prior = str(tmp_path / "first" / "sgf_map.safetensors")
    assert all(isinstance(d, MapDescriptor) for d in load_map(prior).descriptors())
    cfg = config({"name": "isam2", "prior_map": prior}, {"prior_map": prior})
    metrics = Pipeline.from_config(cfg, run_dir=tmp_path / "second", plugins=plugins).run()
    assert metrics["loops"]["accepted_map"] >= 2
    assert metrics["loops"]["false_closed"] == 0
    with open(tmp_path / "second" / "loops.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    from_map = [row for row in rows if row["from_map"] == "True"]
    assert len(from_map) == metrics["loops"]["accepted_map"]
    # a map loop's first frame is the map's, not this run's: no time in this run, but its truth is known
    assert all(row["time_from"] == "" and float(row["truth_error_m"]) < 0.5 for row in from_map)
    assert metrics["backend"]["prior_map"]["anchored"] is True


def test_a_missing_prior_map_stops_the_pipeline_while_it_is_built(tmp_path: Path, plugins) -> None:  # type: ignore[no-untyped-def]
    from sgf_pipeline.errors import ConfigError

    missing = str(tmp_path / "none.safetensors")
    with pytest.raises(ConfigError, match="backend=gtsam_lm cannot start: SGF map not found"):
        Pipeline.from_config(config({"name": "gtsam_lm", "prior_map": missing}), run_dir=tmp_path, plugins=plugins)


def test_a_map_of_another_camera_stops_the_run_before_the_first_frame(tmp_path: Path, plugins) -> None:  # type: ignore[no-untyped-def]
    from sgf_pipeline.calibration import Calibration
    from sgf_pipeline.errors import DataError
    from sgf_pipeline.sgf_map import save_map

    WORLDS.clear()
    Pipeline.from_config(config({"name": "none"}), run_dir=tmp_path / "first", plugins=plugins).run()
    first = load_map(tmp_path / "first" / "sgf_map.safetensors")
    other = Calibration.from_mounting(CALIBRATION.intrinsics, height=1.2, tilt=0.35)
    save_map(tmp_path / "other.safetensors", replace(first, calibration=other))
    pipeline = Pipeline.from_config(
        config({"name": "isam2", "prior_map": str(tmp_path / "other.safetensors")}),
        run_dir=tmp_path / "second",
        plugins=plugins,
    )
    with pytest.raises(DataError, match="another camera calibration"):
        pipeline.run()
    assert pipeline.info.frames_processed == 0


def test_the_final_pose_graph_as_g2o_reads_back_to_the_same_poses(tmp_path: Path, plugins) -> None:  # type: ignore[no-untyped-def]
    """GTSAM reads pose_graph.g2o; optimised from dead reckoning under a prior on the first pose, it gives the run's poses."""
    import gtsam
    import numpy as np

    from sgf_pipeline.geometry import xy_yaw

    WORLDS.clear()
    pipeline = Pipeline.from_config(config({"name": "gtsam_lm", "graph": "g2o"}), run_dir=tmp_path, plugins=plugins)
    metrics = pipeline.run()
    backend = metrics["backend"]
    graph, written = gtsam.readG2o(str(tmp_path / "pose_graph.g2o"), False)
    keys = written.keys()
    ids = sorted(int(k) for k in keys)
    assert backend["loop_factors"] == 7 and backend["pose_nodes"] == len(ids) > 50
    assert graph.size() == len(ids) - 1 + 7  # an odometry edge between consecutive nodes, and the loops
    assert backend["graph"] == {"file": "pose_graph.g2o", "format": "g2o", "vertices": len(ids), "edges": graph.size()}
    lines = (tmp_path / "pose_graph.g2o").read_text().splitlines()
    assert lines[-1] == f"FIX {ids[0]}" and sum(line.startswith("EDGE_SE2 ") for line in lines) == graph.size()
    # the gauge: a prior on the first pose (as the run's); the start: the odometry edges chained from it
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, math.radians(0.01)]))
    graph.add(gtsam.PriorFactorPose2(ids[0], written.atPose2(ids[0]), noise))
    steps = {}
    for i in range(graph.size() - 1):
        factor = graph.at(i)
        a, b = factor.keys()
        if ids.index(b) == ids.index(a) + 1:
            steps[a] = factor.measured()
    start = gtsam.Values()
    pose = written.atPose2(ids[0])
    for key in ids:
        start.insert(key, pose)
        pose = pose.compose(steps[key]) if key in steps else pose
    assert len(steps) == len(ids) - 1
    lm = gtsam.LevenbergMarquardtParams()
    lm.setRelativeErrorTol(1e-14)
    lm.setAbsoluteErrorTol(1e-14)
    lm.setMaxIterations(500)
    result = gtsam.LevenbergMarquardtOptimizer(graph, start, lm).optimize()
    # The run's LM stopped once a step lowered the error by less than max(solver.relative_error_tol * error, the
    # absolute tolerance): its poses lie within that error of the optimum, so within sqrt(2 dE sigma^2) of
    # it along each axis (sigma^2: the optimum's marginal covariance, the inverse of the error's Hessian).
    run_lm = gtsam.LevenbergMarquardtParams()
    error = graph.error(written)
    stop = max(1e-6 * error, run_lm.getAbsoluteErrorTol())  # solver.relative_error_tol of backend=gtsam_lm: 1e-6
    marginals = gtsam.Marginals(graph, result)
    sgf = read_tum(tmp_path / "trajectory_sgf.tum")
    world = next(iter(WORLDS.values()))
    stamps = {f.index: f.timestamp for f in world.frames}
    worst = [0.0, 0.0]
    for key in ids:
        ours, theirs = written.atPose2(key), result.atPose2(key)
        covariance = marginals.marginalCovariance(key)
        tol_xy = math.sqrt(2 * stop * float(np.linalg.eigvalsh(covariance[:2, :2]).max()))
        tol_yaw = math.sqrt(2 * stop * float(covariance[2, 2]))
        offset = math.hypot(ours.x() - theirs.x(), ours.y() - theirs.y())
        turn = abs(math.remainder(ours.theta() - theirs.theta(), math.tau))
        assert offset <= tol_xy and turn <= tol_yaw, (key, offset, tol_xy, turn, tol_yaw)
        worst = [max(worst[0], offset / tol_xy), max(worst[1], turn / tol_yaw)]
        row = int(np.argmin(np.abs(sgf.timestamps - stamps[key])))  # the run's trajectory file: 9 decimals
        x, y, _ = xy_yaw(sgf.poses[row])
        assert math.hypot(x - theirs.x(), y - theirs.y()) <= tol_xy + 1e-8
    assert 0.0 < max(worst) <= 1.0


def test_a_g2o_graph_of_pose3_or_a_prior_map_is_refused(tmp_path: Path, plugins) -> None:  # type: ignore[no-untyped-def]
    from sgf_pipeline import ConfigError

    with pytest.raises(ConfigError, match=r"backend: graph=g2o writes the Pose2 graph of one session; the pose3"):
        Pipeline.from_config(config({"name": "gtsam_lm", "graph": "g2o", "pose": "pose3"}), plugins=plugins)
