"""Scoring the loop stage's loops against the ground truth, from what the stage emits at the end of the run.

The stage decides without the truth; this module judges its accepted loops (truth errors, true or
false), counts the revisit pairs they close (Table 3), and builds the records of ``loops.csv``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.truth import RevisitPair, SequenceTruth
from sgf_plugins.loop.candidate import Candidate
from sgf_plugins.loop.params import EvaluationParams, IcpLoopParams
from sgf_plugins.shared.drift import pose_error
from sgf_plugins.shared.frame_log import FrameLog


def truth_error(c: Candidate, frames: FrameLog) -> tuple[float, float] | None:
    """How far (m, rad) an accepted constraint's relative pose is from the ground truth's (None: unknown)."""
    k = c.constraint
    start = c.map_truth if k.from_map else frames.ground_truth(k.frame_from)
    end = frames.ground_truth(k.frame_to)
    if start is None or end is None:
        return None
    truth = invert(start) @ end
    if k.marking is not None:  # where the loop puts its marking, seen from frame_from; no heading to judge
        centre = np.array([*k.marking, 0.0, 1.0])
        return float(np.linalg.norm((truth @ centre - k.relative @ centre)[:2])), 0.0
    x, y, yaw = pose_error(truth, k.relative)
    return math.hypot(x, y), abs(yaw)


def is_true(c: Candidate, error: tuple[float, float] | None, p: EvaluationParams) -> bool | None:
    """Whether an accepted constraint joins the same marking at the true relative pose (None: unknown).

    ``error`` is the constraint's :func:`truth_error`.
    """
    ids = c.constraint.instance_ids
    if ids[0] is not None and ids[1] is not None and ids[0] != ids[1]:
        return False
    if error is not None:
        return bool(error[0] <= p.truth_tolerance_xy and error[1] <= math.radians(p.truth_tolerance_yaw_deg))
    if ids[0] is not None and ids[1] is not None:
        return True
    return None


def loop_entry(c: Candidate, error: tuple[float, float] | None, true: bool | None, frames: FrameLog) -> dict[str, Any]:
    """One accepted loop as the run reports it (``artifacts['loops']``, ``loops.csv``)."""
    k = c.constraint
    x, y, yaw = xy_yaw(k.relative)
    return {
        "frame_from": k.frame_from,
        "frame_to": k.frame_to,
        "time_from": None if k.from_map else frames.get_time(k.frame_from),
        "time_to": frames.get_time(k.frame_to),
        "relative_xy_yaw": [x, y, yaw],
        "group_id": c.group_id,
        "reverse": k.reverse,
        "from_map": k.from_map,
        "position_only": k.position_only,
        "fitness": k.fitness,
        "inlier_ratio": k.inlier_ratio,
        "instance_ids": list(k.instance_ids),
        "truth_error_m": None if error is None else error[0],
        "truth_error_deg": None if error is None else math.degrees(error[1]),
        "true": None if true is None else bool(true),
    }


def closes(pair: RevisitPair, accepted: list[Candidate], truths: list[bool | None], truth: SequenceTruth) -> bool:
    """Whether an accepted, not false constraint joins the pair's two passes over its marking."""
    for c, t in zip(accepted, truths, strict=True):
        k = c.constraint
        if (
            not k.from_map
            and t is not False
            and k.instance_ids == (pair.instance_id, pair.instance_id)
            and pair.first == truth.drive_by(pair.instance_id, k.frame_from)
            and pair.second == truth.drive_by(pair.instance_id, k.frame_to)
        ):
            return True
    return False


def evaluate_loops(
    loops: dict[str, Any],
    accepted: list[Candidate],
    frames: FrameLog,
    truth: SequenceTruth | None,
    p: IcpLoopParams,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The stage's loop metrics with the ground truth's verdicts, and the records of ``loops.csv``.

    ``loops`` holds the stage's counts: ``false_closed`` joins them after ``accepted_map``, then
    ``closed`` and ``closed_reverse`` (with the sequence's truth).
    """
    errors = [truth_error(c, frames) for c in accepted]
    truths = [is_true(c, e, p.evaluation) for c, e in zip(accepted, errors, strict=True)]
    known = [t for t in truths if t is not None]
    out: dict[str, Any] = {}
    for key, value in loops.items():
        out[key] = value
        if key == "accepted_map":
            out["false_closed"] = sum(not t for t in known) if known else None
    if not accepted and (truth is not None or frames.has_truth()):
        out["false_closed"] = 0  # nothing accepted, and the truth to judge it by is known
    if truth is not None:
        closed = [r for r in truth.revisits if closes(r, accepted, truths, truth)]
        out["closed"] = len(closed)
        out["closed_reverse"] = sum(bool(r.reverse) for r in closed)
    records = [loop_entry(c, e, t, frames) for c, e, t in zip(accepted, errors, truths, strict=True)]
    return out, records
