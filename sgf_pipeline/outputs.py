"""The run directory: metrics.json, trajectories, loops, effective config, plot and report."""

from __future__ import annotations

import logging
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sgf_pipeline.errors import StageError
from sgf_pipeline.evaluation import aligned_positions, ate_rmse
from sgf_pipeline.io import atomic_path, atomic_write_json, atomic_write_text
from sgf_pipeline.run_info import RunView, peak_rss_mb
from sgf_pipeline.trajectory import Trajectory, write_tum

log = logging.getLogger("sgf_pipeline")

#: Fields every metrics.json has, null when the run cannot know them.
METRIC_SKELETON: dict[str, Any] = {
    "ate_rmse_m": {"odometry": None, "sgf": None},
    "sgf": {"detected": None, "total": None},
    "loops": {
        "pairs_found": None,
        "pairs_total": None,
        "pairs_found_reverse": None,
        "pairs_total_reverse": None,
        "closed": None,
        "closed_reverse": None,
        "false_closed": None,
    },
}


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """A new dict: ``extra`` merged into ``base`` key by key; nested dicts are copied, never shared."""
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict):
            out[key] = _merge(out[key] if isinstance(out.get(key), dict) else {}, value)
        else:
            out[key] = value
    return out


def collect_metrics(run: RunView, trajectories: dict[str, Trajectory]) -> dict[str, Any]:
    """Merge the skeleton, ATE, the stages' metrics and the observers' reports."""
    metrics: dict[str, Any] = {
        "status": "finished",
        "sequence": run.info.sequence,
        "stages": {n.kind: n.name for n in run.info.stages},
    }
    metrics = _merge(metrics, METRIC_SKELETON)
    gt = trajectories.get("gt")
    if gt is not None and len(gt) >= 3:
        for name in ("odometry", "sgf"):
            est = trajectories.get(name)
            if est is not None and len(est) >= 3:
                try:
                    metrics["ate_rmse_m"][name] = ate_rmse(gt, est, "se3", run.options.ate_max_time_diff)
                except Exception as exc:
                    log.warning("ATE of %s not computed: %s", name, exc)
                    metrics.setdefault("warnings", []).append(f"ATE of {name} not computed: {exc}")
    metrics = _merge(metrics, run.context.metrics)
    metrics["runner"] = run.dropped
    for report in run.hooks.sgf_report_metrics(run=run.info):
        if report:
            metrics = _merge(metrics, report)
    metrics["peak_rss_mb"] = round(peak_rss_mb(), 1)
    return metrics


def write_run(run: RunView, trajectories: dict[str, Trajectory], metrics: dict[str, Any]) -> None:
    """Write every file of the run directory atomically."""
    run_dir = run.run_dir
    assert run_dir is not None
    run_dir.mkdir(parents=True, exist_ok=True)
    for name, trajectory in trajectories.items():
        write_tum(run_dir / f"trajectory_{name}.tum", trajectory)
    if run.effective_config is not None:
        atomic_write_text(run_dir / "config.yaml", yaml.safe_dump(run.effective_config, sort_keys=False))
    if run.options.plots:
        plot_trajectories(run_dir / "trajectory.png", trajectories, metrics, run.context.artifacts.get("loops"))
        atomic_write_text(run_dir / "report.md", render_report(metrics, run.context.report_sections))
    atomic_write_json(run_dir / "metrics.json", metrics)


def link_figures(run_dir: Path) -> None:
    """Add the figures the observers drew at the end of the run (the PNGs beside the plot) to report.md."""
    report = run_dir / "report.md"
    figures = sorted(p.name for p in run_dir.glob("*.png") if p.name != "trajectory.png")
    if report.is_file() and figures:
        section = "\n".join(f"![{name[:-4]}]({name})\n" for name in figures)
        atomic_write_text(report, report.read_text().rstrip("\n") + "\n\n## Figures\n\n" + section)


def write_failure(run: RunView, status: str, exc: BaseException) -> None:
    """Record a failed or interrupted run, keeping whatever the run directory already holds.

    ``failure.json`` names the error (and the stage and frame of a stage error); the trajectories
    so far are written as ``trajectory_<name>.partial.tum``: odometry and ground truth of the
    processed frames, and any trajectory a stage published before the failure.
    """
    run_dir = run.run_dir
    assert run_dir is not None
    info = run.info
    payload: dict[str, Any] = {
        "status": status,
        "error": f"{type(exc).__name__}: {exc}",
        "stage": None,
        "frame": None,
        "frames_seen": info.frames_seen,
        "frames_processed": info.frames_processed,
        "runner": run.dropped,
        "traceback": traceback.format_exception(type(exc), exc, exc.__traceback__)[-6:],
    }
    if isinstance(exc, StageError):
        payload["stage"] = f"{exc.kind}={exc.name}"
        payload["frame"] = exc.frame_index
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        partial = dict(run.context.trajectories)
        for name, trajectory in run.recorded.items():
            partial.setdefault(name, trajectory)
        for name, trajectory in partial.items():
            write_tum(run_dir / f"trajectory_{name}.partial.tum", trajectory)
        atomic_write_json(run_dir / "failure.json", payload)
    except Exception:  # pragma: no cover - best effort while failing
        log.exception("could not record the failed run")


LoopSegment = tuple[np.ndarray, np.ndarray, bool | None]


def loop_segments(loops: list[dict[str, Any]], trajectory: Trajectory) -> list[LoopSegment]:
    """Where each loop's two frames are on ``trajectory`` (nearest stamps), with the loop's truth flag.

    Loops against a prior map (no ``time_from`` in this run) are left out.
    """
    segments: list[LoopSegment] = []
    if len(trajectory) == 0:
        return segments
    stamps = trajectory.timestamps
    for loop in loops:
        times = (loop.get("time_from"), loop.get("time_to"))
        if times[0] is None or times[1] is None:
            continue
        ends = [trajectory.positions[int(np.argmin(np.abs(stamps - t))), :2] for t in times]
        segments.append((ends[0], ends[1], loop.get("true")))
    return segments


def plot_trajectories(
    path: Any, trajectories: dict[str, Trajectory], metrics: dict[str, Any], loops: list[dict[str, Any]] | None = None
) -> None:
    """Top-down plot of the ground truth, odometry and SGF trajectories (aligned as for ATE), with the loops.

    Each accepted loop joins its two frames on the ground truth (else on the SGF trajectory): green when
    it is true, magenta when false, grey when the run cannot tell.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    gt = trajectories.get("gt")
    styles = {"gt": ("k", "ground truth"), "odometry": ("tab:red", "odometry"), "sgf": ("tab:blue", "odometry + SGF")}
    for name, trajectory in trajectories.items():
        color, label = styles.get(name, (None, name))
        xy = aligned_positions(gt, trajectory) if gt is not None and name != "gt" else trajectory.positions
        ate = metrics.get("ate_rmse_m", {}).get(name)
        if ate is not None:
            label = f"{label} (ATE {ate:.2f} m)"
        ax.plot(xy[:, 0], xy[:, 1], color=color, lw=1.2, label=label)
    base = gt if gt is not None else trajectories.get("sgf")
    if loops and base is not None:
        kinds = {
            True: ("tab:green", "o", "loop"),
            False: ("magenta", "x", "false loop"),
            None: ("0.4", "o", "loop (truth unknown)"),
        }
        counts: dict[bool | None, int] = {}
        segments = loop_segments(loops, base)
        for _, _, true in segments:
            counts[true] = counts.get(true, 0) + 1
        labelled: set[bool | None] = set()
        for start, end, true in segments:
            color, marker, name = kinds[true]
            legend = None if true in labelled else f"{name}s ({counts[true]})"
            labelled.add(true)
            ax.plot([start[0], end[0]], [start[1], end[1]], color=color, lw=2.0, zorder=4)
            ax.plot(end[0], end[1], marker, color=color, ms=6, mfc="none", mew=1.5, zorder=5, label=legend)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    if trajectories:
        ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{metrics.get('sequence', '')}: trajectories (SE(3)-aligned to ground truth)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def render_report(metrics: dict[str, Any], sections: Sequence[str] = ()) -> str:
    """A short Markdown report of one run, then the ``sections`` the stages added (``RunContext.report_sections``)."""
    ate = metrics.get("ate_rmse_m", {})
    sgf = metrics.get("sgf", {})
    loops = metrics.get("loops", {})
    timing = metrics.get("timing", {})
    lines = [
        f"# Run report: {metrics.get('sequence', '')}",
        "",
        "Stages: " + ", ".join(f"`{k}={v}`" for k, v in metrics.get("stages", {}).items()),
        "",
        "| ATE RMSE (m) | odometry | odometry + SGF |",
        "|---|---|---|",
        f"| SE(3)-aligned | {_fmt(ate.get('odometry'))} | {_fmt(ate.get('sgf'))} |",
        "",
        "| detection | find loop pairs (rev.) | loops closed (rev.) | false loops |",
        "|---|---|---|---|",
        f"| {_fmt(sgf.get('detected'))}/{_fmt(sgf.get('total'))} "
        f"| {_fmt(loops.get('pairs_found'))}/{_fmt(loops.get('pairs_total'))} "
        f"({_fmt(loops.get('pairs_found_reverse'))}/{_fmt(loops.get('pairs_total_reverse'))}) "
        f"| {_fmt(loops.get('closed'))} ({_fmt(loops.get('closed_reverse'))}) | {_fmt(loops.get('false_closed'))} |",
        "",
        "| stage | mean ms | total s |",
        "|---|---|---|",
    ]
    for stage, row in timing.get("stages", {}).items():
        lines.append(f"| {stage} | {_fmt(row.get('mean_ms'), 2)} | {_fmt(row.get('total_s'), 2)} |")
    lines += [
        "",
        f"Frames: {timing.get('frames', '-')} processed of {timing.get('dataset_frames', '-')}; "
        f"{_fmt(timing.get('fps'), 1)} frames/s; real-time factor {_fmt(timing.get('realtime_factor'), 2)}; "
        f"peak RSS {_fmt(metrics.get('peak_rss_mb'), 0)} MiB.",
        "",
        "![trajectories](trajectory.png)",
        "",
    ]
    return "\n".join([*lines, *sections])
