"""``sgf-run``: run the pipeline on a dataset (Hydra app; ``-m`` for sweeps)."""

from __future__ import annotations

import json
import logging
import signal
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, open_dict

from sgf_pipeline.cli.common import console, friendly_errors, raise_terminated
from sgf_pipeline.config import config_dir, plain_config
from sgf_pipeline.run_directory import RunDirectory
from sgf_pipeline.runner import Pipeline

log = logging.getLogger("sgf_pipeline")

#: Runner options that do not change a run's results: a sweep run again skips a finished job that differs only in them.
RESULT_NEUTRAL_OPTIONS = ("progress", "torch_threads", "overwrite", "cache", "cache_dir", "cache_max_gb")


def _fmt(value: Any, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)


def summary(metrics: dict[str, Any], run_dir: Path) -> str:
    """The short table printed at the end of a run."""
    ate = metrics["ate_rmse_m"]
    sgf = metrics["sgf"]
    loops = metrics["loops"]
    timing = metrics.get("timing", {})
    rows = [
        ("ATE odometry (m)", _fmt(ate["odometry"])),
        ("ATE odometry + SGF (m)", _fmt(ate["sgf"])),
        ("SGF detected", f"{_fmt(sgf['detected'], 'd')}/{_fmt(sgf['total'], 'd')}"),
        (
            "loop pairs found (rev.)",
            f"{_fmt(loops['pairs_found'], 'd')}/{_fmt(loops['pairs_total'], 'd')} "
            f"({_fmt(loops['pairs_found_reverse'], 'd')}/{_fmt(loops['pairs_total_reverse'], 'd')})",
        ),
        (
            "loops closed (rev.), false",
            f"{_fmt(loops['closed'], 'd')} ({_fmt(loops['closed_reverse'], 'd')}), {_fmt(loops['false_closed'], 'd')}",
        ),
        ("frames processed / seen", f"{timing.get('frames', '-')}/{timing.get('dataset_frames', '-')}"),
        ("frames/s, real-time factor", f"{_fmt(timing.get('fps'), '.1f')}, {_fmt(timing.get('realtime_factor'))}"),
        ("peak RSS (MiB)", _fmt(metrics.get("peak_rss_mb"), ".0f")),
    ]
    cache = metrics.get("cache")
    if cache:
        hits, total = len(cache["hits"]), len(cache["hits"]) + len(cache["misses"])
        unread = ", no image read" if cache["dataset_from_cache"] else ""
        rows.append(("stages from the cache", f"{hits} of {total}{unread}"))
    width = max(len(k) for k, _ in rows)
    lines = [f"  {k:<{width}}  {v}" for k, v in rows]
    names = ("metrics.json", "report.md", "trajectory.png", "loops.csv")
    files = [run_dir / n for n in names if (run_dir / n).exists()]
    lines.append("")
    lines += [f"  {f}" for f in files]
    return "\n".join([f"sgf-run: {metrics.get('sequence', '')}", *lines])


def _results_config(config: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(config)
    out["run"] = {k: v for k, v in dict(out.get("run") or {}).items() if k not in RESULT_NEUTRAL_OPTIONS}
    return out


def finished_job(run_dir: Path, cfg: DictConfig) -> dict[str, Any] | None:
    """The metrics of the run that already finished in ``run_dir`` with this configuration, else ``None``.

    A sweep run again with the same command finds its finished jobs so and skips them; a job whose
    directory holds another configuration's run is not skipped (the run directory then refuses it).
    """
    metrics, saved = run_dir / "metrics.json", run_dir / "config.yaml"
    if not (metrics.is_file() and saved.is_file()):
        return None
    try:
        same = _results_config(yaml.safe_load(saved.read_text())) == _results_config(plain_config(cfg))
        return json.loads(metrics.read_text()) if same else None
    except (OSError, ValueError, yaml.YAMLError):
        return None


def _parallel_sweep(hydra_cfg: Any) -> bool:
    """Whether this job runs in a multirun whose launcher runs jobs in parallel."""
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return False
    target = str(hydra_cfg.launcher.get("_target_", ""))
    return "BasicLauncher" not in target


@hydra.main(config_path=str(config_dir()), config_name="config", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> float | None:
    """Build the configured pipeline, stream the dataset through it and write the run directory."""
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    if _parallel_sweep(hydra_cfg) and cfg.get("run", {}).get("torch_threads") is None:
        # Parallel jobs on one machine: torch's intra-op threads would fight over the cores.
        with open_dict(cfg):
            cfg.run.torch_threads = 1
    if hydra_cfg.mode == RunMode.MULTIRUN and not cfg.get("run", {}).get("overwrite"):
        done = finished_job(run_dir, cfg)
        if done is not None:  # the same sweep run again: this job has finished already
            log.info("%s holds this job's finished run; skipped", run_dir)
            print(f"sgf-run: {run_dir} finished already; skipped (run.overwrite=true runs it again)", flush=True)
            value = done.get("ate_rmse_m", {}).get("sgf")
            return float(value) if value is not None else None
        if not (run_dir / "metrics.json").exists() and RunDirectory(run_dir, overwrite=True).interrupted_files():
            log.warning("%s holds this job's run that did not finish; the sweep run again replaces it", run_dir)
            with open_dict(cfg):
                cfg.run.overwrite = True
    pipeline = Pipeline.from_config(cfg, run_dir=run_dir)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, raise_terminated)
    metrics = pipeline.run()
    print(summary(metrics, run_dir), flush=True)
    value = metrics["ate_rmse_m"]["sgf"]
    return float(value) if value is not None else None


#: The ``sgf-run`` console script.
main = console(app)

if __name__ == "__main__":
    main()
