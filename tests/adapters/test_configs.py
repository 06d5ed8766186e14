"""sgf_eval.yaml matches its model."""

from __future__ import annotations

import yaml

from sgf_pipeline.cli.eval import EvalOptions
from sgf_pipeline.config import config_dir

VARIANTS = ["folder", "kitti", "euroc", "rosbag"]


def test_eval_config_matches_its_model():
    node = yaml.safe_load((config_dir() / "sgf_eval.yaml").read_text())
    node.pop("defaults")
    node.pop("hydra")
    options = EvalOptions.model_validate({**node, "reference": "a.tum", "estimate": "b.tum"})
    assert options.align == "se3" and options.max_time_diff == 0.01 and options.rpe.delta_unit == "frames"
    assert set(node) | {"reference", "estimate"} == set(EvalOptions.model_fields)
