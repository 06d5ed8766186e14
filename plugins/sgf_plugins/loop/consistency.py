"""Pairwise consistency of accepted loops through the odometry (as in PCM), and their largest consistent set.

Two loops ``a: i1 -> j1`` and ``b: i2 -> j2`` with measured relative poses ``Z_a`` and ``Z_b`` close a
cycle with the odometry between their ends: ``(Z_a O(j1 -> j2))^-1 O(i1 -> i2) Z_b`` is the identity
when both are true, up to the odometry's drift over the path ``d`` driven between ``i1`` and ``i2``
and between ``j1`` and ``j2``. The ratio of the cycle's position error to ``floor + per_metre * d``
measures their disagreement; loops that disagree with the others beyond ``threshold`` fall outside
the largest mutually consistent set (a maximum clique of the agreement graph). Two copies of a
design at two crossings laid out alike give loops that agree with each other and with no true one.

The odometry's heading bias per metre bends every long stretch alike, and a reverse loop's two
stretches the opposite way: at full length (1.3 km) it lifts true loops' ratios to 2.7, so the
test takes the odometry with that bias off (:func:`bias_corrected_path`), as the loops estimate it
(:func:`loop_heading_bias`); true loops then agree within 0.4.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sgf_pipeline.geometry import xy_yaw
from sgf_plugins.loop.candidate import Candidate
from sgf_plugins.loop.params import ConsistencyParams
from sgf_plugins.shared.drift import EXPECTED_YAW_BIAS
from sgf_plugins.shared.frame_log import FrameLog
from sgf_plugins.shared.heading_bias import HeadingBias
from sgf_plugins.shared.se2 import se2


@dataclass(frozen=True)
class LoopEnds:
    """One loop: its frames, its measured relative pose (planar 3x3, ``i -> j``), the odometry at both ends.

    ``odometry_i``/``odometry_j``: planar 3x3 odometry poses of the two frames (``se2`` of ``xy_yaw``);
    ``distance_i``/``distance_j``: metres the odometry had driven at them.
    """

    frame_i: int
    frame_j: int
    relative: np.ndarray
    odometry_i: np.ndarray
    odometry_j: np.ndarray
    distance_i: float
    distance_j: float


def loop_heading_bias(
    frames: np.ndarray,
    odometry: np.ndarray,
    loops: Sequence[tuple[int, int, float, float]],
    prior_sigma: float = math.radians(0.5),
    odometry_sigma_yaw: float = math.radians(0.5),
    kernel_width: float = 3.0,
    reading_sigma: float = EXPECTED_YAW_BIAS,
) -> float:
    """The odometry's heading bias (rad per metre) the loops measure, as the back-end estimates it.

    ``frames`` and ``odometry`` (N, 4, 4): the path, in order; ``loops``: per loop its two frames, its
    relative yaw and that yaw's variance. A Cauchy-weighted least squares with a zero-mean prior
    (:class:`sgf_plugins.shared.heading_bias.HeadingBias`), so one false loop among true ones hardly moves
    it; zero unless two loops agree on it and it stands out of its uncertainty.
    """
    estimator = HeadingBias(prior_sigma, odometry_sigma_yaw, kernel_width, reading_sigma=reading_sigma)
    for index, pose in zip(frames, odometry, strict=True):
        estimator.correct(int(index), pose)
    for frame_from, frame_to, yaw, variance in loops:
        estimator.observe(frame_from, frame_to, yaw, variance)
    return estimator.value


def bias_corrected_path(odometry: np.ndarray, travelled: np.ndarray, bias: float) -> np.ndarray:
    """Planar poses (N, 3, 3) of an odometry path with its heading turned by ``-bias`` per metre travelled.

    Each step is turned by the correction at its start; the first pose stays.
    """
    xy = odometry[:, :2, 3]
    turn = -bias * (travelled - travelled[0])
    steps = np.diff(xy, axis=0)
    c, s = np.cos(turn[:-1]), np.sin(turn[:-1])
    turned = np.stack([c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1]], axis=1)
    corrected = np.vstack([xy[:1], xy[:1] + np.cumsum(turned, axis=0)])
    yaw = np.arctan2(odometry[:, 1, 0], odometry[:, 0, 0]) + turn
    out = np.zeros((len(odometry), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    out[:, :2, 2] = corrected
    out[:, 2, 2] = 1.0
    return out


def cycle_ratio(a: LoopEnds, b: LoopEnds, floor: float = 1.0, per_metre: float = 0.05) -> float:
    """Position error of the cycle through loops ``a`` and ``b`` over ``floor + per_metre * d`` (module docstring)."""
    o_i = np.linalg.solve(a.odometry_i, b.odometry_i)  # O(i1 -> i2)
    o_j = np.linalg.solve(a.odometry_j, b.odometry_j)  # O(j1 -> j2)
    cycle = np.linalg.solve(a.relative @ o_j, o_i @ b.relative)
    driven = abs(a.distance_i - b.distance_i) + abs(a.distance_j - b.distance_j)
    return float(math.hypot(cycle[0, 2], cycle[1, 2]) / (floor + per_metre * driven))


def consistency_ratios(loops: Sequence[LoopEnds], floor: float = 1.0, per_metre: float = 0.05) -> np.ndarray:
    """The symmetric matrix of :func:`cycle_ratio` over every pair of loops (zero on the diagonal)."""
    n = len(loops)
    ratios = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            ratios[a, b] = ratios[b, a] = cycle_ratio(loops[a], loops[b], floor, per_metre)
    return ratios


def maximum_consistent_sets(ratios: np.ndarray, threshold: float) -> list[list[int]]:
    """Every largest set of loops whose every pair's ratio is at most ``threshold`` (Bron-Kerbosch with pivots).

    Each set's indices are sorted; the sets come in the order found. None for no loops.
    """
    n = len(ratios)
    agree = [{b for b in range(n) if b != a and ratios[a, b] <= threshold} for a in range(n)]
    found: list[list[int]] = []

    def expand(clique: list[int], candidates: set[int], excluded: set[int]) -> None:
        size = len(found[0]) if found else 0
        if not candidates and not excluded:
            if len(clique) > size:
                found.clear()
            if len(clique) >= size and clique:
                found.append(sorted(clique))
            return
        if len(clique) + len(candidates) < size:
            return
        pivot = max(candidates | excluded, key=lambda u: len(agree[u] & candidates))
        for v in sorted(candidates - agree[pivot]):
            expand([*clique, v], candidates & agree[v], excluded & agree[v])
            candidates = candidates - {v}
            excluded = excluded | {v}

    expand([], set(range(n)), set())
    return found


def _worst(ratios: np.ndarray, clique: list[int]) -> float:
    return max((float(ratios[a, b]) for a in clique for b in clique if a < b), default=0.0)


def largest_consistent_set(ratios: np.ndarray, threshold: float) -> list[int]:
    """The largest set of loops whose every pair's ratio is at most ``threshold``.

    Ties go to the set whose worst ratio is smallest; the indices are returned sorted.
    """
    return min(maximum_consistent_sets(ratios, threshold), key=lambda c: _worst(ratios, c), default=[])


def inconsistent_loops(ratios: np.ndarray, threshold: float) -> list[int]:
    """Loops outside the largest consistent set: those the loops' majority contradicts (sorted indices).

    Equally large sets go to the one whose worst ratio is smallest; a loop in any of several sets
    equal in both (two lone loops that contradict each other) is kept: a tie leaves it undecided.
    """
    sets = maximum_consistent_sets(ratios, threshold)
    least = min((_worst(ratios, c) for c in sets), default=0.0)
    kept = {k for c in sets if _worst(ratios, c) == least for k in c}
    return [k for k in range(len(ratios)) if k not in kept]


@dataclass(frozen=True)
class ConsistencyRound:
    """One round of the end-of-run test: the loops it judged, and those outside the largest consistent set."""

    judged: tuple[Candidate, ...]
    outside: tuple[Candidate, ...]


def consistency_entry(
    accepted: list[Candidate], frames: FrameLog, p: ConsistencyParams, threshold: float
) -> tuple[dict[str, Any], list[int]]:
    """Accepted loops outside the largest mutually consistent set (:func:`inconsistent_loops`) and its metrics.

    Returns the metrics entry (``metrics.json`` loops.consistency; the evaluation adds how many of
    them are false) and those loops' places in ``accepted`` (map loops and position-only loops, whose
    cycles have no turn to close, are not judged).
    """
    own = [k for k, c in enumerate(accepted) if not (c.constraint.from_map or c.constraint.position_only)]
    constraints = [accepted[k].constraint for k in own]
    entry: dict[str, Any] = {"threshold": threshold, "dropped": p.drop_inconsistent}
    if not constraints:
        return entry | {"heading_bias_deg_per_m": None, "outside_largest_set": []}, []
    path_frames, odometry, travelled = frames.path()
    measured = [(c.frame_from, c.frame_to, xy_yaw(c.relative)[2], float(c.covariance[2][2])) for c in constraints]
    r = math.radians
    bias = loop_heading_bias(  # taken off the odometry the cycles run through
        path_frames,
        odometry,
        measured,
        prior_sigma=r(p.yaw_bias_sigma_deg_per_m),
        odometry_sigma_yaw=r(p.odometry_sigma_yaw_deg),
        kernel_width=p.kernel_width,
        reading_sigma=r(p.yaw_bias_reading_sigma_deg_per_m),
    )
    path = bias_corrected_path(odometry, travelled, bias)
    row = {int(f): k for k, f in enumerate(path_frames)}
    ends = [
        LoopEnds(
            c.frame_from,
            c.frame_to,
            se2(*xy_yaw(c.relative)),
            path[row[c.frame_from]],
            path[row[c.frame_to]],
            float(travelled[row[c.frame_from]]),
            float(travelled[row[c.frame_to]]),
        )
        for c in constraints
    ]
    outside = [own[k] for k in inconsistent_loops(consistency_ratios(ends), threshold)]
    entry |= {
        "heading_bias_deg_per_m": math.degrees(bias),
        "outside_largest_set": [[accepted[k].constraint.frame_from, accepted[k].constraint.frame_to] for k in outside],
    }
    return entry, outside


class LoopConsistency:
    """The end-of-run test over the accepted loops, round by round (``loop.consistency``)."""

    def __init__(self, p: ConsistencyParams, frames: FrameLog) -> None:
        self.p = p
        self.frames = frames
        self.entry: dict[str, Any] | None = None  # metrics.json loops.consistency, both rounds
        self.rounds: list[ConsistencyRound] = []  # what each round judged (for the evaluation)

    def judge(self, accepted: list[Candidate]) -> list[Candidate] | None:
        """The loops to take back: with ``drop_inconsistent`` those outside the largest consistent set.

        ``None`` without the test. A second round (after the final pass) adds to the first's record.
        """
        if self.p.threshold is None:
            return None
        entry, outside = consistency_entry(accepted, self.frames, self.p, self.p.threshold)
        judged = tuple(c for c in accepted if not (c.constraint.from_map or c.constraint.position_only))
        self.rounds.append(ConsistencyRound(judged, tuple(accepted[k] for k in outside)))
        if self.entry is not None and self.p.drop_inconsistent:  # the rounds judged different loops
            entry["outside_largest_set"] = self.entry["outside_largest_set"] + entry["outside_largest_set"]
        self.entry = entry
        return [accepted[k] for k in sorted(set(outside))] if self.p.drop_inconsistent else []
