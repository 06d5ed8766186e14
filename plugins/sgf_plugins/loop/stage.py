"""Loop closing with SGF factors (paper Sec. III-D): ICP between an SGF and its group's closest member.

When a new SGF joins a group holding an SGF from an earlier pass (``GroupAssignment.matched``;
when the association matched a view of the same pass, the group's closest member from an earlier
pass), the match is put through these steps, each in its module:

1. ICP alignment (:mod:`~sgf_plugins.loop.fitting`): seeded by the column shift's yaw, the fits that
   pass the shape tests, one per alignment.
2. The gate (:mod:`~sgf_plugins.loop.gate`): the ICP pose against the relative pose the estimate
   predicts, within the drift since a loop last anchored the two frames
   (:mod:`~sgf_plugins.loop.anchoring`, :mod:`~sgf_plugins.shared.drift`).
3. The neighbour consensus (:mod:`~sgf_plugins.loop.consensus`): look-alike markings are told
   apart by the markings around them, unless the match is into a distinct marking or the gate
   alone decides it; a match short of agreeing neighbours waits for those seen after it.
4. Map anchoring (:mod:`~sgf_plugins.loop.anchoring`): matches into a prior map wait until
   enough of them agree on where the run is in the map.

A match into a symmetric group (a round manhole) gives a position-only loop when the gate alone
decides it (``symmetric.position_only``). At the end of the run the final groups' unjoined
drive-bys are matched once more (:mod:`~sgf_plugins.loop.final_pass`), and the loops are
scored against the ground truth (:mod:`~sgf_plugins.loop.evaluation`). Every decision is a row of
``loop_candidates.csv`` (:mod:`~sgf_plugins.loop.decisions`), its outcome one of
:mod:`~sgf_plugins.loop.outcomes`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from sgf_pipeline import Previous, RunContext, Stage, StageRegistry, hookimpl
from sgf_pipeline.sgf_map import MapDescriptor
from sgf_pipeline.stage import Settlement
from sgf_pipeline.truth import SequenceTruth
from sgf_pipeline.types import Frame, GroupAssignment, GroupAssignments, LoopConstraint, LoopConstraints, PoseEstimate
from sgf_plugins.loop import outcomes
from sgf_plugins.loop.anchoring import LoopAnchoring
from sgf_plugins.loop.candidate import Candidate
from sgf_plugins.loop.consensus import NeighbourConsensus, Waiting, support_detail
from sgf_plugins.loop.decisions import DecisionLog
from sgf_plugins.loop.evaluation import evaluate_loops
from sgf_plugins.loop.files import write_loop_files
from sgf_plugins.loop.final_pass import FinalPass
from sgf_plugins.loop.fitting import IcpFitting
from sgf_plugins.loop.gate import LoopGate
from sgf_plugins.loop.memory import SgfMemory
from sgf_plugins.loop.params import IcpLoopParams
from sgf_plugins.shared.frame_log import FrameLog


class IcpLoopClosing(Stage):
    """SGF loop constraints from ICP between group members, gated by the estimate's uncertainty (Sec. III-D)."""

    kind = "loop"
    name = "icp"
    output = "loops"
    Params = IcpLoopParams

    def __init__(self, params: IcpLoopParams) -> None:
        super().__init__(params)
        self.p = params
        from scipy.stats import chi2  # imported here: scipy.stats takes seconds to import

        self.threshold = float(chi2.ppf(params.gate.probability, df=3))
        self.begin(RunContext(run_dir=None))

    def begin(self, context: RunContext) -> None:
        """Forget the previous sequence."""
        self.truth: SequenceTruth | None = context.truth
        self.frames = FrameLog(truth=True)  # every processed frame: loops may reach any earlier place
        self.memory = SgfMemory()
        self.fitting = IcpFitting(self.p)
        self.anchoring = LoopAnchoring(self.frames, self.p.gate, self.p.map, self.threshold)
        self.gate = LoopGate(self.p, self.frames, self.memory, self.fitting, self.anchoring, self.threshold)
        self.consensus = NeighbourConsensus(self.p, self.frames, self.memory)
        self.log = DecisionLog(self.frames)
        self.final_pass = FinalPass(self.p, self.frames, self.gate, self.anchoring, self.log)
        self.counts = self.log.counts
        self.decisions = self.log.rows  # every candidate's outcome: loop_candidates.csv
        context.artifacts["loop_candidates"] = self.decisions  # grows as matches are decided: observers watch it
        self.waiting: list[Waiting] = []
        self.assignments: list[GroupAssignment] = []
        self.ties_resolved = 0
        self.aliases_resolved = 0
        self.distinct = 0
        self.gate_decided = 0
        self.position_only = 0
        self.earlier_members = 0
        self._estimate: PoseEstimate | None = None  # the newest estimate (for the final pass)
        self._settled = False
        self.final_accepted = 0  # loops the final pass closed

    # -- per frame --------------------------------------------------------------------------

    def process(
        self, frame: Frame, assignments: GroupAssignments | None, estimate: Previous[PoseEstimate]
    ) -> LoopConstraints:
        """Loop constraints of the SGFs assigned to groups on this frame."""
        self.frames.append(frame)
        if estimate is not None:
            self._estimate = estimate
        if assignments is None:
            return LoopConstraints(tuple(self._settle_waiting(estimate, new_sgfs=False)))
        earlier, self.waiting = self.waiting, []  # this frame's matches were just decided: they wait untested
        out: list[LoopConstraint] = []
        for a in assignments.items:
            kept = replace(a, descriptor=a.descriptor.without_pixels())  # for the map and the gate: no pixels
            self.assignments.append(kept)
            j = a.descriptor.sgf.frame_index
            if j in self.frames:
                self.memory.remember(kept, self.frames.distance(j))
            out.extend(self._close(a, estimate))
        out.extend(self._settle_waiting(estimate, new_sgfs=bool(assignments.items), waiting=earlier))
        return LoopConstraints(tuple(out))

    def _close(self, a: GroupAssignment, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """ICP, acceptance tests, gate and neighbour consensus for one assignment; the constraints to emit now."""
        if a.new_group or a.matched is None:
            return []
        self.counts["candidates"] += 1
        if a.symmetric:
            if not self.p.symmetric.position_only:
                self.log.refuse(a, outcomes.SYMMETRIC)
                return []
            return self._close_position_only(a, estimate)
        if a.ambiguous:
            return self._resolve_tie(a, estimate)
        a, candidate = self._evaluate_or_earlier(a, estimate)
        if candidate is None:
            return []
        need, basis = self.p.consensus.min_support, ""
        if self.p.distinct.support is not None and need > self.p.distinct.support and self.consensus.distinct(a):
            need, basis = self.p.distinct.support, "distinct"
            self.distinct += 1
        if need > 0 and candidate.map_pose is None and self.gate.decides(a, candidate, estimate):
            need, basis = 0, "the gate decides"
            self.gate_decided += 1
        if need > 0 and candidate.map_pose is None:
            return self._consensus(((a, candidate),), need, False, outcomes.CONSENSUS, None, estimate)
        return self._accept(candidate, estimate, basis)

    def _evaluate_or_earlier(
        self, a: GroupAssignment, estimate: PoseEstimate | None
    ) -> tuple[GroupAssignment, Candidate | None]:
        """The gate's evaluation, redone with an earlier pass's member when the match is of one pass; None: refused."""
        candidate = self.gate.evaluate(a, estimate)
        if candidate == outcomes.SEPARATION:
            earlier = self.gate.earlier_member(a, self.assignments)
            if earlier is not None:
                a, candidate = earlier, self.gate.evaluate(earlier, estimate)
                self.earlier_members += 1
        if isinstance(candidate, str):
            self.log.refuse(a, candidate, self.gate.reading, self.fitting.detail if candidate == outcomes.ICP else "")
            return a, None
        return a, candidate

    def _close_position_only(self, a: GroupAssignment, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """A match into a symmetric group: a position-only loop when the gate alone decides (``symmetric``).

        Round markings are the campus's most repeated design, so no neighbour vouches for one: the
        gate must predict the match tightly (``gate.support_sigma``) with no look-alike seen within
        its reach. Such loops are not matched against a prior map, whose anchoring needs a heading.
        """
        if isinstance(a.matched, MapDescriptor):
            self.log.refuse(a, outcomes.SYMMETRIC, detail="no position-only loop into a prior map")
            return []
        if a.ambiguous:
            self.log.refuse(a, outcomes.AMBIGUOUS, detail="a tie of symmetric groups")
            return []
        a, candidate = self._evaluate_or_earlier(a, estimate)
        if candidate is None:
            return []
        if not self.gate.decides(a, candidate, estimate):
            self.log.refuse(a, outcomes.CONSENSUS, candidate.gate, f"position only: {self.gate.refusal}")
            return []
        self.gate_decided += 1
        self.position_only += 1
        return self._accept(candidate, estimate, "position only: the gate decides")

    def _resolve_tie(self, a: GroupAssignment, estimate: PoseEstimate | None) -> list[LoopConstraint]:
        """A match among look-alike groups: the one option whose neighbouring SGFs agree, else nothing."""
        options = [a] + [
            replace(a, group_id=alt.group_id, matched=alt.matched, shift=alt.shift, yaw=alt.yaw, alternatives=())
            for alt in a.alternatives
        ]
        if any(isinstance(o.matched, MapDescriptor) for o in options):
            self.log.refuse(a, outcomes.AMBIGUOUS, detail="tie with a map group")
            return []
        if a.aliased and not a.alternatives and self.p.consensus.aliased_support > 0:
            # a repeated pattern: only markings unlike the query may vouch for which copy it is
            candidate = self.gate.evaluate(a, estimate)
            if isinstance(candidate, str):
                self.log.refuse(a, outcomes.AMBIGUOUS, detail=f"aliased: {self._failure(candidate)}")
                return []
            return self._consensus(
                ((a, candidate),), self.p.consensus.aliased_support, True, outcomes.AMBIGUOUS, "aliases", estimate
            )
        if a.aliased or not a.alternatives or self.p.consensus.tie_support == 0:
            why = "aliased" if a.aliased else "tie with an aliased group" if not a.alternatives else "tie_support 0"
            self.log.refuse(a, outcomes.AMBIGUOUS, detail=why)
            return []
        passed, failed = [], []
        for option in options:
            candidate = self.gate.evaluate(option, estimate)
            if isinstance(candidate, str):
                failed.append(self._failure(candidate))
            else:
                passed.append((option, candidate))
        if not passed:
            self.log.refuse(a, outcomes.AMBIGUOUS, detail="tie: every option failed (" + "; ".join(failed) + ")")
            return []
        if len(passed) == 1 and self.gate.decides(*passed[0], estimate):
            self.gate_decided += 1
            self.ties_resolved += 1
            return self._accept(passed[0][1], estimate, "the gate decides the tie")
        need = max(self.p.consensus.tie_support, self.p.consensus.min_support)
        return self._consensus(tuple(passed), need, False, outcomes.AMBIGUOUS, "ties", estimate)

    def _consensus(
        self,
        options: tuple[tuple[GroupAssignment, Candidate], ...],
        need: int,
        unlike: bool,
        refused: str,
        resolved: str | None,
        estimate: PoseEstimate | None,
    ) -> list[LoopConstraint]:
        """Settle a match by its neighbours now, or let it wait for the SGFs of the next ``consensus.window`` metres."""
        distance = self.frames.distance(options[0][0].descriptor.sgf.frame_index)
        waiting = Waiting(options, need, unlike, refused, resolved, distance)
        out = self._settle(waiting, estimate, final=not self.p.consensus.wait)
        if out is None:
            self.waiting.append(waiting)
            return []
        return out

    def _settle(self, w: Waiting, estimate: PoseEstimate | None, final: bool) -> list[LoopConstraint] | None:
        """The constraint of the one option with enough agreeing neighbours, [] when refused, None to wait on."""
        support = [self.consensus.support(a, c.constraint, unlike=w.unlike) for a, c in w.options]
        supported = [c for (_, c), n in zip(w.options, support, strict=True) if n >= w.need]
        if len(supported) == 1:
            if w.resolved == "ties":
                self.ties_resolved += 1
            elif w.resolved == "aliases":
                self.aliases_resolved += 1
            return self._accept(supported[0], estimate, support_detail(support, w.need))
        if len(supported) > 1 or final:
            outcome = outcomes.AMBIGUOUS if len(supported) > 1 else w.refused
            self.log.refuse(w.options[0][0], outcome, w.options[0][1].gate, support_detail(support, w.need))
            return []
        return None

    def _settle_waiting(
        self, estimate: PoseEstimate | None, new_sgfs: bool, waiting: list[Waiting] | None = None
    ) -> list[LoopConstraint]:
        """Re-test waiting matches (all, or ``waiting`` taken out of the list) with the SGFs seen since.

        Those the robot has driven ``consensus.window`` past expire; the unsettled go back on the list.
        """
        if waiting is None:
            waiting, self.waiting = self.waiting, []
        here = self.frames.travelled
        out: list[LoopConstraint] = []
        for w in waiting:
            expired = here - w.distance > self.p.consensus.window
            settled = self._settle(w, estimate, final=expired) if new_sgfs or expired else None
            if settled is None:
                self.waiting.append(w)
            else:
                out.extend(settled)
        return out

    def _accept(self, candidate: Candidate, estimate: PoseEstimate | None, basis: str = "") -> list[LoopConstraint]:
        """Emit a candidate that passed every test (map matches wait for the run's anchoring in the map).

        ``basis`` says, in ``loop_candidates.csv``, what vouched for it beyond ICP and the gate.
        """
        if candidate.map_pose is not None and not candidate.anchored:
            confirmed = self.anchoring.confirm_map(candidate, estimate)
            if not confirmed:
                self.counts[outcomes.MAP_UNCONFIRMED] += 1
                self.log.decided(candidate.constraint, candidate.group_id, outcomes.MAP_UNCONFIRMED, candidate.gate)
                return []
            self.counts[outcomes.MAP_UNCONFIRMED] -= len(confirmed) - 1
            for c in confirmed:
                self.log.decided(c.constraint, c.group_id, outcomes.ACCEPTED, c.gate)
            return [c.constraint for c in confirmed]
        self.anchoring.accepted.append(candidate)
        self.log.decided(candidate.constraint, candidate.group_id, outcomes.ACCEPTED, candidate.gate, basis)
        return [candidate.constraint]

    def _failure(self, test: str) -> str:
        """A failed test's name, with what ICP's best fit missed when it was ICP."""
        return f"{outcomes.ICP}, {self.fitting.detail}" if test == outcomes.ICP else test

    # -- end of the run ---------------------------------------------------------------------

    def settle(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Refuse the candidates still waiting (the run ended before they were settled)."""
        for w in self.waiting:  # the run ended before they were settled
            support = [self.consensus.support(a, c.constraint, unlike=w.unlike) for a, c in w.options]
            detail = support_detail(support, w.need) + " when the run ended"
            self.log.refuse(w.options[0][0], w.refused, w.options[0][1].gate, detail)
        self.waiting = []
        self._settled = True
        return settlement

    def conclude(self, context: RunContext, settlement: Settlement) -> Settlement:
        """The final pass: matches within the association's final groups (``settlement.groups``).

        Against the newest estimate. A caller that ends the run without :meth:`settle` gets it here
        first. Hands on the final pass's loops and every group assignment (for the SGF map).
        """
        if not self._settled:
            settlement = self.settle(context, settlement)
        estimate = self._estimate
        final: list[LoopConstraint] = []
        groups = settlement.groups
        if self.p.final_pass.enabled and groups is not None and estimate is not None:
            final = self.final_pass.run(list(groups), dict(settlement.group_of), estimate)
        self.final_accepted = len(final)
        return replace(settlement, final_loops=LoopConstraints(tuple(final)), assignments=tuple(self.assignments))

    def finalize(self, context: RunContext) -> None:
        """The loop metrics (Table 3), the accepted loops and every candidate's outcome."""
        accepted = self.anchoring.accepted
        loops: dict[str, Any] = {
            "accepted": len(accepted),
            "accepted_reverse": sum(bool(c.constraint.reverse) for c in accepted),
            "accepted_map": sum(bool(c.constraint.from_map) for c in accepted),
            "rejected": {k: v for k, v in self.counts.items() if k != "candidates"},
            "candidates": self.counts["candidates"],
            "ties_resolved": self.ties_resolved,
            "aliases_resolved": self.aliases_resolved,
            "distinct": self.distinct,
            "gate_decided": self.gate_decided,
            "position_only": self.position_only,
            "earlier_members": self.earlier_members,
            "final_pass": {"tried": self.final_pass.tried, "accepted": self.final_accepted},
        }
        truth = context.truth if context.truth is not None else self.truth
        loops, records = evaluate_loops(loops, accepted, self.frames, truth, self.p)
        context.metrics.setdefault("loops", {}).update(loops)
        context.artifacts["loops"] = records
        context.artifacts["loop_candidates"] = list(self.decisions)
        write_loop_files(context, records, context.artifacts["loop_candidates"])

    def partial(self, context: RunContext, settlement: Settlement) -> Settlement:
        """The group assignments so far, for the SGF map of a run that stopped early."""
        return replace(settlement, assignments=tuple(self.assignments))


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the loop-closing variants."""
    registry.add(IcpLoopClosing)
