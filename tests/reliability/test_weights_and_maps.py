"""Weights and SGF map files from elsewhere: truncated, foreign or made for another setup give clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from backend_world import CALIBRATION, OracleAssociation, make_world

from sgf_pipeline import RunContext
from sgf_pipeline.errors import DataError
from sgf_pipeline.sgf_map import build_map, save_map


@pytest.fixture(scope="module")
def saved_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    world = make_world(seed=5, laps=1.0, reverse_lap=True)
    assoc = OracleAssociation(world)
    assignments = [a for f in world.frames for a in (assoc.assign(f).items if assoc.assign(f) else ())]
    poses = {f.index: f.odometry for f in world.frames}
    path = tmp_path_factory.mktemp("map") / "sgf_map.safetensors"
    save_map(path, build_map(assignments, poses, calibration=CALIBRATION, sequence="toy"))
    return path


def test_a_truncated_weights_file_is_refused_without_unpickling(tmp_path: Path) -> None:
    import torch
    from sgf_plugins.saliency.models import build_model
    from sgf_plugins.saliency.stages import U2NetPParams, U2NetPSaliency, default_architecture
    from sgf_plugins.saliency.weights import save_weights

    torch.manual_seed(0)
    arch = default_architecture("u2netp")
    whole = save_weights(build_model("u2netp", arch), tmp_path / "u2netp.safetensors", "u2netp", arch)
    data = whole.read_bytes()
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="not a readable safetensors"):
        U2NetPSaliency(U2NetPParams(weights=str(cut)))
    U2NetPSaliency(U2NetPParams(weights=str(whole)))  # the whole file loads


def test_a_map_of_another_descriptor_size_is_refused_before_the_first_frame(saved_map: Path) -> None:
    from sgf_plugins.sgf.association.stage import OnlineGroupsParams, OnlineSgfGroups

    stage = OnlineSgfGroups(OnlineGroupsParams(prior_map=str(saved_map)))
    context = RunContext(run_dir=None, calibration=CALIBRATION)
    context.artifacts["descriptor_shape"] = (20, 60)
    with pytest.raises(DataError, match=r"holds descriptors of N_r x N_s = \d+x\d+, this run makes 20x60"):
        stage.begin(context)


def test_a_map_seeds_the_association_with_anchored_groups(saved_map: Path) -> None:
    from sgf_plugins.sgf.association.stage import OnlineGroupsParams, OnlineSgfGroups

    from sgf_pipeline.sgf_map import load_map

    stage = OnlineSgfGroups(OnlineGroupsParams(prior_map=str(saved_map)))
    context = RunContext(run_dir=None, calibration=CALIBRATION)
    stage.begin(context)
    sgf_map = load_map(saved_map)
    assert len(stage.groups) == len(sgf_map.groups)
    group = stage.groups[0]
    view = sgf_map.groups[0].views[0]
    expected = view.pose[:2, :2] @ np.asarray(view.centroid)[:2] + view.pose[:2, 3]
    assert np.allclose(group.anchors[0], expected)
