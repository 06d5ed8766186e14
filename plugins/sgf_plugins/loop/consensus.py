"""The neighbour consensus: which of look-alike matches the markings seen around both sightings agree with.

Look-alike markings (the campus repeats standard ones) defeat eq. 10 and, while the drift is larger
than their spacing, the gate too. The association then reports the match as ambiguous with the tied
groups as ``alternatives``; each option is put through ICP and the gate, and then through the
neighbour consensus (:meth:`NeighbourConsensus.support`): the SGFs seen in the last
``consensus.window`` metres, carried by the locally accurate odometry and the option's ICP pose into
the earlier pass, must land on look-alike SGFs of that pass (with ``consensus.heading_deg`` set,
look-alike at the heading the match predicts for them, and a neighbour that looks alike turned half a
turn too, a bar or a disc, fixes no heading and counts ``consensus.unoriented_weight``; off by
default). The one option with at least ``consensus.tie_support`` agreeing markings wins; none or
several, and the match gives no factor.

``consensus.min_support`` asks the same of every loop, except a match into a distinct marking: one
the query looks like (eq. 10 within ``consensus.distance``) while no SGF of any other group comes
within ``distinct.distance`` of it. Such a marking (a custom one, painted once) vouches for itself and
needs ``distinct.support`` agreeing neighbours, so a route that revisits one marking only can close
its loop; the gate is what stands against the second copy of a repeated design met before any third
copy made it look common.
With ``consensus.wait``, a match that has too few agreeing neighbours so far waits while the robot
drives ``consensus.window`` metres on, and the SGFs seen after it count too. A neighbour tens of
metres from its sighting lies off by the odometry's drift over that path; the tolerance grows with
it (``consensus.drift`` per metre).

A match into an aliased group (a repeated pattern: dashes, chevrons, bars) may be with the wrong copy,
one period away, where the pattern's other copies agree with it too; it needs
``consensus.aliased_support`` agreeing markings that do not look like the query, each within half the
period of the copies seen around it (0: aliased groups never give loop factors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.types import GroupAssignment, LoopConstraint
from sgf_plugins.loop.candidate import Candidate
from sgf_plugins.loop.memory import SgfMemory, odometry_xy
from sgf_plugins.loop.params import IcpLoopParams
from sgf_plugins.shared.frame_log import FrameLog
from sgf_plugins.shared.polar import shifted_distances, yaw_to_shift

#: Look-alike SGFs nearer each other than this (m) are one marking seen twice, not two copies of a pattern.
COPY_MIN_SPACING_M = 0.5


@dataclass(frozen=True)
class Waiting:
    """A match that passed ICP and the gate and waits for agreeing neighbours (``consensus.wait``).

    ``options`` are the candidates of the match (one, or the look-alikes of a tie that passed);
    the one with ``need`` agreeing neighbours wins. ``refused`` names the count of a match that
    expires, ``resolved`` the counter of one that is settled (ties, aliases).
    """

    options: tuple[tuple[GroupAssignment, Candidate], ...]
    need: int
    unlike: bool
    refused: str
    resolved: str | None
    distance: float


class NeighbourConsensus:
    """How many markings around a match's two sightings agree with it; whether its marking is distinct."""

    def __init__(self, params: IcpLoopParams, frames: FrameLog, memory: SgfMemory) -> None:
        self.p = params
        self.frames = frames
        self.memory = memory

    def support(self, a: GroupAssignment, c: LoopConstraint, unlike: bool = False) -> float:
        """How many other markings near the query agree with the match: seen where it puts them, and alike.

        The match says the query's frame sits at ``c.relative`` in the matched frame; odometry is
        accurate over tens of metres, so it carries the SGFs seen within ``consensus.window`` before
        the query (and after it so far, with ``consensus.wait``) into the earlier pass's odometry
        frame. A neighbour agrees when an SGF of the earlier pass (within the window around the
        matched SGF, and at least ``separation.min_distance`` of path before the neighbour) lies
        within ``consensus.radius + consensus.drift * (path from the two sightings)`` of it and looks
        like it (eq. 10 distance at most ``consensus.distance``); with ``consensus.heading_deg`` set,
        at the heading the match predicts for it, within that many degrees, and a neighbour that
        looks alike at the opposite heading too (a bar, a disc) confirms the position but not the
        heading, and counts ``consensus.unoriented_weight``. Agreeing neighbours closer than
        ``consensus.exclude`` to each other, or to the query, are one marking; the count is of
        markings. A look-alike marking elsewhere on campus has other neighbours, so its match finds
        none. With ``unlike``, neighbours that look like the query (eq. 10 distance at most
        ``consensus.distance``) do not count: in a repeated pattern they are its other copies, which
        agree with a match shifted by a period; and the tolerance is capped at half the pattern's
        period (:meth:`copy_spacing`), since a neighbour allowed more would agree with the match
        one period off too.
        """
        p = self.p.consensus
        assert a.matched is not None
        query, matched = a.descriptor, a.matched
        odo_j = np.asarray(query.sgf.odometry, dtype=np.float64)
        odo_i = np.asarray(matched.sgf.odometry, dtype=np.float64)
        x, y, yaw = xy_yaw(odo_i @ c.relative @ invert(odo_j))
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        xy = self.memory.xy()
        dist = self.memory.distances()
        headings = self.memory.headings()
        d_j, d_i = self.frames.distance(query.sgf.frame_index), self.frames.distance(matched.sgf.frame_index)
        q_xy, m_xy = odometry_xy(query), odometry_xy(matched)
        near_query = (dist >= d_j - p.window) & (dist <= d_j + (p.window if p.wait else 0.0))
        near_query &= np.hypot(*(xy - q_xy).T) > p.exclude
        near_match = (np.abs(dist - d_i) <= p.window) & (np.hypot(*(xy - m_xy).T) > p.exclude)
        earlier = np.flatnonzero(near_match)
        if not len(earlier):
            return 0.0
        agreeing: list[tuple[np.ndarray, float]] = []
        neighbours = np.flatnonzero(near_query)
        if unlike and len(neighbours):
            alike = shifted_distances(query.matrix, np.stack([self.memory[k].matrix for k in neighbours])).min(axis=1)
            neighbours = neighbours[alike > p.distance]
        far = np.abs(dist[earlier] - d_i)  # path from the matched sighting to each earlier SGF
        cap = 0.5 * self.copy_spacing(a) if unlike else math.inf
        for k in neighbours:
            here = rot @ xy[k] + (x, y)
            near = abs(d_j - dist[k])
            tolerance = np.minimum(p.radius + p.drift * (near + far), cap)
            close = earlier[
                (np.hypot(*(xy[earlier] - here).T) <= tolerance)
                & (dist[earlier] <= dist[k] - self.p.separation.min_distance)
            ]
            if not len(close):
                continue
            profiles = shifted_distances(self.memory[k].matrix, np.stack([self.memory[m].matrix for m in close]))
            # the neighbour's heading in each earlier SGF's frame, as the match predicts it (eq. 10's shift convention)
            predicted = headings[k] + yaw - headings[close]
            weight = _agreement(profiles, predicted, p.distance, p.heading_deg, p.unoriented_weight)
            if weight <= 0.0:
                continue
            same = [n for n, (g, _) in enumerate(agreeing) if np.hypot(*(xy[k] - g)) <= p.exclude]
            if same:
                agreeing[same[0]] = (agreeing[same[0]][0], max(agreeing[same[0]][1], weight))
            else:
                agreeing.append((xy[k], weight))
        return float(sum(w for _, w in agreeing))

    def copy_spacing(self, a: GroupAssignment) -> float:
        """The period of a repeated pattern: the nearest copy of the query's design seen around either sighting.

        Copies are SGFs of other groups that look like the query (eq. 10 at most
        ``consensus.distance``), seen within ``consensus.window`` of path of the matched SGF or of
        the query, and farther than ``COPY_MIN_SPACING_M`` from it (nearer is the same marking seen
        again); distances in that pass's odometry frame, exact over such short paths. Infinite when
        no copy was seen.
        """
        assert a.matched is not None
        others, distances = self.memory.other_groups_distances(np.asarray(a.descriptor.matrix), a.group_id)
        copies = others[distances <= self.p.consensus.distance]
        if not len(copies):
            return math.inf
        xy = self.memory.xy()[copies]
        travelled = self.memory.distances()[copies]
        spacing = math.inf
        for sighting in (a.matched, a.descriptor):
            around = np.abs(travelled - self.frames.distance(sighting.sgf.frame_index)) <= self.p.consensus.window
            gaps = np.hypot(*(xy[around] - odometry_xy(sighting)).T)
            gaps = gaps[gaps > COPY_MIN_SPACING_M]
            if len(gaps):
                spacing = min(spacing, float(gaps.min()))
        return spacing

    def distinct(self, a: GroupAssignment) -> bool:
        """Whether the query looks like its match (eq. 10) and like no SGF of any other group seen so far.

        The campus repeats standard markings; a marking whose copies have been seen elsewhere has
        them in other groups (the spatial gate keeps them apart), so its matches need neighbours
        that agree. A marking that looks like nothing else seen (a custom one, painted once) is
        its own evidence; so, with ``distinct.ratio`` set, is one far more like its match than like
        any SGF of another group (that many times: a ratio test; false pairs measured at most 1.2).
        The first copy of a repeated design met twice is the risk this takes.
        """
        assert a.matched is not None
        query = np.asarray(a.descriptor.matrix)
        match = float(shifted_distances(query, np.asarray(a.matched.matrix)).min())
        if match > self.p.consensus.distance:
            return False
        _, alike = self.memory.other_groups_distances(query, a.group_id)
        if not len(alike):
            return False
        nearest, ratio = float(alike.min()), self.p.distinct.ratio
        if nearest > self.p.distinct.distance:
            return True
        return ratio is not None and nearest > self.p.distinct.floor and nearest >= ratio * match


def support_detail(support: list[float], need: float) -> str:
    """The agreeing neighbours of each option (weighted) against the number needed, for ``loop_candidates.csv``."""
    return "support " + ", ".join(f"{n:.3g}" for n in support) + f" of {need:g} needed"


def _agreement(
    profiles: np.ndarray, predicted: np.ndarray, distance: float, heading_deg: float | None, unoriented: float
) -> float:
    """How much a neighbour agrees with its best earlier look-alike: 1, ``unoriented``, or 0.

    ``profiles`` holds eq. 10 at every column shift against each earlier SGF, ``predicted`` the
    neighbour's heading in each one's frame. It agrees when some profile is at most ``distance``
    within ``heading_deg`` of the predicted heading (anywhere when ``None``: weight 1), and counts
    ``unoriented`` when that profile is as low at the opposite heading (the shape fixes no heading).
    """
    if heading_deg is None:
        return 1.0 if float(profiles.min()) <= distance else 0.0
    n_s = profiles.shape[1]
    shifts = np.arange(n_s)[None, :]
    width = heading_deg / 360.0 * n_s

    def lowest(yaws: np.ndarray) -> np.ndarray:
        centre = np.array([yaw_to_shift(float(y), n_s) for y in yaws])[:, None]
        gap = np.abs(np.mod(shifts - centre + n_s / 2.0, n_s) - n_s / 2.0)
        return np.where(gap <= width, profiles, np.inf).min(axis=1)

    at = lowest(predicted)
    opposite = lowest(predicted + math.pi)
    weights = np.where(at <= distance, np.where(opposite <= distance, unoriented, 1.0), 0.0)
    return float(weights.max())
