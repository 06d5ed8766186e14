"""What the loop stage decided on each match (``loop_candidates.csv``), and its counts of refusals."""

from __future__ import annotations

from typing import Any

from sgf_pipeline.sgf_map import MapDescriptor
from sgf_pipeline.types import GroupAssignment, LoopConstraint
from sgf_plugins.loop.candidate import GateReading
from sgf_plugins.loop.outcomes import REFUSALS
from sgf_plugins.shared.frame_log import FrameLog


class DecisionLog:
    """One row per match the stage decided on, with the outcome; refusals counted by reason."""

    def __init__(self, frames: FrameLog) -> None:
        self.frames = frames
        self.counts = {"candidates": 0} | dict.fromkeys(REFUSALS, 0)
        self.rows: list[dict[str, Any]] = []  # grows as matches are decided: observers watch it

    def refuse(self, a: GroupAssignment, reason: str, gate: GateReading | None = None, detail: str = "") -> None:
        """Count a refused candidate under ``reason`` and log it (with what the gate saw, and why, when known)."""
        assert a.matched is not None
        self.counts[reason] += 1
        ends = (a.matched.sgf.frame_index, a.descriptor.sgf.frame_index)
        ids = (a.matched.sgf.instance_id, a.descriptor.sgf.instance_id)
        self.add(ends, ids, a.group_id, isinstance(a.matched, MapDescriptor), reason, gate, detail)

    def decided(
        self, k: LoopConstraint, group_id: int, outcome: str, gate: GateReading | None, detail: str = ""
    ) -> None:
        """Log a constraint's outcome (accepted, held for the map anchoring)."""
        self.add((k.frame_from, k.frame_to), k.instance_ids, group_id, k.from_map, outcome, gate, detail)

    def add(
        self,
        ends: tuple[int, int],
        ids: tuple[int | None, int | None],
        group_id: int,
        from_map: bool,
        outcome: str,
        gate: GateReading | None,
        detail: str = "",
    ) -> None:
        """One row of ``loop_candidates.csv``: a match the loop stage decided on, and the outcome."""
        self.rows.append(
            {
                "frame_from": ends[0],
                "frame_to": ends[1],
                "time_from": None if from_map else self.frames.get_time(ends[0]),
                "time_to": self.frames.get_time(ends[1]),
                "group_id": group_id,
                "from_map": from_map,
                "outcome": outcome,
                "instance_from": ids[0],
                "instance_to": ids[1],
                "anchored_distance": None if gate is None else round(gate.distance, 2),
                "gate_sigma_xy": None if gate is None else round(gate.sigma_xy, 3),
                "gate_chi2": None if gate is None else round(gate.chi2, 3),
                "detail": detail,
            }
        )
