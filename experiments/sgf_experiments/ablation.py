"""The leave-one-out table: what each extension of the default pipeline buys, and the paper as printed.

A run of ``+experiment=leave_one_out`` carries ``run.tag = "ablate/<name>"`` (``conf/ablate``):
``none`` is the default pipeline, ``paper`` every extension off, any other name the default with
that one extension off. Each row is compared with ``none`` on the same sequence and seeds. An
extension *earns its place* when turning it off costs, on some sequence, a false loop, a closed
revisit pair, or more ATE than the default's spread between seeds (its standard deviation; a row
whose own seeds scatter more is not excused by that); otherwise it does not measurably help on these runs.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from typing import Any

from sgf_experiments.robustness import RunRecord, mean_std, metric

#: The ``run.tag`` prefix of the leave-one-out runs, and the names of the two reference rows.
PREFIX = "ablate/"
DEFAULT = "none"
PAPER = "paper"


def ablation_name(tag: Any) -> str | None:
    """The extension a ``run.tag`` turns off (``none``, ``paper`` or a ``conf/ablate`` name); None otherwise."""
    if not isinstance(tag, str) or not tag.startswith(PREFIX) or "/" in tag[len(PREFIX) :]:
        return None
    return tag[len(PREFIX) :] or None


def ablation_table(runs: Iterable[RunRecord]) -> dict[str, Any]:
    """Rows per ablation and sequence over seeds, and each ablation's verdict against the default."""
    members: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for run in runs:
        name = ablation_name(run.config.get("run", {}).get("tag"))
        ate_odo, ate_sgf = metric(run.metrics, "ate_rmse_m", "odometry"), metric(run.metrics, "ate_rmse_m", "sgf")
        if name is None or ate_odo is None or ate_sgf is None:
            continue
        loops = run.metrics.get("loops") or {}
        members[(name, run.sequence)].append(
            {
                "seed": str(run.seed),
                "ate_odometry": float(ate_odo),
                "ate_sgf": float(ate_sgf),
                "false_closed": int(loops.get("false_closed") or 0),
                "closed": int(loops.get("closed") or 0),
                "pairs_found": int(loops.get("pairs_found") or 0),
            }
        )
    rows: list[dict[str, Any]] = []
    order = {DEFAULT: 0, PAPER: 1}
    for (name, sequence), group in sorted(members.items(), key=lambda i: (order.get(i[0][0], 2), i[0][0], i[0][1])):
        found = sum(r["pairs_found"] for r in group)
        closed = sum(r["closed"] for r in group)
        rows.append(
            {
                "name": name,
                "sequence": sequence,
                "seeds": sorted(r["seed"] for r in group),
                "ratio": mean_std([r["ate_sgf"] / r["ate_odometry"] for r in group if r["ate_odometry"] > 0]),
                "ate_sgf": mean_std([r["ate_sgf"] for r in group]),
                "false_closed": sum(r["false_closed"] for r in group),
                "closed": closed,
                "pairs_found": found,
                "closed_share": closed / found if found else None,
            }
        )
    default = {r["sequence"]: r for r in rows if r["name"] == DEFAULT}
    verdicts: dict[str, dict[str, Any]] = {}
    for row in rows:
        reference = default.get(row["sequence"])
        if row["name"] == DEFAULT or reference is None or row["seeds"] != reference["seeds"]:
            continue
        costs = []
        if row["false_closed"] > reference["false_closed"]:
            costs.append(f"{row['false_closed'] - reference['false_closed']} false loop(s)")
        if row["closed"] < reference["closed"]:
            costs.append(f"{reference['closed'] - row['closed']} closed pair(s)")
        spread = reference["ate_sgf"][1]  # the default's spread between seeds
        if row["ate_sgf"][0] - reference["ate_sgf"][0] > spread:
            costs.append(f"{row['ate_sgf'][0] - reference['ate_sgf'][0]:.2f} m ATE")
        verdict = verdicts.setdefault(row["name"], {"costs": {}})
        if costs:
            verdict["costs"][row["sequence"]] = costs
    for verdict in verdicts.values():
        verdict["earns_its_place"] = bool(verdict["costs"])
    return {"rows": rows, "verdicts": verdicts}


def render_ablation(table: dict[str, Any]) -> list[str]:
    """The leave-one-out section of report.md."""
    out = [
        "## What each extension buys: the default, the paper as printed, and each extension off alone",
        "",
        "An extension earns its place when turning it off costs, on some sequence, a false loop, a closed revisit "
        "pair, or more ATE than the spread between seeds; `paper` is every extension off.",
        "",
        "| off | sequence | seeds | ATE (m) | ATE / odometry | false loops | closed / found | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in table["rows"]:
        verdict = table["verdicts"].get(r["name"])
        if r["name"] == DEFAULT:
            text = "reference"
        elif verdict is None:
            text = "-"
        else:
            costs = verdict["costs"].get(r["sequence"])
            text = "costs " + ", ".join(costs) if costs else "no measurable cost"
        mean, std = r["ate_sgf"]
        ratio, ratio_std = r["ratio"]
        out.append(
            f"| {r['name']} | {r['sequence']} | {', '.join(r['seeds'])} | {mean:.2f} ± {std:.2f} "
            f"| {100 * ratio:.1f} ± {100 * ratio_std:.1f} % | {r['false_closed']} | {r['closed']}/{r['pairs_found']} "
            f"| {text} |"
        )
    out.append("")
    idle = sorted(n for n, v in table["verdicts"].items() if not v["earns_its_place"] and n != PAPER)
    if idle:
        out += ["Turned off alone, these cost nothing measurable on these runs: " + ", ".join(idle) + ".", ""]
    return out
