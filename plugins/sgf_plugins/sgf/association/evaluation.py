"""Ground-truth scoring of SGF groups: purity and the revisit pairs found (Table 3)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from sgf_pipeline.stage import SettledGroup
from sgf_pipeline.types import MarkingPass, SequenceTruth
from sgf_plugins.sgf.association.groups import SgfGroup


def instance_counts(group: SgfGroup | SettledGroup) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth instances of a group's labelled members (sorted) and how many members show each."""
    return np.unique([m.sgf.instance_id for m in group.members if m.sgf.instance_id is not None], return_counts=True)


def majority_instance(group: SgfGroup | SettledGroup) -> int | None:
    """The ground-truth instance most of a group's labelled members show (None when none is labelled)."""
    values, counts = instance_counts(group)
    return int(values[np.argmax(counts)]) if len(values) else None


def group_purity(groups: Iterable[SgfGroup | SettledGroup]) -> float | None:
    """Share of ground-truth-labelled members that carry their group's majority instance (None if no labels)."""
    majority = total = 0
    for group in groups:
        _, counts = instance_counts(group)
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
