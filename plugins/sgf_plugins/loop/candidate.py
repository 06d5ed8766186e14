"""A match the loop stage tests: the constraint that passed ICP, and what the gate saw of it."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sgf_pipeline.types import GroupAssignment, LoopConstraint, SgfDescriptor
from sgf_plugins.shared.polar import best_shift, shift_to_yaw, shifted_distances


@dataclass(frozen=True)
class GateReading:
    """What the gate saw of a match (``loop_candidates.csv``): distance since the anchor, sigma, chi-square."""

    distance: float  # m of travel since a loop last anchored the two frames (``d`` of the drift model)
    sigma_xy: float  # the prediction's position sigma (m) from the drift model
    chi2: float  # the best fit's squared Mahalanobis distance to the prediction


@dataclass(frozen=True)
class Candidate:
    """A constraint that passed ICP, with what the gate and the map anchoring need."""

    constraint: LoopConstraint
    map_pose: np.ndarray | None
    map_truth: np.ndarray | None
    group_id: int
    anchored: bool = False  # a map match made once the run was placed in the map
    gate: GateReading | None = None


def match_closest(a: GroupAssignment, members: list[SgfDescriptor]) -> GroupAssignment:
    """The match redone with the closest of ``members`` (eq. 10 at its best shift) as the matched SGF."""
    query = np.asarray(a.descriptor.matrix)
    profiles = shifted_distances(query, np.stack([np.asarray(m.matrix) for m in members]))
    k = int(np.argmin(profiles.min(axis=1)))
    shift = best_shift(profiles[k])
    yaw = shift_to_yaw(shift, profiles.shape[1])
    return replace(a, matched=members[k], distance=float(profiles[k, shift]), shift=shift, yaw=yaw)
