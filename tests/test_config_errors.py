"""Every configuration and wiring error is raised before the first frame, with a message that says how to fix it."""

from __future__ import annotations

from pathlib import Path

import pytest
from toy_stages import ToyPlugin

from sgf_pipeline import ConfigError, Pipeline, PipelineGraphError, load_plugins
from sgf_pipeline.config import parse_config


@pytest.fixture(scope="module")
def plugins():
    return load_plugins(extra=[("toy", ToyPlugin())])


def build(plugins, **stages):
    cfg = {"pipeline": ["dataset", *stages], "dataset": {"name": "figure_eight"}, "run": {"progress": False}}
    cfg.update(stages)
    return Pipeline.from_config(cfg, plugins=plugins)


def test_unknown_variant_lists_the_registered_ones(plugins):
    with pytest.raises(ConfigError) as err:
        build(plugins, enhance={"name": "sharpen"})
    msg = str(err.value)
    assert "enhance: unknown variant 'sharpen'" in msg
    assert "Registered variants of 'enhance': clahe, none" in msg
    assert "enhance=<variant>" in msg


def test_unknown_kind_lists_the_registered_kinds(plugins):
    with pytest.raises(
        ConfigError, match=r"no plugin registers stages of kind 'teleport'.*Registered kinds: .*enhance"
    ):
        build(plugins, teleport={"name": "x"})


def test_missing_producer_names_the_input_and_the_fix(plugins):
    with pytest.raises(PipelineGraphError) as err:
        build(plugins, measure={"name": "brightness"})
    msg = str(err.value)
    assert "measure=brightness needs input 'image' (CameraImage) but no stage produces it" in msg
    assert "frame (dataset=figure_eight)" in msg
    assert "measure.rename.image=<output>" in msg


def test_two_producers_of_one_output(plugins):
    cfg = {
        "pipeline": ["dataset", "enhance", "backend"],
        "dataset": {"name": "figure_eight"},
        "enhance": {"name": "none"},
        "backend": {"name": "trust_odometry"},
    }
    cfg["pipeline"].append("other")
    cfg["other"] = {"name": "dup"}
    with pytest.raises(
        PipelineGraphError, match=r"output 'image' is produced by two stages, enhance=none and other=dup"
    ):
        Pipeline.from_config(cfg, plugins=plugins)


def test_cycle_names_the_stages(plugins):
    # gate=loops needs `consumed`, which consumer=strict makes from `gated`: a cycle.
    cfg = {
        "pipeline": ["dataset", "gate", "consumer"],
        "dataset": {"name": "figure_eight"},
        "gate": {"name": "loops"},
        "consumer": {"name": "strict"},
    }
    with pytest.raises(PipelineGraphError) as err:
        Pipeline.from_config(cfg, plugins=plugins)
    msg = str(err.value)
    assert "the stages form a cycle" in msg
    assert "gate" in msg and "consumer" in msg
    assert "Previous[...]" in msg


def test_type_mismatch_on_an_edge(plugins):
    with pytest.raises(PipelineGraphError) as err:
        build(plugins, enhance={"name": "none"}, bevuser={"name": "needs_bev", "rename": {"bev": "image"}})
    msg = str(err.value)
    assert "type mismatch on edge enhance=none -> bevuser=needs_bev" in msg
    assert "produces 'image' as CameraImage" in msg
    assert "expects 'bev' as Bev" in msg


def test_rename_of_an_unknown_input(plugins):
    with pytest.raises(PipelineGraphError, match=r"bevuser.rename names input\(s\) \['picture'\].*its inputs: bev"):
        build(plugins, bevuser={"name": "needs_bev", "rename": {"picture": "image"}})


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        ({"clip_limit": "lots"}, "enhance.clip_limit: Input should be a valid number"),
        ({"clip_limit": -1.0}, "enhance.clip_limit: Input should be greater than 0"),
        ({"tiles": 2.5}, "enhance.tiles: Input should be a valid integer"),
        (
            {"clip": 2.0},
            "enhance.clip: unknown parameter (parameters of this variant: clip_limit, tiles, max_brightness)",
        ),
    ],
)
def test_bad_parameter_names_group_key_and_expected_type(plugins, params, expected):
    with pytest.raises(ConfigError) as err:
        build(plugins, enhance={"name": "clahe", **params})
    msg = str(err.value)
    assert "invalid parameters for enhance=clahe" in msg
    assert expected in msg
    if "unknown" not in expected:
        assert "expected float" in msg or "expected int" in msg


def test_target_key_is_refused_anywhere_in_a_stage_node(plugins):
    with pytest.raises(
        ConfigError, match=r"enhance\._target_: `_target_` is refused. Variants are chosen by registered name"
    ):
        build(plugins, enhance={"name": "none", "_target_": "os.system"})
    with pytest.raises(ConfigError, match=r"enhance\.nested\._target_"):
        build(plugins, enhance={"name": "clahe", "nested": {"_target_": "builtins.eval"}})


def test_run_options_are_validated():
    with pytest.raises(ConfigError, match=r"run.keyframe_distance: Input should be greater than or equal to 0"):
        parse_config({"pipeline": ["dataset"], "dataset": {"name": "x"}, "run": {"keyframe_distance": -1}})
    with pytest.raises(ConfigError, match=r"run.progres: unknown parameter"):
        parse_config({"pipeline": ["dataset"], "dataset": {"name": "x"}, "run": {"progres": False}})


def test_pipeline_list_problems():
    with pytest.raises(ConfigError, match="no `pipeline` list"):
        parse_config({"dataset": {"name": "x"}})
    with pytest.raises(
        ConfigError, match=r"ipm: listed in `pipeline` but has no config node; choose a variant with `ipm=<variant>`"
    ):
        parse_config({"pipeline": ["dataset", "ipm"], "dataset": {"name": "x"}})
    with pytest.raises(ConfigError, match="lists a stage kind twice"):
        parse_config({"pipeline": ["dataset", "dataset"], "dataset": {"name": "x"}})
    with pytest.raises(ConfigError, match=r"ipm: the config node needs a `name`"):
        parse_config({"pipeline": ["dataset", "ipm"], "dataset": {"name": "x"}, "ipm": {"queue": 3}})
    with pytest.raises(ConfigError, match="not a finite number"):
        parse_config({"pipeline": ["dataset"], "dataset": {"name": "x", "scale": float("nan")}})


def test_a_pipeline_needs_one_dataset(plugins):
    cfg = {"pipeline": ["enhance"], "enhance": {"name": "none"}}
    with pytest.raises(PipelineGraphError, match="exactly one dataset stage, got 0"):
        Pipeline.from_config(cfg, plugins=plugins)


def test_a_finished_run_is_not_overwritten(plugins, tmp_path: Path):
    cfg = {"pipeline": ["dataset"], "dataset": {"name": "figure_eight", "frames": 3}, "run": {"progress": False}}
    Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins).run()
    before = (tmp_path / "metrics.json").read_bytes()
    with pytest.raises(ConfigError, match=r"already holds a finished run.*run.overwrite=true"):
        Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins)
    assert (tmp_path / "metrics.json").read_bytes() == before
    cfg["run"]["overwrite"] = True
    Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins).run()
