"""The loop stage's files: ``loops.csv``, ``loop_candidates.csv`` and its section of ``report.md``."""

from __future__ import annotations

import csv
import io
import math
from typing import Any

from sgf_pipeline import RunContext
from sgf_pipeline.io import atomic_write_text

#: Columns of ``loops.csv``: one row per accepted loop, from the loop stage's ``artifacts["loops"]`` records.
LOOP_COLUMNS = (
    "frame_from",
    "frame_to",
    "time_from",
    "time_to",
    "reverse",
    "from_map",
    "position_only",
    "group_id",
    "x",
    "y",
    "yaw_deg",
    "fitness",
    "inlier_ratio",
    "instance_from",
    "instance_to",
    "truth_error_m",
    "truth_error_deg",
    "true",
)

#: Columns of ``loop_candidates.csv``: every match the loop stage decided on (``artifacts["loop_candidates"]``).
CANDIDATE_COLUMNS = (
    "frame_from",
    "frame_to",
    "time_from",
    "time_to",
    "group_id",
    "from_map",
    "outcome",
    "instance_from",
    "instance_to",
    "anchored_distance",
    "gate_sigma_xy",
    "gate_chi2",
    "detail",
)

#: Rows of the loop table in ``report.md`` (``loops.csv`` has them all).
REPORT_LOOP_ROWS = 30


def loop_row(loop: dict[str, Any]) -> dict[str, Any]:
    """A ``loops.csv`` row of an accepted loop's record: its pose in degrees, its two marking instances."""
    x, y, yaw = loop.get("relative_xy_yaw") or (None, None, None)
    ids = loop.get("instance_ids") or (None, None)
    return {
        **{k: loop.get(k) for k in LOOP_COLUMNS},
        "x": x,
        "y": y,
        "yaw_deg": None if yaw is None else math.degrees(yaw),
        "instance_from": ids[0],
        "instance_to": ids[1],
    }


def render_loops_csv(loops: list[dict[str, Any]]) -> str:
    """``loops.csv``: the accepted loops, one per row (empty cells: unknown, e.g. no ground truth)."""
    return render_csv([loop_row(loop) for loop in loops], LOOP_COLUMNS)


def render_csv(rows: list[dict[str, Any]], columns: tuple[str, ...]) -> str:
    """CSV text of ``rows`` over ``columns``: empty cells for None (unknown), floats to 6 significant digits."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        cells = {k: row.get(k) for k in columns}
        writer.writerow({k: "" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for k, v in cells.items()})
    return out.getvalue()


def render_candidates_csv(candidates: list[dict[str, Any]]) -> str:
    """``loop_candidates.csv``: each match the loop stage decided on, and its outcome.

    The outcome is ``accepted`` or the test that refused it, named as in ``loops.rejected`` of
    ``metrics.json``; a map match held for confirmation is ``map_unconfirmed`` (and has a second
    row when it is confirmed later). A match that reached the gate also has what the gate saw:
    the travel since a loop last anchored its two frames (m), the predicted position's sigma (m)
    and the best fit's chi-square (3 dof; the gate passes up to ``chi2(loop.gate.probability)``).
    ``detail`` says more where a test has parts: what the best ICP fit missed, why a match was
    ambiguous, or how many agreeing neighbours each option of a consensus had against the number needed.
    """
    return render_csv(candidates, CANDIDATE_COLUMNS)


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _loop_table(loops: list[dict[str, Any]]) -> list[str]:
    lines = [f"## Accepted loops ({len(loops)}; all in `loops.csv`)", ""]
    if not loops:
        return [*lines, "None.", ""]
    lines += [
        "| frames | reverse | map | x, y (m), yaw (deg) | fitness | inliers | off the truth (m, deg) | true |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for loop in loops[:REPORT_LOOP_ROWS]:
        row = loop_row(loop)
        pose = "-" if row["x"] is None else f"{row['x']:.2f}, {row['y']:.2f}, {row['yaw_deg']:.1f}"
        off = "-" if row["truth_error_m"] is None else f"{row['truth_error_m']:.2f}, {row['truth_error_deg']:.1f}"
        if row.get("position_only"):  # a round marking's loop: its place, the turn left free
            pose += " (place only)"
            off = "-" if row["truth_error_m"] is None else f"{row['truth_error_m']:.2f} at its marking"
        lines.append(
            f"| {row['frame_from']} -> {row['frame_to']} | {'yes' if row['reverse'] else 'no'} "
            f"| {'yes' if row['from_map'] else 'no'} | {pose} | {_fmt(row['fitness'])} "
            f"| {_fmt(row['inlier_ratio'], 2)} | {off} | {_fmt(row['true'])} |"
        )
    if len(loops) > REPORT_LOOP_ROWS:
        lines.append(f"| ... and {len(loops) - REPORT_LOOP_ROWS} more | | | | | | | |")
    return [*lines, ""]


def write_loop_files(context: RunContext, loops: list[dict[str, Any]], candidates: list[dict[str, Any]]) -> None:
    """Write ``loops.csv`` and ``loop_candidates.csv`` (when the run writes files); add the report's loop section."""
    loops_path, candidates_path = context.path("loops.csv"), context.path("loop_candidates.csv")
    if loops_path is not None and candidates_path is not None:
        atomic_write_text(loops_path, render_loops_csv(loops))
        atomic_write_text(candidates_path, render_candidates_csv(candidates))
    context.report_sections.append(report_section(loops))


def report_section(accepted: list[dict[str, Any]]) -> str:
    """The accepted loops (the first ``REPORT_LOOP_ROWS``), as Markdown for ``report.md``."""
    return "\n".join(_loop_table(accepted))
