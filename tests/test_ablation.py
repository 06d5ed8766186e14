"""The paper as printed, each extension off alone, and sgf-report's leave-one-out table."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from sgf_experiments import CONF as EXPERIMENTS_CONF
from sgf_experiments.ablation import ablation_name, ablation_table
from sgf_experiments.report import write_report
from sgf_testing import run_cli

from sgf_pipeline import load_plugins
from sgf_pipeline.config import config_dir

NAMES = sorted(p.stem for p in (EXPERIMENTS_CONF / "ablate").glob("*.yaml"))
STAGES = ("ipm", "saliency", "detector", "descriptor", "association", "loop", "odometry_scale", "backend")


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for key, value in node.items():
            out |= _leaves(value, f"{prefix}{key}.")
        return out
    return {prefix[:-1]: node}


def _stages(*overrides: str) -> dict[str, Any]:
    cfg = compose("config", overrides=list(overrides))
    node = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(node, dict)
    return {k: node[k] for k in STAGES}


def test_each_ablation_turns_off_what_it_names_and_the_paper_turns_off_them_all() -> None:
    registry = load_plugins().registry
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        default = _leaves(_stages())
        changed: dict[str, dict[str, Any]] = {}
        for name in NAMES:
            cfg = compose("config", overrides=[f"+ablate={name}"])
            assert cfg.run.tag == f"ablate/{name}" and ablation_name(cfg.run.tag) == name
            stages = _stages(f"+ablate={name}")
            for kind, node in stages.items():  # every value is one the stage's parameters take
                params = dict(node)
                registry.get(kind, params.pop("name")).params_model.model_validate(params)
            leaves = _leaves(stages)
            changed[name] = {k: v for k, v in leaves.items() if default.get(k, object()) != v}
        assert changed.pop("none") == {}
        # each extension off changes the default pipeline, in a stage's parameters or in the variant chosen
        assert all(changed.values()), [n for n, c in changed.items() if not c]
        # the paper: every extension off at once, with the paper's own variants (SelfReformer*, MC-IPM)
        paper = changed.pop("paper")
        assert "saliency.name" not in paper and "ipm.name" not in paper
        assert default["saliency.name"] == "selfreformer" and default["ipm.name"] == "mc"
        for name, keys in changed.items():
            if name.startswith("saliency_") or name == "camera_heading_bias":  # the network kept; no camera at all
                continue
            for key, value in keys.items():
                if key.startswith("odometry_scale.") and key != "odometry_scale.name":
                    continue  # the variant's own parameters go with odometry_scale=none
                assert paper.get(key) == value, (name, key)
        assert paper["odometry_scale.name"] == "none"


def test_the_leave_one_out_experiment_sweeps_every_ablation_on_the_evaluation_seeds() -> None:
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=leave_one_out"], return_hydra_config=True)
        params = cfg.hydra.sweeper.params
        assert sorted(params["+ablate"].split(",")) == NAMES
        assert params["dataset.seed"] == "301,302,303"  # the robustness suite's evaluation seeds
        assert params["dataset"] == "campus_reverse_slope,campus_large_loop"
        paper = compose("config", overrides=["+experiment=paper"])
        assert (
            paper.run.tag == "ablate/paper"
            and paper.loop.consensus.min_support == 0
            and not paper.backend.heading_bias.enabled
        )


def _run(root: Path, name: str, sequence: str, seed: int, ate: float, closed: int = 8, false: int = 0) -> None:
    run = root / f"{name}_{sequence}_{seed}"
    run.mkdir(parents=True)
    metrics = {
        "status": "finished",
        "sequence": sequence,
        "ate_rmse_m": {"odometry": 20.0, "sgf": ate},
        "loops": {"pairs_found": 10, "pairs_total": 12, "closed": closed, "false_closed": false},
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    config = {"dataset": {"name": sequence, "seed": seed, "scale": 0.3}, "run": {"tag": f"ablate/{name}"}}
    (run / "config.yaml").write_text(yaml.safe_dump(config))


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    root = tmp_path / "sweep"
    for seed, wobble in ((201, -0.1), (202, 0.1)):  # the default's ATE: 1.0 +- 0.14 m over the two seeds
        _run(root, "none", "campus_reverse_slope", seed, 1.0 + wobble)
        _run(root, "idle", "campus_reverse_slope", seed, 1.05 - wobble)  # within the spread
        _run(root, "drifts", "campus_reverse_slope", seed, 1.5 + wobble)  # 0.5 m worse: beyond it
        _run(root, "scattered", "campus_reverse_slope", seed, 1.2 + 3 * wobble)  # 0.2 m worse, its own spread 0.42 m
        _run(root, "consensus", "campus_reverse_slope", seed, 1.0, false=int(seed == 202))
        _run(root, "final_pass", "campus_reverse_slope", seed, 1.0, closed=7)
        _run(root, "paper", "campus_reverse_slope", seed, 9.0, closed=3, false=2)
    return root


def test_an_extension_earns_its_place_by_a_false_loop_a_closed_pair_or_ate_beyond_the_spread(sweep: Path) -> None:
    from sgf_experiments.runs import find_runs

    table = ablation_table(find_runs(sweep))
    assert [r["name"] for r in table["rows"]] == [
        "none",
        "paper",
        "consensus",
        "drifts",
        "final_pass",
        "idle",
        "scattered",
    ]
    verdicts = table["verdicts"]
    assert verdicts["consensus"]["costs"] == {"campus_reverse_slope": ["1 false loop(s)"]}
    assert verdicts["final_pass"]["costs"] == {"campus_reverse_slope": ["2 closed pair(s)"]}
    assert verdicts["drifts"]["costs"] == {"campus_reverse_slope": ["0.50 m ATE"]}
    assert verdicts["scattered"]["costs"] == {"campus_reverse_slope": ["0.20 m ATE"]}  # the default's spread decides
    assert not verdicts["idle"]["earns_its_place"] and verdicts["idle"]["costs"] == {}
    assert verdicts["paper"]["earns_its_place"]  # the default beats the paper as printed
    (none,) = [r for r in table["rows"] if r["name"] == "none"]
    assert none["ratio"][0] == pytest.approx(0.05) and none["closed"] == 16 and none["closed_share"] == 0.8


def test_sgf_report_writes_the_leave_one_out_section(sweep: Path) -> None:
    write_report(sweep)
    report = (sweep / "report.md").read_text()
    assert "## What each extension buys" in report
    assert "| idle | campus_reverse_slope | 201, 202 | 1.05 ± 0.14 |" in report
    assert "cost nothing measurable on these runs: idle." in report
    assert json.loads((sweep / "tables.json").read_text())["ablation"]["verdicts"]["idle"]["earns_its_place"] is False
    assert "## Robustness" not in report  # ``ablate/none`` has the suite's tag form, but is no perturbed robot


def test_the_paper_as_printed_runs_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "paper"
    result = run_cli(
        "sgf-run",
        "+experiment=paper",
        "dataset=campus_reverse_slope",
        "run.max_frames=40",
        "run.plots=false",
        "saliency=classical",
        f"hydra.run.dir={out}",
    )
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "finished" and metrics["timing"]["dataset_frames"] == 40
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["run"]["tag"] == "ablate/paper" and saved["odometry_scale"]["name"] == "none"
    assert "odometry_yaw_bias" not in metrics["backend"]  # eq. 11 as printed: no heading bias estimated
