"""The final pass: at the end of the run, the drive-bys each final SGF group joins that no loop joins yet.

The association's split and merge at the end (with the estimate the loops made) put some revisits
into their marking's group only then; each such pair of drive-bys is matched once more against the
final estimate, and closed when ICP passes and the gate alone decides it (``final_pass.enabled``).
"""

from __future__ import annotations

from typing import Any

from sgf_pipeline.types import GroupAssignment, LoopConstraint, PoseEstimate
from sgf_plugins.loop import outcomes
from sgf_plugins.loop.anchoring import LoopAnchoring
from sgf_plugins.loop.candidate import match_closest
from sgf_plugins.loop.decisions import DecisionLog
from sgf_plugins.loop.gate import LoopGate
from sgf_plugins.loop.params import IcpLoopParams
from sgf_plugins.shared.frame_log import FrameLog


class FinalPass:
    """Match the final groups' unjoined drive-bys once more, against the final estimate."""

    def __init__(
        self, params: IcpLoopParams, frames: FrameLog, gate: LoopGate, anchoring: LoopAnchoring, log: DecisionLog
    ) -> None:
        self.p = params
        self.frames = frames
        self.gate = gate
        self.anchoring = anchoring
        self.log = log
        self.tried = 0  # matches the pass put through ICP and the gate

    def run(
        self, groups: list[Any], group_of: dict[tuple[int, int], int], estimate: PoseEstimate
    ) -> list[LoopConstraint]:
        """Close the drive-bys each final group joins that no loop joins yet, against the final estimate.

        The association's split and merge at the end (with the estimate the loops made) put some
        revisits into their marking's group only then: one seen before any loop, while the gate
        reached several look-alikes, may have joined another's group. For each group, each member
        and its closest earlier member (eq. 10) of another drive-by (``separation.min_distance``)
        are matched once more when no accepted loop between members of the group joins the two
        drive-bys (both ends within that distance of path); the match is closed when it passes
        ICP and the gate, and the gate alone decides it (:meth:`~sgf_plugins.loop.gate.LoopGate.decides`, with every SGF
        counted in its final group).
        """
        # The run is over: every SGF counts in its final group from now on (the look-alike test).
        self.gate.memory.regroup(group_of)
        out: list[LoopConstraint] = []
        for group in groups:
            if group.symmetric or len(group.members) < 2:
                continue
            members = sorted(
                (m for m in group.members if m.sgf.frame_index in self.frames), key=lambda m: m.sgf.frame_index
            )
            frames = {m.sgf.frame_index for m in members}
            for k, query in enumerate(members):
                j = query.sgf.frame_index
                earlier = [
                    m
                    for m in members[:k]
                    if self.gate.separated(m.sgf.frame_index, j) and not self.joined(m.sgf.frame_index, j, frames)
                ]
                if not earlier:
                    continue
                a = match_closest(GroupAssignment(query, group.group_id, False, 1.0, 0, 0.0, None, False), earlier)
                assert a.matched is not None
                self.tried += 1
                candidate = self.gate.evaluate(a, estimate)
                ends = (a.matched.sgf.frame_index, j)
                ids = (a.matched.sgf.instance_id, query.sgf.instance_id)
                if isinstance(candidate, str):
                    detail = "final pass" + (f": {self.gate.fitting.detail}" if candidate == outcomes.ICP else "")
                    self.log.add(ends, ids, group.group_id, False, candidate, self.gate.reading, detail)
                elif not self.gate.decides(a, candidate, estimate):
                    detail = f"final pass: {self.gate.refusal}"
                    self.log.add(ends, ids, group.group_id, False, outcomes.CONSENSUS, candidate.gate, detail)
                else:
                    self.anchoring.accepted.append(candidate)
                    self.log.add(ends, ids, group.group_id, False, outcomes.ACCEPTED, candidate.gate, "final pass")
                    out.append(candidate.constraint)
        return out

    def joined(self, i: int, j: int, frames: set[int]) -> bool:
        """Whether an accepted loop between two of ``frames`` (a group's) joins the drive-bys of ``i`` and ``j``."""
        near = self.p.separation.min_distance
        di, dj = self.frames.distance(i), self.frames.distance(j)
        for c in self.anchoring.accepted:
            k = c.constraint
            if k.from_map or k.frame_from not in frames or k.frame_to not in frames:
                continue
            a, b = self.frames.distance(k.frame_from), self.frames.distance(k.frame_to)
            if (abs(a - di) < near and abs(b - dj) < near) or (abs(a - dj) < near and abs(b - di) < near):
                return True
        return False
