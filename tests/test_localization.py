"""Localization on a prior SGF map: a second session is corrected in the first session's map frame (eq. 11)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from backend_world import Marking, OracleAssociation, ate, make_world, rmse, run_stages
from sgf_plugins.backend.isam2 import Isam2Backend
from sgf_plugins.backend.lm import GtsamLmBackend
from sgf_plugins.backend.params import Isam2Params, LmParams
from sgf_plugins.loop.stage import IcpLoopClosing, IcpLoopParams

from sgf_pipeline.sgf_map import load_map

MARKINGS = [
    Marking(1, "arrow", (15.0, 0.0, 0.2)),
    Marking(2, "ell", (40.0, 0.0, -0.3)),
    Marking(3, "tee", (60.0, 12.0, math.pi / 2)),
    Marking(4, "arrow", (60.0, 30.0, 1.0)),
    Marking(5, "ell", (45.0, 40.0, math.pi)),
    Marking(6, "tee", (20.0, 40.0, 2.5)),
    Marking(7, "arrow", (0.0, 30.0, -math.pi / 2)),
    Marking(8, "ell", (0.0, 10.0, 0.7)),
]


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Session 1: a lap and a reverse lap, optimized, its SGF map saved."""
    world = make_world(seed=21, laps=1.0, markings=MARKINGS)
    run_dir = tmp_path_factory.mktemp("session1")
    run_stages(
        world,
        IcpLoopClosing(IcpLoopParams()),
        GtsamLmBackend(LmParams()),
        OracleAssociation(world, by="instance"),
        run_dir=run_dir,
    )
    return run_dir / "sgf_map.safetensors"


def second_session(seed: int = 5):  # type: ignore[no-untyped-def]
    """Session 2: its own drifting odometry in its own frame, starting a fifth of a lap further on."""
    world = make_world(
        seed=seed,
        laps=1.3,
        reverse_lap=False,
        markings=MARKINGS,
        odometry_noise=(0.02, math.radians(0.4), 0.015, math.radians(-0.12)),
        odometry_start=(-20.0, 35.0, 1.0),  # its own odometry frame, unrelated to the map's
    )
    return world, world.frames[40:]


@pytest.mark.parametrize("backend", ["gtsam_lm", "isam2"])
def test_a_second_session_is_corrected_in_the_map_frame(mapped: Path, backend: str) -> None:
    sgf_map = load_map(mapped)
    assert len(sgf_map.groups) == 8
    world, frames = second_session()
    params = {"prior_map": str(mapped), "save_map": False}
    stage = GtsamLmBackend(LmParams(**params)) if backend == "gtsam_lm" else Isam2Backend(Isam2Params(**params))
    run = run_stages(
        world,
        IcpLoopClosing(IcpLoopParams()),
        stage,
        OracleAssociation(world, by="instance", prior=sgf_map.descriptors()),
        frames=frames,
    )
    metrics = run.context.metrics  # type: ignore[attr-defined]
    assert metrics["loops"]["accepted_map"] >= 7
    assert metrics["loops"]["false_closed"] == 0
    assert metrics["backend"]["prior_map"] == {"map_id": sgf_map.map_id, "anchored": True}
    assert metrics["backend"]["map_factors"] == metrics["loops"]["accepted_map"]
    estimate = run.context.trajectories["sgf"].poses  # type: ignore[attr-defined]
    gt = world.gt[40:]
    odometry = world.odometry[40:]
    assert ate(odometry, gt) > 2.5
    assert ate(estimate, gt) < 0.2 * ate(odometry, gt)
    # in the map's own frame (session 1 started on its ground truth), with no alignment at all:
    # as good as the map itself (session 1's own error in that frame is 0.6 m)
    assert rmse(estimate, gt) < 1.0
    assert rmse(odometry, gt) > 20.0


def test_a_look_alike_in_the_map_does_not_place_the_run() -> None:
    # the default world: arrows 1 and 5 look alike and share a group, in the map too
    first = make_world(seed=1, laps=1.0, odometry_noise=(0.01, math.radians(0.3), 0.01, math.radians(0.05)))
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        run_stages(first, IcpLoopClosing(IcpLoopParams()), GtsamLmBackend(LmParams()), run_dir=Path(tmp))
        sgf_map = load_map(Path(tmp) / "sgf_map.safetensors")
        second = make_world(seed=9, laps=1.2, reverse_lap=False, odometry_start=(0.0, 0.0, 2.0))
        run = run_stages(
            second,
            IcpLoopClosing(IcpLoopParams()),
            Isam2Backend(Isam2Params(prior_map=str(Path(tmp) / "sgf_map.safetensors"), save_map=False)),
            OracleAssociation(second, prior=sgf_map.descriptors()),
        )
    loops = run.context.metrics["loops"]  # type: ignore[attr-defined]
    map_loops = [c for c in run.loops if c.from_map]
    assert len(map_loops) >= 2
    assert all(c.instance_ids[0] == c.instance_ids[1] for c in map_loops)
    assert loops["false_closed"] == 0
    assert run.context.metrics["backend"]["prior_map"]["anchored"] is True  # type: ignore[attr-defined]
    estimate = run.context.trajectories["sgf"].poses  # type: ignore[attr-defined]
    assert ate(estimate, second.gt) < ate(second.odometry, second.gt)


def test_one_map_match_alone_does_not_place_the_run(mapped: Path) -> None:
    sgf_map = load_map(mapped)
    world, frames = second_session()
    # a short drive past a single marking of the map
    first_sgf = min(k for k in world.sgfs if k >= 40)
    short = [f for f in frames if f.index <= first_sgf + 5]
    run = run_stages(
        world,
        IcpLoopClosing(IcpLoopParams()),
        GtsamLmBackend(LmParams(prior_map=str(mapped), save_map=False)),
        OracleAssociation(world, by="instance", prior=sgf_map.descriptors()),
        frames=short,
    )
    metrics = run.context.metrics  # type: ignore[attr-defined]
    assert metrics["loops"]["rejected"]["map_unconfirmed"] == 1
    assert metrics["backend"]["map_factors"] == 0
    assert metrics["backend"]["prior_map"]["anchored"] is False
    # the run stays in its own odometry frame
    odometry = world.odometry[[f.index for f in short]]
    np.testing.assert_allclose(run.context.trajectories["sgf"].poses, odometry, atol=1e-6)  # type: ignore[attr-defined]
