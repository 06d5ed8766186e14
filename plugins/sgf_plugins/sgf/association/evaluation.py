"""Ground-truth scoring of the SGF groups, from what the association publishes: purity, revisit pairs found (Table 3).

:func:`score_groups` reads the association's artifacts (``sgf_groups``, ``sgf_groups_online``,
``sgf_rankings``) and the run's truth; the association plugin reports it into ``metrics.json``
(``sgf_report_metrics``) when a run ends.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from sgf_pipeline import RunContext, hookimpl
from sgf_pipeline.runner import RunInfo
from sgf_pipeline.stage import SettledGroup
from sgf_pipeline.truth import MarkingPass, SequenceTruth
from sgf_pipeline.types import SgfDescriptor
from sgf_plugins.sgf.association.groups import Ranking, SgfGroup


def instance_counts(members: Iterable[SgfDescriptor]) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth instances of labelled group members (sorted) and how many members show each."""
    return np.unique([m.sgf.instance_id for m in members if m.sgf.instance_id is not None], return_counts=True)


def majority_instance(members: Iterable[SgfDescriptor]) -> int | None:
    """The ground-truth instance most of the labelled group members show (None when none is labelled)."""
    values, counts = instance_counts(members)
    return int(values[np.argmax(counts)]) if len(values) else None


def group_purity(groups: Iterable[SgfGroup | SettledGroup]) -> float | None:
    """Share of ground-truth-labelled members that carry their group's majority instance (None if no labels)."""
    majority = total = 0
    for group in groups:
        _, counts = instance_counts(group.members)
        if len(counts):
            majority += int(counts.max())
            total += int(counts.sum())
    return majority / total if total else None


def loop_pairs(groups: Iterable[SgfGroup | SettledGroup], truth: SequenceTruth) -> dict[str, int]:
    """Revisit pairs found (Table 3): SGFs of the pair's instance from both passes share a group."""
    together: set[tuple[int, int, int]] = set()
    for group in groups:
        passes: set[MarkingPass] = set()
        for member in group.members:
            if member.sgf.instance_id is not None:
                drive_by = truth.drive_by(member.sgf.instance_id, member.sgf.frame_index)
                if drive_by is not None:
                    passes.add(drive_by)
        for pair in truth.revisits:
            if pair.first in passes and pair.second in passes:
                together.add((pair.instance_id, pair.first.number, pair.second.number))
    found = [(p, (p.instance_id, p.first.number, p.second.number) in together) for p in truth.revisits]
    return {
        "pairs_found": sum(1 for _, ok in found if ok),
        "pairs_total": len(found),
        "pairs_found_reverse": sum(1 for p, ok in found if ok and p.reverse),
        "pairs_total_reverse": sum(1 for p, _ in found if p.reverse),
    }


def own_group_ranked_first(online: Iterable[SettledGroup], rankings: Iterable[Ranking]) -> dict[str, Any]:
    """How often the ranking put the group of the query's own marking (its members' majority) first.

    Only labelled queries whose own group and another one were both gated count; a group is judged
    by the members it had when the query was ranked. The share ranked first measures how well the
    association tells markings apart on a run.
    """
    members = {g.group_id: g.members for g in online}
    decisions = first = 0
    for ranking in rankings:
        instance = ranking.query.sgf.instance_id
        if instance is None:
            continue
        own = np.array([majority_instance(members[g][:n]) == instance for g, n in ranking.groups])
        if own.any() and not own.all():
            decisions += 1
            first += int(ranking.score[own].min() < ranking.score[~own].min())
    return {"decisions": decisions, "share": first / decisions if decisions else None}


def score_groups(context: RunContext) -> dict[str, dict[str, Any]] | None:
    """The ``sgf`` and ``loops`` metrics of the association's groups against the run's truth (None without them).

    ``purity_online`` and ``pairs_found_online`` score the groups before the split and merge at the end.
    """
    final, online = context.artifacts.get("sgf_groups"), context.artifacts.get("sgf_groups_online")
    if final is None or online is None:
        return None
    sgf: dict[str, Any] = {"purity": None}
    loops: dict[str, Any] = {"pairs_found": None, "pairs_total": None, "pairs_found_reverse": None}
    loops["pairs_total_reverse"] = None
    truth = context.truth
    if truth is not None:
        sgf["purity"] = group_purity(final)
        sgf["purity_online"] = group_purity(online)
        sgf["own_group_ranked_first"] = own_group_ranked_first(online, context.artifacts.get("sgf_rankings", []))
        sgf["mixed_groups"] = sum(1 for g in final if len(instance_counts(g.members)[0]) > 1)
        loops.update(loop_pairs(final, truth))
        loops["pairs_found_online"] = loop_pairs(online, truth)["pairs_found"]
    return {"sgf": sgf, "loops": loops}


@hookimpl
def sgf_report_metrics(run: RunInfo) -> dict[str, Any] | None:
    """The ground-truth scores of the association's groups, when it ran."""
    return None if run.context is None else score_groups(run.context)
