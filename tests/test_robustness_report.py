"""sgf-report on the robustness suite: each perturbed run against the preset robot's, breaking points, figure."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from sgf_experiments import CONF as EXPERIMENTS_CONF
from sgf_experiments.report import write_report
from sgf_experiments.robustness import perturbed_runs, robustness_table, split_tag
from sgf_experiments.runs import find_runs

from sgf_pipeline import load_plugins
from sgf_pipeline.config import config_dir


def _run(
    root: Path,
    tag: str,
    sequence: str,
    seed: int,
    ate: tuple[float, float],
    found: int = 10,
    closed: int = 10,
    false: int = 0,
    pairs: int = 12,
) -> None:
    run = root / f"{tag.replace('/', '_')}_{sequence}_{seed}"
    run.mkdir(parents=True)
    metrics = {
        "status": "finished",
        "sequence": sequence,
        "ate_rmse_m": {"odometry": ate[0], "sgf": ate[1]},
        "sgf": {"detected": 9, "total": 10},
        "loops": {
            "pairs_found": found,
            "pairs_total": pairs,
            "pairs_found_reverse": 0,
            "pairs_total_reverse": 0,
            "closed": closed,
            "closed_reverse": 0,
            "false_closed": false,
        },
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    config = {"dataset": {"name": sequence, "seed": seed, "scale": 0.3}, "run": {"tag": tag}}
    (run / "config.yaml").write_text(yaml.safe_dump(config))


@pytest.fixture
def suite(tmp_path: Path) -> Path:
    for seed in (201, 202):
        _run(tmp_path, "none/none", "campus_large_loop", seed, (100.0, 1.0))
        _run(tmp_path, "none/none", "campus_reverse_slope", seed, (20.0, 0.5))
    # heading bias: mild within the bound on both; strong over it on the large loop (seed 202)
    for seed in (201, 202):
        _run(tmp_path, "heading_bias_left/mild", "campus_large_loop", seed, (200.0, 1.4))  # 1.5 x 1.0 bounds it
        _run(tmp_path, "heading_bias_left/mild", "campus_reverse_slope", seed, (40.0, 1.9))  # 5 % of 40 = 2.0
    _run(tmp_path, "heading_bias_left/strong", "campus_large_loop", 201, (300.0, 14.0))  # 5 % of 300 = 15
    _run(tmp_path, "heading_bias_left/strong", "campus_large_loop", 202, (300.0, 16.0))  # over 15
    for seed in (201, 202):
        _run(tmp_path, "heading_bias_left/strong", "campus_reverse_slope", seed, (60.0, 0.6))
    # clutter: a false loop at mild severity on the reverse + slope; too few pairs closed on the large loop
    for seed in (201, 202):
        _run(tmp_path, "clutter/mild", "campus_reverse_slope", seed, (20.0, 0.5), false=int(seed == 202))
        _run(tmp_path, "clutter/mild", "campus_large_loop", seed, (100.0, 1.0), found=10, closed=8)
    (tmp_path / "unrelated").mkdir()  # a run of another tag is not part of the suite
    _run(tmp_path / "unrelated", "my experiment", "campus_large_loop", 201, (100.0, 1.0))
    return tmp_path


def test_the_tags_of_the_suite() -> None:
    assert split_tag("camera_low/strong") == ("camera_low", "strong")
    assert split_tag("none/none") == ("none", "none")
    assert split_tag("camera_low/extreme") is None and split_tag("my experiment") is None and split_tag(None) is None


def test_each_run_is_held_to_the_larger_bound(suite: Path) -> None:
    runs = {(r.variant, r.severity, r.sequence, r.seed): r for r in perturbed_runs(find_runs(suite))}
    assert len(runs) == 16  # the unrelated run is left out
    mild = runs[("heading_bias_left", "mild", "campus_large_loop", 201)]
    assert mild.reference_ate == 1.0 and mild.bound == pytest.approx(10.0)  # 5 % of 200 m beats 1.5 x 1.0 m
    assert mild.ratio == pytest.approx(0.007) and mild.within and mild.holds
    slope = runs[("heading_bias_left", "mild", "campus_reverse_slope", 201)]
    assert slope.bound == pytest.approx(2.0) and slope.within
    over = runs[("heading_bias_left", "strong", "campus_large_loop", 202)]
    assert over.bound == pytest.approx(15.0) and not over.within and not over.holds
    few = runs[("clutter", "mild", "campus_large_loop", 201)]
    assert few.within and few.closed_share == pytest.approx(0.8) and not few.holds  # 8 of 10 found pairs: < 85 %
    false = runs[("clutter", "mild", "campus_reverse_slope", 202)]
    assert false.within and false.false_closed == 1 and not false.holds


def test_the_table_gives_each_variant_its_breaking_point(suite: Path) -> None:
    table = robustness_table(find_runs(suite))
    rows = {(r["variant"], r["severity"], r["sequence"]): r for r in table["rows"]}
    strong = rows[("heading_bias_left", "strong", "campus_large_loop")]
    assert strong["within"] == 1 and strong["runs"] == 2 and not strong["holds"]
    assert strong["ratio"][0] == pytest.approx((14.0 / 300.0 + 16.0 / 300.0) / 2)
    assert rows[("clutter", "mild", "campus_reverse_slope")]["false_closed"] == 1
    assert table["breaking_point"] == {
        "heading_bias_left": {"campus_large_loop": "strong", "campus_reverse_slope": "beyond strong"},
        "clutter": {"campus_large_loop": "mild", "campus_reverse_slope": "mild"},
    }
    assert table["rows"][0]["variant"] == "none"  # the preset robot's rows first


def test_a_variant_whose_strong_severity_was_not_run_has_no_breaking_point_beyond_strong(suite: Path) -> None:
    mild_only = [r for r in find_runs(suite) if not str(r.config.get("run", {}).get("tag")).endswith("/strong")]
    assert robustness_table(mild_only)["breaking_point"]["heading_bias_left"] == {
        "campus_large_loop": "beyond mild (strong not run)",
        "campus_reverse_slope": "beyond mild (strong not run)",
    }


def test_sgf_report_writes_the_robustness_section_and_figure(suite: Path, tmp_path_factory) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path_factory.mktemp("report")
    tables = write_report(suite, out)
    assert tables["robustness_figure"] == "robustness.png"
    assert (out / "robustness.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = (out / "report.md").read_text()
    assert "## Robustness: perturbed robots and worlds" in report
    assert "| heading_bias_left | strong | campus_large_loop | 201, 202 | 5.0 ± 0.5 % | 1/2 | 0 | 20/20 " in report
    assert "| clutter | mild | mild |" in report  # breaking points, one column per sequence
    saved = json.loads((out / "tables.json").read_text())
    assert saved["robustness"]["breaking_point"]["clutter"]["campus_large_loop"] == "mild"


def test_the_suite_config_names_its_seeds_and_perturbations() -> None:
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        evaluation = compose("config", overrides=["+experiment=robustness"], return_hydra_config=True)
        development = compose("config", overrides=["+experiment=robustness_development"], return_hydra_config=True)
        params = evaluation.hydra.sweeper.params
        assert params["dataset.seed"] == "301,302,303"
        assert development.hydra.sweeper.params["dataset.seed"] == "0,1,2,201,202,203"
        names = params["+perturbation"].split(",")
        on_disk = sorted(p.stem for p in (EXPERIMENTS_CONF / "perturbation").glob("*.yaml"))
        assert sorted(names) == on_disk  # every perturbation is in the suite
        registry = load_plugins().registry
        for name in names:
            cfg = compose("config", overrides=["+experiment=robustness", f"+perturbation={name}"])
            parts = split_tag(cfg.run.tag)
            assert parts is not None and name in (f"{parts[0]}_{parts[1]}", "none"), name
            assert cfg.dataset.scale == 0.3
            # every world parameter it sets is one the campus takes, within its bounds
            node = OmegaConf.to_container(cfg.dataset, resolve=True)
            assert isinstance(node, dict)
            registry.get("dataset", node.pop("name")).params_model.model_validate(node)
