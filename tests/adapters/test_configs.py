"""conf/dataset/*.yaml list every parameter of their variant with its default; sgf_eval.yaml matches its model."""

from __future__ import annotations

import pytest
import yaml

from sgf_pipeline.cli.eval import EvalOptions
from sgf_pipeline.config import config_dir
from sgf_pipeline.registry import load_plugins

VARIANTS = ["folder", "kitti", "euroc", "rosbag"]


@pytest.mark.parametrize("variant", VARIANTS)
def test_dataset_config_lists_every_default(variant: str):
    path = config_dir() / "dataset" / f"{variant}.yaml"
    text = path.read_text()
    assert text.startswith("# "), "a config file starts with a comment saying what it is"
    node = yaml.safe_load(text)
    assert node.pop("name") == variant
    params = load_plugins().registry.get("dataset", variant).params_model
    defaults = {name: field.get_default(call_default_factory=True) for name, field in params.model_fields.items()}
    assert node == defaults
    for name, field in params.model_fields.items():
        assert field.description, f"{variant}.{name} has no description"


def test_eval_config_matches_its_model():
    node = yaml.safe_load((config_dir() / "sgf_eval.yaml").read_text())
    node.pop("defaults")
    node.pop("hydra")
    options = EvalOptions.model_validate({**node, "reference": "a.tum", "estimate": "b.tum"})
    assert options.align == "se3" and options.max_time_diff == 0.01 and options.rpe.delta_unit == "frames"
    assert set(node) | {"reference", "estimate"} == set(EvalOptions.model_fields)
