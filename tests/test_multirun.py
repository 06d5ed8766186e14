"""Multirun sweeps with each launcher: one run directory per job, each with metrics and effective config."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
import yaml
from sgf_testing import run_cli

pytestmark = pytest.mark.slow

LAUNCHERS = {
    "basic": [],
    "joblib": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
    "ray": [
        "hydra/launcher=ray",
        "+hydra.launcher.ray.init.num_cpus=2",
        "+hydra.launcher.ray.init.include_dashboard=false",
    ],
    "submitit_local": ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10"],
}
MODULES = {
    "joblib": "hydra_plugins.hydra_joblib_launcher",
    "ray": "hydra_plugins.hydra_ray_launcher",
    "submitit_local": "hydra_plugins.hydra_submitit_launcher",
}


@pytest.mark.parametrize("launcher", list(LAUNCHERS))
def test_sweep_over_a_stage_parameter(launcher: str, toy_plugin_site: Path, tmp_path: Path):
    module = MODULES.get(launcher)
    if module and importlib.util.find_spec(module) is None:
        pytest.skip(f"the {launcher} launcher is not installed (pip install -e '.[sweeps]')")
    sweep = tmp_path / "sweep"
    # Ray's socket paths must stay under 107 bytes: a short temporary folder, removed afterwards.
    ray_tmp = tempfile.mkdtemp(prefix="sgfray", dir="/tmp")
    result = run_cli(
        "sgf-run",
        "-m",
        "pipeline=[dataset,enhance]",
        "dataset=toy_circle",
        "dataset.frames=12",
        "enhance=clahe",
        "enhance.clip_limit=1.0,3.0",
        "run.progress=false",
        f"hydra.sweep.dir={sweep}",
        *LAUNCHERS[launcher],
        env={"PYTHONPATH": str(toy_plugin_site), "RAY_TMPDIR": ray_tmp},
    )
    shutil.rmtree(ray_tmp, ignore_errors=True)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and (p / "metrics.json").exists())
    # a job's folder is named by its overrides alone (no job number): any sweep holding it finds it
    assert ["enhance.clip_limit=1.0" in j.name for j in jobs] == [True, False]
    assert ["enhance.clip_limit=3.0" in j.name for j in jobs] == [False, True]
    clip_limits = []
    for job in jobs:
        metrics = json.loads((job / "metrics.json").read_text())
        assert metrics["status"] == "finished"
        assert metrics["timing"]["frames"] == 12
        config = (job / "config.yaml").read_text()
        clip_limits += [float(line.split(":")[1]) for line in config.splitlines() if "clip_limit" in line]
        if launcher != "basic":
            assert "torch_threads: 1" in config
    assert clip_limits == [1.0, 3.0]


def _suite_slice(sweep: Path, *launcher: str, env: dict[str, str] | None = None):  # type: ignore[no-untyped-def]
    """Two jobs of the robustness suite (the preset robot and one perturbation), 40 frames each.

    The classical saliency keeps the jobs short: what is tested is the suite's sweep, not the network.
    """
    return run_cli(
        "sgf-run",
        "-m",
        "+experiment=robustness",
        "dataset=campus_reverse_slope",
        "+perturbation=none,clutter_strong",
        "dataset.seed=201",
        "run.max_frames=40",
        "run.plots=false",
        "saliency=classical",
        f"hydra.sweep.dir={sweep}",
        *launcher,
        env=env,
    )


def _check_suite(sweep: Path) -> None:
    jobs = sorted(p for p in sweep.iterdir() if (p / "metrics.json").exists())
    assert len(jobs) == 2
    tags = sorted(yaml.safe_load((j / "config.yaml").read_text())["run"]["tag"] for j in jobs)
    assert tags == ["clutter/strong", "none/none"]
    report = run_cli("sgf-report", str(sweep))
    assert report.returncode == 0, report.stderr[-2000:]
    table = json.loads((sweep / "tables.json").read_text())["robustness"]
    assert [(r["variant"], r["severity"], r["seeds"]) for r in table["rows"]] == [
        ("none", "none", ["201"]),
        ("clutter", "strong", ["201"]),
    ]
    assert (sweep / "robustness.png").exists()


def test_the_robustness_suite_runs_with_joblib(tmp_path: Path) -> None:
    sweep = tmp_path / "suite"
    result = _suite_slice(sweep)  # the experiment's own launcher: joblib, two jobs at once
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    _check_suite(sweep)


def test_the_robustness_suite_runs_on_a_ray_cluster(tmp_path: Path) -> None:
    if importlib.util.find_spec("hydra_plugins.hydra_ray_launcher") is None:
        pytest.skip("the ray launcher is not installed (pip install -e '.[sweeps]')")
    import socket
    import sys

    ray = str(Path(sys.executable).parent / "ray")
    ray_tmp = tempfile.mkdtemp(prefix="sgfray", dir="/tmp")  # socket paths must stay under 107 bytes
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {"RAY_TMPDIR": ray_tmp, "HOME": str(tmp_path)}
    head = [ray, "start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false"]
    started = subprocess.run(
        [*head, f"--temp-dir={ray_tmp}"], capture_output=True, text=True, env={**os.environ, **env}
    )
    try:
        assert started.returncode == 0, started.stdout[-2000:] + started.stderr[-2000:]
        sweep = tmp_path / "suite"
        # the launcher asks for an object store size, which ray refuses when it joins a running cluster: none
        launcher = (
            "hydra/launcher=ray",
            f"+hydra.launcher.ray.init.address=127.0.0.1:{port}",
            "+hydra.launcher.ray.init.object_store_memory=null",
        )
        result = _suite_slice(sweep, *launcher, env=env)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        _check_suite(sweep)
    finally:
        subprocess.run([ray, "stop", "--force"], capture_output=True, env={**os.environ, **env})
        shutil.rmtree(ray_tmp, ignore_errors=True)


def test_a_sweep_run_again_skips_its_finished_jobs(toy_plugin_site: Path, tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    args = [
        "sgf-run",
        "-m",
        "pipeline=[dataset,enhance]",
        "dataset=toy_circle",
        "dataset.frames=12",
        "enhance=clahe",
        "enhance.clip_limit=1.0,3.0",
        "run.progress=false",
        f"hydra.sweep.dir={sweep}",
    ]
    env = {"PYTHONPATH": str(toy_plugin_site)}
    first = run_cli(*args, env=env)
    assert first.returncode == 0, first.stderr[-3000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    stamps = [(j / "metrics.json").stat().st_mtime_ns for j in jobs]
    (jobs[1] / "metrics.json").unlink()  # as if the sweep had stopped during its second job
    (jobs[1] / "failure.json").write_text('{"status": "interrupted"}')
    again = run_cli(*args, "run.progress=true", env=env)  # a result-neutral option may differ
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("finished already; skipped") == 1
    assert (jobs[0] / "metrics.json").stat().st_mtime_ns == stamps[0]  # not run again
    assert json.loads((jobs[1] / "metrics.json").read_text())["status"] == "finished"
    assert not (jobs[1] / "failure.json").exists()  # the interrupted job ran again, in place
    # another sweep that holds one finished job, in another order, skips it and runs only the new one
    wider = run_cli(*[a.replace("1.0,3.0", "5.0,3.0") for a in args], env=env)
    assert wider.returncode == 0, wider.stderr[-3000:]
    assert wider.stdout.count("finished already; skipped") == 1
    assert len([p for p in sweep.iterdir() if (p / "metrics.json").exists()]) == 3
    other = run_cli(*args[:-1], "enhance.tiles=4", f"hydra.sweep.dir={sweep}", env=env)  # another config
    assert "skipped" not in other.stdout
