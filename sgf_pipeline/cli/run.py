"""``sgf-run``: run the pipeline on a dataset (Hydra app; ``-m`` for sweeps)."""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

from sgf_pipeline.cli.common import console, friendly_errors, raise_terminated
from sgf_pipeline.config import config_dir
from sgf_pipeline.outputs import taken_back
from sgf_pipeline.runner import Pipeline


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
            f"{_fmt(loops['closed'], 'd')} ({_fmt(loops['closed_reverse'], 'd')}), {_fmt(loops['false_closed'], 'd')}"
            + (f"; {len(back)} taken back" if (back := taken_back(loops)) else ""),
        ),
        ("frames processed / seen", f"{timing.get('frames', '-')}/{timing.get('dataset_frames', '-')}"),
        ("frames/s, real-time factor", f"{_fmt(timing.get('fps'), '.1f')}, {_fmt(timing.get('realtime_factor'))}"),
        ("peak RSS (MiB)", _fmt(metrics.get("peak_rss_mb"), ".0f")),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"  {k:<{width}}  {v}" for k, v in rows]
    names = ("metrics.json", "report.md", "trajectory.png", "loops.csv")
    files = [run_dir / n for n in names if (run_dir / n).exists()]
    lines.append("")
    lines += [f"  {f}" for f in files]
    return "\n".join([f"sgf-run: {metrics.get('sequence', '')}", *lines])


def _parallel_sweep(hydra_cfg: Any) -> bool:
    """Whether this job runs in a multirun whose launcher runs jobs in parallel."""
    from hydra.types import RunMode

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
