"""Aggregate run directories into the paper's tables (Tables 1-4), CSV and figures."""

from __future__ import annotations

import csv
import io
import math
import os
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from sgf_experiments.ablation import ablation_name, ablation_table, render_ablation
from sgf_experiments.paper import PAPER_TABLE2, PAPER_TABLE3, PAPER_TABLE4, SEQUENCE_ORDER
from sgf_experiments.robustness import plot_robustness, render_robustness, robustness_table
from sgf_experiments.runs import METRIC_LOOP_KEYS, RunRecord, find_runs, flatten, swept_keys, value_at
from sgf_pipeline.io import atomic_path, atomic_write_json, atomic_write_text


def _mean_std(values: list[float]) -> tuple[float, float] | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if not vals:
        return None
    mean = sum(vals) / len(vals)
    std = math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1)) if len(vals) > 1 else 0.0
    return mean, std


def _fmt_ms(stat: tuple[float, float] | None, n: int, digits: int = 2) -> str:
    if stat is None:
        return "-"
    return f"{stat[0]:.{digits}f} ± {stat[1]:.{digits}f}" if n > 1 else f"{stat[0]:.{digits}f}"


def _sum(runs: list[RunRecord], *path: str) -> int | None:
    values = [value_at(r.metrics, *path) for r in runs]
    return None if any(v is None for v in values) else int(sum(values))


def _purities(runs: list[RunRecord]) -> list[float | None]:
    """Each run's SGF group purity, in seed order (None where a run has none)."""
    ordered = sorted(runs, key=lambda r: str(r.seed))
    return [value_at(r.metrics, "sgf", "purity") for r in ordered]


def _ranked_first(runs: list[RunRecord]) -> tuple[int, int] | None:
    """Decisions where the association ranked the own marking's group first, and all such decisions, over the runs."""
    found = [value_at(r.metrics, "sgf", "own_group_ranked_first") for r in runs]
    known = [f for f in found if isinstance(f, dict) and f.get("decisions")]
    if not known:
        return None
    return sum(round(f["share"] * f["decisions"]) for f in known), sum(int(f["decisions"]) for f in known)


def _variant_label(run: RunRecord, keys: list[str]) -> str:
    flat = flatten(run.config)
    return ", ".join(f"{k}={flat.get(k)}" for k in keys if k != "dataset.name") or "default"


def _ordered(sequences: Iterable[str]) -> list[str]:
    seqs = set(sequences)
    return [s for s in SEQUENCE_ORDER if s in seqs] + sorted(seqs - set(SEQUENCE_ORDER))


def build_tables(runs: list[RunRecord]) -> dict[str, Any]:
    """The paper's tables as data: per variant and sequence, mean/std over seeds and sums of counts."""
    keys = [k for k in swept_keys(runs) if k != "dataset.name"]
    groups: dict[tuple[str, str], list[RunRecord]] = defaultdict(list)
    for run in runs:
        groups[(_variant_label(run, keys), run.sequence)].append(run)
    rows = []
    for (variant, sequence), members in sorted(groups.items()):
        ate_odo = _mean_std([value_at(r.metrics, "ate_rmse_m", "odometry") for r in members])
        ate_sgf = _mean_std([value_at(r.metrics, "ate_rmse_m", "sgf") for r in members])
        fps = _mean_std([value_at(r.metrics, "timing", "fps") for r in members])
        rtf = _mean_std([value_at(r.metrics, "timing", "realtime_factor") for r in members])
        rows.append(
            {
                "variant": variant,
                "sequence": sequence,
                "runs": len(members),
                "seeds": sorted({str(r.seed) for r in members}),
                "ate_odometry": ate_odo,
                "ate_sgf": ate_sgf,
                "detected": _sum(members, "sgf", "detected"),
                "total": _sum(members, "sgf", "total"),
                "pairs_found": _sum(members, "loops", "pairs_found"),
                "pairs_total": _sum(members, "loops", "pairs_total"),
                "pairs_found_reverse": _sum(members, "loops", "pairs_found_reverse"),
                "pairs_total_reverse": _sum(members, "loops", "pairs_total_reverse"),
                "closed": _sum(members, "loops", "closed"),
                "closed_reverse": _sum(members, "loops", "closed_reverse"),
                "false_closed": _sum(members, "loops", "false_closed"),
                "purity": _purities(members),
                "own_group_ranked_first": _ranked_first(members),
                "fps": fps,
                "realtime_factor": rtf,
            }
        )
    return {"swept": keys, "rows": rows}


def _num(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _ratio(a: int | None, b: int | None) -> str:
    return "-" if a is None or b is None else f"{a}/{b}"


def render_markdown(runs: list[RunRecord], tables: dict[str, Any], figures: dict[str, str]) -> str:
    """report.md with the paper's table layouts and its numbers beside the measured ones."""
    rows = tables["rows"]
    variants = sorted({r["variant"] for r in rows})
    out = [f"# sgf-report: {len(runs)} run(s)", ""]
    if tables.get("robustness"):
        out += render_robustness(tables["robustness"], tables.get("robustness_figure"))
    if tables.get("ablation"):
        out += render_ablation(tables["ablation"])
    if tables["swept"]:
        out += ["Swept: " + ", ".join(f"`{k}`" for k in tables["swept"]), ""]
    out += ["Values are mean ± standard deviation over seeds; counts are summed over seeds.", ""]

    out += ["## Table 2: absolute trajectory error (m, SE(3)-aligned)", ""]
    for variant in variants:
        vrows = {r["sequence"]: r for r in rows if r["variant"] == variant}
        seqs = _ordered(vrows)
        if len(variants) > 1:
            out += [f"**{variant}**", ""]
        out += ["| method | " + " | ".join(seqs) + " |", "|---" * (len(seqs) + 1) + "|"]
        for label, key in (("odometry", "ate_odometry"), ("odometry + SGF", "ate_sgf")):
            cells = [_fmt_ms(vrows[s][key], vrows[s]["runs"]) for s in seqs]
            out.append(f"| {label} | " + " | ".join(cells) + " |")
        for label, col in (("paper: odometry", 0), ("paper: odometry + SGF", 2)):
            cells = [_num(PAPER_TABLE2.get(s, (None, None, None))[col]) for s in seqs]
            out.append(f"| {label} | " + " | ".join(cells) + " |")
        out.append("")

    out += ["## Table 3: SGF detection, loop pairs found and loops closed", ""]
    header = ["variant", "sequence", "runs", "detection", "find loop pairs (rev.)", "loops closed (rev.)"]
    extra = ["false loops", "group purity per seed", "own group ranked first", "paper"]
    out += ["| " + " | ".join([*header, *extra]) + " |", "|---" * (len(header) + len(extra)) + "|"]
    for r in sorted(rows, key=lambda r: (r["variant"], _ordered([r["sequence"]]))):
        paper3 = PAPER_TABLE3.get(r["sequence"])
        reverse = _ratio(r["pairs_found_reverse"], r["pairs_total_reverse"])
        pairs = f"{_ratio(r['pairs_found'], r['pairs_total'])} ({reverse})"
        closed = f"{_num(r['closed'])} ({_num(r['closed_reverse'])})"
        cells = [
            r["variant"],
            r["sequence"],
            str(r["runs"]),
            _ratio(r["detected"], r["total"]),
            pairs,
            closed,
            _num(r["false_closed"]),
            ", ".join(_num(v) for v in r["purity"]),
            "-" if r["own_group_ranked_first"] is None else _ratio(*r["own_group_ranked_first"]),
            " / ".join(paper3) if paper3 else "-",
        ]
        out.append("| " + " | ".join(cells) + " |")
    out.append("")

    ipm_key = next((k for k in tables["swept"] if k == "ipm.name"), None)
    if ipm_key:
        out += ["## Table 4: MC-IPM vs plain IPM (ATE of odometry + SGF, m)", ""]
        seqs = _ordered({r["sequence"] for r in rows})
        out += [
            "| sequence | " + " | ".join(variants) + " | paper MC-IPM | paper IPM |",
            "|---" * (len(variants) + 3) + "|",
        ]
        for s in seqs:
            cells = []
            for v in variants:
                match = [r for r in rows if r["variant"] == v and r["sequence"] == s]
                cells.append(_fmt_ms(match[0]["ate_sgf"], match[0]["runs"]) if match else "-")
            p = PAPER_TABLE4.get(s)
            out.append(f"| {s} | " + " | ".join(cells) + f" | {p[0] if p else '-'} | {p[1] if p else '-'} |")
        out.append("")

    out += ["## Speed", "", "| variant | sequence | frames/s | real-time factor |", "|---|---|---|---|"]
    for r in rows:
        out.append(
            f"| {r['variant']} | {r['sequence']} | {_fmt_ms(r['fps'], r['runs'], 1)} "
            f"| {_fmt_ms(r['realtime_factor'], r['runs'])} |"
        )
    out.append("")
    if figures:
        out += ["## Figures", ""]
        for title, rel in figures.items():
            out += [f"### {title}", "", f"![{title}]({rel})", ""]
    out += ["## Runs", "", "| run | sequence | seed | ATE odometry | ATE SGF |", "|---|---|---|---|---|"]
    for run in runs:
        ate = run.metrics.get("ate_rmse_m", {})
        fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
        out.append(
            f"| {run.path.name} | {run.sequence} | {run.seed} | {fmt(ate.get('odometry'))} | {fmt(ate.get('sgf'))} |"
        )
    return "\n".join(out) + "\n"


def runs_csv(runs: list[RunRecord]) -> str:
    """One CSV row per run with the headline metrics and the swept config keys."""
    keys = swept_keys(runs)
    fields = [
        "run",
        "sequence",
        "seed",
        *keys,
        "ate_odometry",
        "ate_sgf",
        "detected",
        "total",
        *METRIC_LOOP_KEYS,
        "purity",
        "fps",
        "realtime_factor",
        "peak_rss_mb",
    ]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    for run in runs:
        flat = flatten(run.config)
        m = run.metrics
        writer.writerow(
            {
                "run": str(run.path),
                "sequence": run.sequence,
                "seed": run.seed,
                **{k: flat.get(k) for k in keys},
                "ate_odometry": value_at(m, "ate_rmse_m", "odometry"),
                "ate_sgf": value_at(m, "ate_rmse_m", "sgf"),
                "detected": value_at(m, "sgf", "detected"),
                "total": value_at(m, "sgf", "total"),
                **{k: value_at(m, "loops", k) for k in METRIC_LOOP_KEYS},
                "purity": value_at(m, "sgf", "purity"),
                "fps": value_at(m, "timing", "fps"),
                "realtime_factor": value_at(m, "timing", "realtime_factor"),
                "peak_rss_mb": m.get("peak_rss_mb"),
            }
        )
    return buf.getvalue()


def plot_timing(path: Path, runs: list[RunRecord]) -> None:
    """Bar chart of mean per-stage milliseconds per frame, averaged over runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per_stage: dict[str, list[float]] = defaultdict(list)
    for run in runs:
        for stage, row in (value_at(run.metrics, "timing", "stages") or {}).items():
            if row.get("mean_ms") is not None:
                per_stage[f"{stage}\n{row.get('variant', '')}"].append(float(row["mean_ms"]))
    if not per_stage:
        return
    labels = list(per_stage)
    means = [sum(v) / len(v) for v in per_stage.values()]
    fig, ax = plt.subplots(figsize=(max(5.0, 1.1 * len(labels)), 3.6), dpi=110)
    bars = ax.bar(range(len(labels)), means, color="tab:blue")
    ax.bar_label(bars, labels=[f"{m:.1f}" for m in means], fontsize=8)
    ax.set_xticks(range(len(labels)), labels, fontsize=8)
    ax.set_ylabel("ms per processed frame")
    ax.set_title("Per-stage time (mean over runs)")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _link(target: Path, out: Path) -> str:
    """A link from ``out``/report.md to ``target``: relative (the folder can move), else absolute."""
    try:
        return os.path.relpath(target.resolve(), out.resolve()).replace(os.sep, "/")
    except ValueError:  # another drive (Windows)
        return str(target.resolve())


#: The aggregate report's name: ``report.md``, or beside a run's own ``report.md`` (in its directory) this one.
REPORT_FILE, REPORT_BESIDE_RUN = "report.md", "tables.md"


def report_path(out_dir: str | Path) -> Path:
    """Where the aggregate report goes in ``out_dir``: never over the ``report.md`` of a run written there."""
    out = Path(out_dir)
    return out / (REPORT_BESIDE_RUN if (out / "metrics.json").exists() else REPORT_FILE)


def write_report(root: str | Path, out_dir: str | Path | None = None) -> dict[str, Any]:
    """Read every run below ``root`` and write the report (:func:`report_path`), runs.csv, tables.json and figures."""
    runs = find_runs(root)
    out = Path(out_dir) if out_dir is not None else Path(root)
    out.mkdir(parents=True, exist_ok=True)
    tables = build_tables(runs)
    # a leave-one-out tag (``ablate/none``) has the suite's form: its runs are no perturbed robot
    robustness = robustness_table([r for r in runs if ablation_name(r.config.get("run", {}).get("tag")) is None])
    if robustness["rows"]:
        tables["robustness"] = robustness
        if plot_robustness(out / "robustness.png", robustness):
            tables["robustness_figure"] = "robustness.png"
    ablation = ablation_table(runs)
    if ablation["rows"]:
        tables["ablation"] = ablation
    suite = bool(robustness["rows"] or ablation["rows"])
    figures: dict[str, str] = {}
    plot_timing(out / "timing.png", runs)
    if (out / "timing.png").exists():
        figures["Per-stage timing"] = "timing.png"
    for run in runs if not suite else ():  # a suite's hundreds of runs: their figures stay in their runs
        for name, title in (
            ("trajectory.png", "Trajectories"),
            ("sgf_frames.png", "Selected SGFs and groups"),
            ("ipm_comparison.png", "MC-IPM vs IPM"),
        ):
            if (run.path / name).exists():
                figures[f"{title}: {run.path.name}"] = _link(run.path / name, out)
    atomic_write_text(report_path(out), render_markdown(runs, tables, figures))
    atomic_write_text(out / "runs.csv", runs_csv(runs))
    atomic_write_json(out / "tables.json", tables)
    return tables
