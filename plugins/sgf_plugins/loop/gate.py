"""The loop gate: a match's ICP pose against the relative pose the estimate predicts (chi-square, 3 dof).

The relative pose predicted by the previous frame's estimate (odometry before the back-end's first
estimate) is compared with ICP's by a chi-square test whose covariance is ICP's plus the drift model's
(:func:`~sgf_plugins.shared.drift.drift_covariance`) across ``d``, the distance since a loop last
anchored the two poses (:mod:`sgf_plugins.loop.anchoring`). This makes a look-alike marking elsewhere
fail the test once the estimate is better than the distance between the look-alikes.

Once loops have anchored the estimate, the gate itself tells a design's copies apart: a match the
gate predicts within ``gate.support_sigma`` metres needs no agreeing neighbours, unless an SGF of
another group that looks like the query was seen within the gate's reach of the matched one and could
be what the query saw (:meth:`LoopGate.decides`).
"""

from __future__ import annotations

import math

import numpy as np

from sgf_pipeline.geometry import invert, xy_yaw
from sgf_pipeline.sgf_map import MapDescriptor
from sgf_pipeline.types import GroupAssignment, PoseEstimate
from sgf_plugins.loop import outcomes
from sgf_plugins.loop.anchoring import MAP, LoopAnchoring
from sgf_plugins.loop.candidate import Candidate, GateReading, match_closest
from sgf_plugins.loop.fitting import IcpFitting
from sgf_plugins.loop.icp import IcpResult
from sgf_plugins.loop.memory import SgfMemory
from sgf_plugins.loop.params import IcpLoopParams
from sgf_plugins.shared.drift import mahalanobis2, pose_error
from sgf_plugins.shared.frame_log import FrameLog
from sgf_plugins.shared.se2 import se2_params


class LoopGate:
    """Separation, ICP and the chi-square gate for one match; and whether the gate alone decides it."""

    def __init__(
        self,
        params: IcpLoopParams,
        frames: FrameLog,
        memory: SgfMemory,
        fitting: IcpFitting,
        anchoring: LoopAnchoring,
        threshold: float,
    ) -> None:
        self.p = params
        self.frames = frames
        self.memory = memory
        self.fitting = fitting
        self.anchoring = anchoring
        self.threshold = threshold  # chi-square bound (3 dof)
        self.reading: GateReading | None = None  # what the gate saw of the match evaluated last
        self.refusal = ""  # why the gate alone did not decide the last match

    def known(self, frame_index: int) -> None:
        """Refuse an SGF of a frame this stage never saw."""
        if frame_index not in self.frames:
            raise ValueError(
                f"an SGF of frame {frame_index} reached the loop stage, which never saw that frame; "
                "SGFs must come from frames processed earlier in this run"
            )

    def evaluate(self, a: GroupAssignment, estimate: PoseEstimate | None) -> Candidate | str:
        """Separation, ICP and the gate for one match: the candidate, or the name of the test it failed."""
        matched, query = a.matched, a.descriptor
        assert matched is not None
        self.reading = None
        j = query.sgf.frame_index
        self.known(j)
        from_map = isinstance(matched, MapDescriptor)
        i = matched.sgf.frame_index
        if not from_map:
            self.known(i)
            if not self.separated(i, j):
                return outcomes.SEPARATION
        if min(len(query.points), len(matched.points)) < self.p.icp.min_points:
            return outcomes.TOO_FEW_POINTS
        position_only = a.symmetric and self.p.symmetric.position_only
        results = self.fitting.align(a, position_only)
        if not results:
            return outcomes.ICP
        map_pose = np.asarray(matched.map_pose, dtype=np.float64) if isinstance(matched, MapDescriptor) else None
        map_truth = matched.ground_truth if isinstance(matched, MapDescriptor) else None
        anchored = from_map and self.anchoring.map_anchored(estimate)
        predicted = None
        distance = math.nan
        if not from_map:
            distance = self.anchoring.anchored_distance(i, j, estimate)
            drift = self.anchoring.drift(distance, j, estimate)
            predicted = (invert(self.anchoring.pose(i, estimate)) @ self.anchoring.pose(j, estimate), drift)
        elif anchored:
            assert map_pose is not None
            distance = self.anchoring.anchored_distance(MAP, j, estimate)
            predicted = (
                invert(map_pose) @ self.anchoring.pose(j, estimate),
                self.anchoring.drift(distance, j, estimate),
            )
        points = np.asarray(query.points, dtype=np.float64)
        fits = self.fitting.centred(results, query) if position_only else self.fitting.fits(results, points)
        if not fits:
            return outcomes.ICP
        turn = None  # a position-only loop turns about its marking as the estimate predicts (ICP's heading when none)
        if position_only:
            turn = xy_yaw(predicted[0])[2] if predicted is not None else se2_params(fits[0].transform)[2]
        if predicted is not None:
            chi2 = [self.chi2(a, r, from_map, predicted, turn) for r in fits]
            self.reading = GateReading(distance, math.sqrt(predicted[1][0, 0]), min(chi2))
        if predicted is None or not self.p.gate.enabled:
            best = self.fitting.select(fits, predicted)
        else:
            # several distinct fits (a twofold symmetric shape, a row one period on): the gate must pick one
            passing = [r for r, value in zip(fits, chi2, strict=True) if value <= self.threshold]
            if len(passing) != 1:
                return outcomes.NOT_UNIQUE if passing else outcomes.GATE
            best = passing[0]
        constraint = self.fitting.constraint(a, best, from_map, turn)
        return Candidate(constraint, map_pose, map_truth, a.group_id, anchored, self.reading)

    def separated(self, i: int, j: int) -> bool:
        """Whether frame ``i`` is far enough before frame ``j`` (frames, time, path) to be another pass."""
        p = self.p.separation
        return (
            i < j
            and j - i >= p.min_frames
            and self.frames.time(j) - self.frames.time(i) >= p.min_time
            and self.frames.distance(j) - self.frames.distance(i) >= p.min_distance
        )

    def chi2(
        self,
        a: GroupAssignment,
        r: IcpResult,
        from_map: bool,
        predicted: tuple[np.ndarray, np.ndarray],
        turn: float | None = None,
    ) -> float:
        """A fit's squared Mahalanobis distance to the prediction (pose, drift covariance); the gate's test value."""
        c = self.fitting.constraint(a, r, from_map, turn)
        cov = c.covariance + predicted[1]
        return mahalanobis2(pose_error(predicted[0], c.relative), cov)

    def decides(self, a: GroupAssignment, candidate: Candidate, estimate: PoseEstimate | None) -> bool:
        """Whether the gate alone tells this match from every look-alike seen so far (``gate.support_sigma``).

        The neighbour consensus exists because the drift can be larger than the spacing of a design's
        copies. Once loops have anchored the estimate, the gate predicts the query's place within
        ``sigma`` metres: a copy farther from the matched SGF than the gate's reach
        (``sqrt(chi2 threshold) * sigma``, plus ``consensus.exclude`` for the markings' extent) would
        have failed it. So the match needs no neighbours when
        no SGF of another group that looks like the query lies within that reach of the matched SGF
        (positions in the current estimate). A copy never seen is the risk left, as for a distinct marking.
        """
        limit, gate = self.p.gate.support_sigma, candidate.gate
        if not self.p.gate.enabled or limit is None or gate is None or not (gate.sigma_xy <= limit):
            sigma = "none" if gate is None else f"{gate.sigma_xy:.2f} m"
            self.refusal = f"the gate's sigma ({sigma}) above gate_support_sigma ({limit})"
            return False
        assert a.matched is not None
        others, distances = self.memory.other_groups_distances(np.asarray(a.descriptor.matrix), a.group_id)
        alike = others[distances <= self.p.consensus.distance]
        query_frame, query_centroid = a.descriptor.sgf.frame_index, np.asarray(a.descriptor.centroid)[:2]
        reach = math.sqrt(self.threshold) * gate.sigma_xy + self.p.consensus.exclude
        matched = self.estimate_xy(a.matched.sgf.frame_index, np.asarray(a.matched.centroid), estimate)
        for k in alike:
            if self.memory[k].frame == query_frame and np.allclose(self.memory[k].centroid, query_centroid):
                continue  # the query itself (remembered in the group it joined: another option's, in a tie)
            here = self.estimate_xy(self.memory[k].frame, self.memory[k].centroid, estimate)
            apart = float(np.hypot(*(here - matched)))
            if apart <= reach:
                self.refusal = (
                    f"a look-alike (frame {self.memory[k].frame}) {apart:.1f} m from the match, within the gate's "
                    f"reach ({reach:.1f} m)"
                )
                return False
        return True

    def estimate_xy(self, frame_index: int, centroid: np.ndarray, estimate: PoseEstimate | None) -> np.ndarray:
        """An SGF's centroid (x, y) in the current estimate (odometry before the first)."""
        pose = self.anchoring.pose(frame_index, estimate)
        return pose[:2, :2] @ np.asarray(centroid, dtype=np.float64)[:2] + pose[:2, 3]

    def earlier_member(self, a: GroupAssignment, assignments: list[GroupAssignment]) -> GroupAssignment | None:
        """The match redone with the group's closest member (eq. 10) from an earlier pass, when there is one.

        The association matches the query to its group's closest member; when that is a view of
        the same pass (the marking seen twice on the way), a member seen on an earlier pass may
        still be in the group (``assignments``: every one so far), and that pair is the loop.
        """
        j = a.descriptor.sgf.frame_index
        members = [
            m.descriptor
            for m in assignments
            if m.group_id == a.group_id
            and m.descriptor.sgf.frame_index in self.frames
            and self.separated(m.descriptor.sgf.frame_index, j)
        ]
        if not members:
            return None
        return match_closest(a, members)
