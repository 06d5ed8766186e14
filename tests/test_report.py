"""sgf-report: aggregation of run directories into the paper's tables."""

from __future__ import annotations

import csv
import json
import statistics
from pathlib import Path

import pytest
import yaml
from sgf_experiments.report import build_tables, write_report
from sgf_experiments.runs import find_runs
from sgf_testing import run_cli

from sgf_pipeline.errors import DataError


def fake_run(
    root: Path,
    name: str,
    sequence: str,
    seed: int,
    ipm: str,
    ate: tuple[float, float],
    counts: dict,
    ipm_params: dict | None = None,
) -> None:
    run = root / name
    run.mkdir(parents=True)
    metrics = {
        "status": "finished",
        "sequence": sequence,
        "ate_rmse_m": {"odometry": ate[0], "sgf": ate[1]},
        "sgf": {
            "detected": counts["detected"],
            "total": counts["total"],
            "purity": counts.get("purity"),
            "own_group_ranked_first": counts.get("ranked"),
        },
        "loops": {
            "pairs_found": counts["found"],
            "pairs_total": counts["pairs"],
            "pairs_found_reverse": 1,
            "pairs_total_reverse": 1,
            "closed": counts["closed"],
            "closed_reverse": 1,
            "false_closed": 0,
        },
        "timing": {"fps": 20.0, "realtime_factor": 2.0, "stages": {"ipm": {"variant": ipm, "mean_ms": 1.5}}},
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    config = {
        "pipeline": ["dataset", "ipm"],
        "dataset": {"name": sequence, "seed": seed},
        "ipm": {"name": ipm, **(ipm_params or {})},
        "run": {"progress": False},
    }
    (run / "config.yaml").write_text(yaml.safe_dump(config))


def test_tables_aggregate_over_seeds_and_split_by_swept_keys(tmp_path: Path):
    ates = {("mc", 0): (100.0, 5.0), ("mc", 1): (120.0, 7.0), ("plain", 0): (100.0, 20.0), ("plain", 1): (120.0, 30.0)}
    for i, ((ipm, seed), ate) in enumerate(ates.items()):
        counts = {"detected": 9 + seed, "total": 10, "found": 3, "pairs": 4, "closed": 2 + seed}
        counts["purity"] = 0.9 - 0.1 * seed if ipm == "mc" else None
        counts["ranked"] = {"decisions": 4 + seed, "share": 0.5 if seed == 0 else 0.8}
        fake_run(tmp_path, f"{i}_run", "campus_reverse_slope", seed, ipm, ate, counts)
    tables = write_report(tmp_path)
    assert tables["swept"] == ["ipm.name"]
    rows = {r["variant"]: r for r in tables["rows"]}
    mc = rows["ipm.name=mc"]
    assert mc["runs"] == 2 and mc["seeds"] == ["0", "1"]
    assert mc["ate_sgf"][0] == pytest.approx(6.0)
    assert mc["ate_sgf"][1] == pytest.approx(statistics.stdev([5.0, 7.0]))
    assert (mc["detected"], mc["total"], mc["closed"]) == (19, 20, 5)
    assert rows["ipm.name=plain"]["ate_sgf"][0] == pytest.approx(25.0)
    report = (tmp_path / "report.md").read_text()
    assert "## Table 4: MC-IPM vs plain IPM" in report
    assert "| campus_reverse_slope | 6.00 ± 1.41 | 25.00 ± 7.07 | 14.384 | 67.625 |" in report
    assert "| paper: odometry + SGF | 14.384 |" in report
    assert "19/20" in report and "6/8 (2/2)" in report
    # purity per seed in seed order; eq. 10's ranking pooled over seeds: 2 of 4 and 4 of 5
    assert mc["purity"] == [pytest.approx(0.9), pytest.approx(0.8)] and mc["own_group_ranked_first"] == (6, 9)
    assert "| 0 | 0.900, 0.800 | 6/9 |" in report and "| 0 | -, - | 6/9 |" in report
    rows_csv = list(csv.DictReader((tmp_path / "runs.csv").open()))
    assert len(rows_csv) == 4 and rows_csv[0]["ipm.name"] in {"mc", "plain"}
    assert sorted(r["purity"] for r in rows_csv if r["ipm.name"] == "mc") == ["0.8", "0.9"]
    assert (tmp_path / "timing.png").stat().st_size > 1000
    assert json.loads((tmp_path / "tables.json").read_text())["swept"] == ["ipm.name"]


def test_a_variant_is_named_by_its_name_not_by_the_parameters_it_brings(tmp_path: Path):
    counts = {"detected": 9, "total": 10, "found": 3, "pairs": 4, "closed": 2}
    mc = {"queue_size": 50, "pitch_threshold": 0.025}
    fake_run(tmp_path / "a", "mc", "campus_delivery", 0, "mc", (10.0, 1.0), counts, mc)
    fake_run(tmp_path / "a", "plain", "campus_delivery", 0, "plain", (10.0, 2.0), counts)
    tables = build_tables(find_runs(tmp_path / "a"))
    assert tables["swept"] == ["ipm.name"]
    assert sorted(r["variant"] for r in tables["rows"]) == ["ipm.name=mc", "ipm.name=plain"]
    # a parameter swept within one variant still names it
    fake_run(tmp_path / "b", "mc50", "campus_delivery", 0, "mc", (10.0, 1.0), counts, mc)
    fake_run(tmp_path / "b", "mc30", "campus_delivery", 0, "mc", (10.0, 1.5), counts, {**mc, "queue_size": 30})
    fake_run(tmp_path / "b", "plain", "campus_delivery", 0, "plain", (10.0, 2.0), counts)
    tables = build_tables(find_runs(tmp_path / "b"))
    assert tables["swept"] == ["ipm.name", "ipm.queue_size"]
    assert sorted(r["variant"] for r in tables["rows"]) == [
        "ipm.name=mc, ipm.queue_size=30",
        "ipm.name=mc, ipm.queue_size=50",
        "ipm.name=plain, ipm.queue_size=None",
    ]


def test_report_cli_takes_a_positional_directory(tmp_path: Path):
    fake_run(
        tmp_path,
        "r",
        "campus_delivery",
        0,
        "mc",
        (70.0, 10.0),
        {"detected": 20, "total": 23, "found": 1, "pairs": 1, "closed": 1},
    )
    result = run_cli("sgf-report", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "| odometry + SGF | 10.00 |" in result.stdout
    assert (tmp_path / "report.md").exists()


def test_report_errors_are_clear(tmp_path: Path):
    with pytest.raises(DataError, match="does not exist"):
        find_runs(tmp_path / "nope")
    with pytest.raises(DataError, match=r"no metrics\.json below"):
        find_runs(tmp_path)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "metrics.json").write_text("{truncated")
    with pytest.raises(DataError, match="not valid JSON"):
        find_runs(tmp_path)
    result = run_cli("sgf-report", str(tmp_path / "nope"))
    assert result.returncode == 2 and "does not exist" in result.stderr


def test_single_run_needs_no_sweep(tmp_path: Path):
    fake_run(
        tmp_path,
        "r",
        "campus_delivery",
        0,
        "mc",
        (70.0, 10.0),
        {"detected": 20, "total": 23, "found": 1, "pairs": 1, "closed": 1},
    )
    tables = build_tables(find_runs(tmp_path))
    assert tables["swept"] == [] and tables["rows"][0]["variant"] == "default"


def test_figures_are_linked_relative_to_the_report(tmp_path: Path):
    runs = tmp_path / "sweep"
    counts = {"detected": 1, "total": 1, "found": 1, "pairs": 1, "closed": 1}
    fake_run(runs, "0_run", "campus_delivery", 0, "mc", (5.0, 1.0), counts)
    (runs / "0_run" / "trajectory.png").write_bytes(b"\x89PNG")
    write_report(runs, tmp_path / "elsewhere")
    report = (tmp_path / "elsewhere" / "report.md").read_text()
    assert "![Trajectories: 0_run](../sweep/0_run/trajectory.png)" in report


def test_the_report_of_a_single_run_goes_beside_its_own_report(tmp_path: Path):
    counts = {"detected": 20, "total": 23, "found": 1, "pairs": 1, "closed": 1}
    fake_run(tmp_path, "r", "campus_delivery", 0, "mc", (70.0, 10.0), counts)
    run = tmp_path / "r"
    own = "# campus_delivery\n\n| stage | ms per frame |\n| ipm | 1.5 |\n"  # the run's report with its timings
    (run / "report.md").write_text(own)
    result = run_cli("sgf-report", str(run))
    assert result.returncode == 0, result.stderr
    assert (run / "report.md").read_text() == own  # untouched
    aggregate = (run / "tables.md").read_text()
    assert "| odometry + SGF | 10.00 |" in aggregate and result.stdout.startswith(aggregate)
    assert f"wrote {run / 'tables.md'}, {run / 'runs.csv'}, {run / 'tables.json'}" in result.stdout
    assert json.loads((run / "tables.json").read_text())["rows"][0]["variant"] == "default"
    # the directory of many runs holds no run of its own: its aggregate is report.md, rewritten on each call
    assert run_cli("sgf-report", f"dir={tmp_path}").returncode == 0
    first = (tmp_path / "report.md").read_text()
    assert "| odometry + SGF | 10.00 |" in first and not (tmp_path / "tables.md").exists()
    assert run_cli("sgf-report", str(tmp_path), f"out={run}").returncode == 0  # out= a run directory: beside too
    assert (run / "report.md").read_text() == own
