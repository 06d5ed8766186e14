"""The robustness table: runs of perturbed robots and worlds held to the preset robot's own runs.

A run of the robustness suite carries ``run.tag = "<variant>/<severity>"`` (``conf/perturbation``);
``none/none`` is the preset's own robot. Each perturbed run is held to the larger of two bounds,
``max(5 % of its odometry's ATE, 1.5 x the preset robot's ATE on the same sequence, seed and
length)``, so that a robot whose odometry is good is not punished by a ratio. A severity *holds*
for a variant when every run of it is within that bound, closes no false loop and closes at least
85 % of the revisit pairs it found; the *breaking point* is the first severity that does not.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from sgf_pipeline.io import atomic_path

#: The severities of a perturbation, in order; ``none`` is the preset's own robot.
SEVERITIES = ("none", "mild", "strong")
REFERENCE_TAG = "none/none"
#: ATE(odometry + SGF) may reach this share of the run's own odometry ATE...
ODOMETRY_SHARE = 0.05
#: ...or this multiple of the preset robot's ATE on the same sequence, seed and length, whichever is larger.
REFERENCE_FACTOR = 1.5
#: The share of the revisit pairs found that must be closed.
MIN_CLOSED_SHARE = 0.85


class RunRecord(Protocol):
    """What the table reads of a finished run (``sgf_experiments.runs.RunRecord``)."""

    metrics: dict[str, Any]
    config: dict[str, Any]

    @property
    def sequence(self) -> str:
        """The dataset variant the run used."""

    @property
    def seed(self) -> Any:
        """The dataset seed."""


@dataclass(frozen=True)
class PerturbedRun:
    """One run of the suite with the bound its ATE is held to."""

    variant: str
    severity: str
    sequence: str
    seed: Any
    scale: Any
    ate_odometry: float
    ate_sgf: float
    reference_ate: float | None  # the preset robot's ATE (odometry + SGF) on the same sequence, seed, length
    false_closed: int
    pairs_found: int
    pairs_total: int
    closed: int
    detected: int | None
    total: int | None

    @property
    def ratio(self) -> float:
        """ATE of odometry + SGF over the odometry's."""
        return self.ate_sgf / self.ate_odometry if self.ate_odometry > 0 else math.inf

    @property
    def bound(self) -> float:
        """The larger of the two bounds (only the odometry's share when the reference run is missing)."""
        own = ODOMETRY_SHARE * self.ate_odometry
        return own if self.reference_ate is None else max(own, REFERENCE_FACTOR * self.reference_ate)

    @property
    def within(self) -> bool:
        """ATE within the bound."""
        return self.ate_sgf <= self.bound

    @property
    def closed_share(self) -> float | None:
        """Revisit pairs closed over those found (None when the route has no revisit pair)."""
        if self.pairs_total == 0:
            return None
        return self.closed / self.pairs_found if self.pairs_found else 0.0

    @property
    def holds(self) -> bool:
        """Within the bound, no false loop, and at least 85 % of the found pairs closed."""
        share = self.closed_share
        return self.within and self.false_closed == 0 and (share is None or share >= MIN_CLOSED_SHARE)


def split_tag(tag: Any) -> tuple[str, str] | None:
    """``(variant, severity)`` of a ``run.tag`` of the suite, None for any other tag."""
    if not isinstance(tag, str) or tag.count("/") != 1:
        return None
    variant, severity = tag.split("/")
    return (variant, severity) if variant and severity in SEVERITIES else None


def metric(metrics: dict[str, Any], *path: str) -> Any:
    """The value at a path of nested keys of metrics.json; None where a key is missing."""
    node: Any = metrics
    for key in path:
        node = node.get(key) if isinstance(node, dict) else None
    return node


def perturbed_runs(runs: Iterable[RunRecord]) -> list[PerturbedRun]:
    """The suite's runs (those tagged ``<variant>/<severity>`` with both ATEs), each paired with its reference."""
    tagged = []
    for run in runs:
        parts = split_tag(run.config.get("run", {}).get("tag"))
        ate_odo = metric(run.metrics, "ate_rmse_m", "odometry")
        ate_sgf = metric(run.metrics, "ate_rmse_m", "sgf")
        if parts is None or ate_odo is None or ate_sgf is None:
            continue
        scale = run.config.get("dataset", {}).get("scale")
        tagged.append((parts, run, float(ate_odo), float(ate_sgf), scale))
    references = {
        (run.sequence, str(run.seed), str(scale)): ate_sgf
        for (variant, _), run, _, ate_sgf, scale in tagged
        if variant == "none"
    }
    out = []
    for (variant, severity), run, ate_odo, ate_sgf, scale in tagged:
        loops = run.metrics.get("loops") or {}
        sgf = run.metrics.get("sgf") or {}
        out.append(
            PerturbedRun(
                variant=variant,
                severity=severity,
                sequence=run.sequence,
                seed=run.seed,
                scale=scale,
                ate_odometry=ate_odo,
                ate_sgf=ate_sgf,
                reference_ate=references.get((run.sequence, str(run.seed), str(scale))),
                false_closed=int(loops.get("false_closed") or 0),
                pairs_found=int(loops.get("pairs_found") or 0),
                pairs_total=int(loops.get("pairs_total") or 0),
                closed=int(loops.get("closed") or 0),
                detected=sgf.get("detected"),
                total=sgf.get("total"),
            )
        )
    return out


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value; NaN for none)."""
    if not values:
        return math.nan, math.nan
    mean = sum(values) / len(values)
    var = sum((v - mean) ** 2 for v in values) / (len(values) - 1) if len(values) > 1 else 0.0
    return mean, math.sqrt(var)


def robustness_table(runs: Iterable[RunRecord]) -> dict[str, Any]:
    """Rows per variant, severity and sequence over seeds, and each variant's breaking point per sequence."""
    members: dict[tuple[str, str, str], list[PerturbedRun]] = defaultdict(list)
    for run in perturbed_runs(runs):
        members[(run.variant, run.severity, run.sequence)].append(run)
    rows: list[dict[str, Any]] = []
    for (variant, severity, sequence), group in sorted(
        members.items(), key=lambda item: (item[0][0] != "none", item[0][0], SEVERITIES.index(item[0][1]), item[0][2])
    ):
        found = sum(r.pairs_found for r in group)
        detected = [r.detected for r in group]
        totals = [r.total for r in group]
        rows.append(
            {
                "variant": variant,
                "severity": severity,
                "sequence": sequence,
                "seeds": sorted(str(r.seed) for r in group),
                "ratio": mean_std([r.ratio for r in group]),
                "ate_sgf": mean_std([r.ate_sgf for r in group]),
                "within": sum(r.within for r in group),
                "runs": len(group),
                "false_closed": sum(r.false_closed for r in group),
                "closed": sum(r.closed for r in group),
                "pairs_found": found,
                "detected": None if None in detected else sum(detected),
                "total": None if None in totals else sum(totals),
                "holds": all(r.holds for r in group),
            }
        )
    breaking: dict[str, dict[str, str]] = defaultdict(dict)
    for row in rows:
        if row["variant"] == "none":
            continue
        known = breaking[row["variant"]]
        current = known.get(row["sequence"])
        if not row["holds"] and (current is None or SEVERITIES.index(row["severity"]) < SEVERITIES.index(current)):
            known[row["sequence"]] = row["severity"]
    highest: dict[tuple[str, str], int] = {}
    for row in rows:
        if row["variant"] != "none":
            key = (row["variant"], row["sequence"])
            highest[key] = max(highest.get(key, 0), SEVERITIES.index(row["severity"]))
    for (variant, sequence), level in highest.items():
        unrun = f" ({SEVERITIES[level + 1]} not run)" if level + 1 < len(SEVERITIES) else ""
        breaking[variant].setdefault(sequence, f"beyond {SEVERITIES[level]}{unrun}")
    return {"rows": rows, "breaking_point": {k: dict(v) for k, v in breaking.items()}}


def render_robustness(table: dict[str, Any], figure: str | None) -> list[str]:
    """The robustness section of report.md."""
    out = [
        "## Robustness: perturbed robots and worlds",
        "",
        f"Each run is held to max({ODOMETRY_SHARE:.0%} of its odometry's ATE, {REFERENCE_FACTOR}x the preset "
        "robot's ATE on the same sequence, seed and length); a severity holds when every run is within it, "
        f"closes no false loop and closes at least {MIN_CLOSED_SHARE:.0%} of the revisit pairs it found.",
        "",
        "| variant | severity | sequence | seeds | ATE / odometry | within bound | false loops | closed / found "
        "| detection | holds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table["rows"]:
        mean, std = r["ratio"]
        detection = "-" if r["detected"] is None or r["total"] is None else f"{r['detected']}/{r['total']}"
        out.append(
            f"| {r['variant']} | {r['severity']} | {r['sequence']} | {', '.join(r['seeds'])} "
            f"| {100 * mean:.1f} ± {100 * std:.1f} % | {r['within']}/{r['runs']} | {r['false_closed']} "
            f"| {r['closed']}/{r['pairs_found']} | {detection} | {'yes' if r['holds'] else '**no**'} |"
        )
    out.append("")
    if table["breaking_point"]:
        sequences = sorted({s for v in table["breaking_point"].values() for s in v})
        out += [
            "Breaking point (the first severity that does not hold):",
            "",
            "| variant | " + " | ".join(sequences) + " |",
            "|---" * (len(sequences) + 1) + "|",
        ]
        for variant, points in sorted(table["breaking_point"].items()):
            out.append(f"| {variant} | " + " | ".join(points.get(s, "-") for s in sequences) + " |")
        out.append("")
    if figure:
        out += [f"![ATE ratio against severity per variant]({figure})", ""]
    return out


def plot_robustness(path: Path, table: dict[str, Any]) -> bool:
    """Draw the ATE ratio against severity: a panel per variant, a line per sequence, red crosses where it fails.

    False when there is nothing to draw.
    """
    rows = [r for r in table["rows"] if r["variant"] != "none"]
    if not rows:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reference = {r["sequence"]: r for r in table["rows"] if r["variant"] == "none"}
    variants = sorted({r["variant"] for r in rows})
    sequences = sorted({r["sequence"] for r in rows})
    cols = min(4, len(variants))
    nrows = math.ceil(len(variants) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.6 * nrows), dpi=100, squeeze=False, sharey=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, variant in zip(axes.ravel(), variants, strict=False):
        for k, sequence in enumerate(sequences):
            points = [reference[sequence]] if sequence in reference else []
            points += [r for r in rows if r["variant"] == variant and r["sequence"] == sequence]
            xs = [SEVERITIES.index(p["severity"]) for p in points]
            ys = [100.0 * p["ratio"][0] for p in points]
            ax.plot(xs, ys, "o-", color=colours[k % len(colours)], label=sequence, ms=4)
            missed = [(x, y) for x, y, p in zip(xs, ys, points, strict=True) if not p["holds"]]
            if missed:
                ax.plot(*zip(*missed, strict=True), "x", color="red", ms=9, mew=2)
        ax.set_title(variant, fontsize=9)
        ax.set_xticks(range(len(SEVERITIES)), SEVERITIES, fontsize=8)
        ax.set_yscale("log")
        ax.axhline(100.0 * ODOMETRY_SHARE, color="grey", lw=0.8, ls="--")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(variants) :]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("ATE / odometry (%)")
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(sequences), fontsize=8, frameon=False)
    fig.suptitle("Robustness: ATE against severity (red x: the severity does not hold; dashed: 5 % of odometry)")
    fig.tight_layout(rect=(0.0, 0.04, 1.0, 0.96))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return True
