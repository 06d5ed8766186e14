"""Multirun sweeps with each launcher: one run directory per job, each with metrics and effective config."""

from __future__ import annotations

import importlib.util
import json
import shutil
import tempfile
from pathlib import Path

import pytest
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
    assert [j.name.split("_")[0] for j in jobs] == ["0", "1"]
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
