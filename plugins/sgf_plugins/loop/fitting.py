"""ICP alignment of a match (paper Sec. III-D): yaw seeds, the fit tests, one fit per alignment.

The two SGFs' point sets are aligned by 2-D ICP (:mod:`sgf_plugins.loop.icp`) seeded by the relative
yaw of the best column shift (so reverse loops converge) and by the centroids. ``GroupAssignment.yaw``
is read as the rotation (rad, counter-clockwise) that turns the new SGF's points about their centroid
onto the matched SGF's; with ``fit.seed_both_signs`` the opposite sign is tried too, so the
association's sign convention does not matter. A fit passes when it converged with a low RMS residual, a
high two-way inlier ratio and no degenerate direction. When ICP finds several distinct near-equal
fits (a twofold symmetric shape turned by 180 degrees, a row laid on itself one period on), the gate
must leave exactly one.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from sgf_pipeline.geometry import invert, wrap_angle, xy_yaw
from sgf_pipeline.types import GroupAssignment, LoopConstraint, SgfDescriptor
from sgf_plugins.loop.icp import Icp2d, IcpResult, IcpSettings, centroid_seed
from sgf_plugins.loop.params import IcpLoopParams
from sgf_plugins.shared.drift import mahalanobis2, pose_error
from sgf_plugins.shared.se2 import se2, se2_params

#: Two ICP fits that put the query's points further apart than this (RMS, m) are distinct fits of one match.
FIT_TOLERANCE_M = 0.25
#: ...and closer than this (RMS, m) they are the same stop of ICP, counted once.
SAME_FIT_M = 0.005


class IcpFitting:
    """ICP between a match's two SGFs: the fits that pass, merged per alignment, as loop constraints."""

    def __init__(self, params: IcpLoopParams) -> None:
        self.p = params
        self.settings = IcpSettings(
            metric=params.icp.metric,
            max_iterations=params.icp.max_iterations,
            max_correspondence_distance=params.icp.max_correspondence_distance,
            inlier_distance=params.icp.inlier_distance,
            tolerance=params.icp.tolerance,
            normal_neighbours=params.icp.normal_neighbours,
        )
        self.detail = ""  # what the last failed ICP missed

    def align(self, a: GroupAssignment, position_only: bool = False) -> list[IcpResult]:
        """ICP from each yaw seed: the results that pass the tests.

        For a position-only loop the heading ICP cannot fix is no failure.
        """
        assert a.matched is not None
        query, matched = a.descriptor, a.matched
        yaws = [float(a.yaw)]
        if self.p.fit.seed_both_signs:
            yaws.append(-float(a.yaw))
        n = self.p.fit.extra_yaw_seeds
        yaws += [float(a.yaw) + 2.0 * math.pi * (k + 1) / (n + 1) for k in range(n)]
        seeds = _distinct_yaws(yaws, [])
        icp = Icp2d(np.asarray(matched.points, dtype=np.float64), self.settings)
        source = np.asarray(query.points, dtype=np.float64)

        tried = [icp.align(source, centroid_seed(query.centroid, matched.centroid, y)) for y in seeds]
        good = [r for r in tried if self.passes(r, position_only)]
        if not good:
            self.detail = self.failed_fit(tried)
        return good

    def passes(self, r: IcpResult, position_only: bool = False) -> bool:
        """Whether an ICP result passes the acceptance tests: converged, RMS, two-way inliers, not degenerate.

        A position-only fit may leave its heading degenerate (that is what a round marking does).
        """
        return (
            r.converged
            and r.fitness <= self.p.icp.max_fitness
            and r.inlier_ratio >= self.p.icp.min_inlier_ratio
            and (position_only or largest_sigma(r) <= self.p.icp.degenerate_sigma)
        )

    def centred(self, results: list[IcpResult], query: SgfDescriptor) -> list[IcpResult]:
        """The best fit of a position-only match, when every fit puts the marking's centre within an inlier distance.

        Fits of a round marking differ in heading, not in where its centre lies; fits that disagree
        on the centre are two places, and the match gives no loop.
        """
        centre = np.asarray(query.centroid, dtype=np.float64)[:2]
        seen = np.array([r.transform[:2, :2] @ centre + r.transform[:2, 2] for r in results])
        apart = float(np.max(np.linalg.norm(seen - seen.mean(axis=0), axis=1))) * 2.0
        if apart > self.p.icp.inlier_distance:
            self.detail = f"fits put the marking's centre {apart:.2f} m apart ({self.p.icp.inlier_distance:g} at most)"
            return []
        return [min(results, key=lambda r: r.fitness)]

    def failed_fit(self, tried: list[IcpResult]) -> str:
        """What the fit with the most inliers of a failed ICP missed, for ``loop_candidates.csv``."""
        r = max(tried, key=lambda r: r.inlier_ratio)
        sigma = largest_sigma(r)
        return (
            f"best fit: inliers {r.inlier_ratio:.2f} ({self.p.icp.min_inlier_ratio:g} needed), "
            f"rms {r.fitness:.3f} m ({self.p.icp.max_fitness:g}), sigma {sigma:.3f} ({self.p.icp.degenerate_sigma:g})"
            + ("" if r.converged else ", not converged")
        )

    def fits(self, results: list[IcpResult], points: np.ndarray) -> list[IcpResult]:
        """The distinct near-equal fits of a match (RMS within ``fit.ambiguity_ratio`` of the best), best first.

        Several come from a twofold symmetric shape turned by 180 degrees, or from a row of
        triangles or bars laid on itself one period on. Fits that lay the query's ``points`` within
        ``FIT_TOLERANCE_M`` (RMS) of each other are one (measured on the marking, not at the
        robot, where a few degrees of yaw about the marking move the pose by its lever arm): ICP
        seeded from either side of a shallow valley (an elongated marking turned a little) stops
        on both sides of the truth, so one fit is the middle of their stops (:func:`_merged`), its
        covariance widened by their spread.
        """
        best = min(r.fitness for r in results)
        clusters: list[list[IcpResult]] = []
        for r in sorted(results, key=lambda r: r.fitness):
            if r.fitness > best * self.p.fit.ambiguity_ratio:
                break
            for cluster in clusters:
                if _displacement(r.transform, cluster[0].transform, points) <= FIT_TOLERANCE_M:
                    cluster.append(r)
                    break
            else:
                clusters.append([r])
        return [_merged(_distinct_fits(cluster, points)) for cluster in clusters]

    def select(self, results: list[IcpResult], predicted: tuple[np.ndarray, np.ndarray] | None) -> IcpResult:
        """The first fit; among several (a twofold symmetric shape), the one nearest the prediction (gate off)."""
        if predicted is None or len(results) == 1:
            return results[0]
        target, cov = predicted
        return min(results, key=lambda r: mahalanobis2(pose_error(target, _pose4(r)), cov + r.covariance))

    def constraint(self, a: GroupAssignment, r: IcpResult, from_map: bool, turn: float | None = None) -> LoopConstraint:
        """The relative pose of the query's frame in the matched frame, with the floored ICP covariance.

        The floor adds the BEV's own error, which ICP cannot see (``covariance.floor_xy``,
        ``covariance.floor_yaw_deg``). With ``turn``, a position-only loop (:func:`position_only_loop`): the
        marking's centre where ICP puts it, known to the RMS residual over the inliers plus that floor.
        """
        assert a.matched is not None
        xy2 = self.p.covariance.floor_xy**2
        floor = np.diag([xy2, xy2, math.radians(self.p.covariance.floor_yaw_deg) ** 2])
        relative, covariance, marking = _pose4(r), r.covariance + floor, None
        if turn is not None:
            centre = np.asarray(a.descriptor.centroid, dtype=np.float64)[:2]
            sigma2 = xy2 + r.fitness**2 / max(r.correspondences, 1)
            free = math.radians(self.p.symmetric.yaw_sigma_deg)
            relative, covariance = position_only_loop(relative, centre, turn, sigma2, free)
            marking = (float(centre[0]), float(centre[1]))
        return LoopConstraint(
            frame_from=a.matched.sgf.frame_index,
            frame_to=a.descriptor.sgf.frame_index,
            relative=relative,
            covariance=covariance,
            marking=marking,
            group_id=a.group_id,
            reverse=abs(xy_yaw(relative)[2]) > math.pi / 2.0,
            fitness=r.fitness,
            inlier_ratio=r.inlier_ratio,
            instance_ids=(a.matched.sgf.instance_id, a.descriptor.sgf.instance_id),
            from_map=from_map,
        )


def largest_sigma(r: IcpResult) -> float:
    """The largest standard deviation of an ICP fit's covariance (inf when it is not finite)."""
    if not np.all(np.isfinite(r.covariance)):
        return math.inf
    return math.sqrt(float(np.linalg.eigvalsh(r.covariance).max()))


def _merged(fits: list[IcpResult]) -> IcpResult:
    """One fit from ICP results of one alignment: the middle of their yaws, the best's covariance plus their spread.

    The middle is the SE(2) mean of the two fits furthest apart in yaw (ICP stops on both walls of a
    shallow valley; stops on one wall are not votes for it).
    """
    if len(fits) == 1:
        return fits[0]
    first = fits[0].transform
    offsets = np.array([se2_params(invert(first) @ r.transform) for r in fits])
    ends = offsets[[int(np.argmin(offsets[:, 2])), int(np.argmax(offsets[:, 2]))]]
    middle = first @ se2(*ends.mean(axis=0))
    spread = np.array([se2_params(invert(middle) @ r.transform) for r in fits])
    covariance = fits[0].covariance + spread.T @ spread / len(fits)
    return replace(fits[0], transform=middle, covariance=covariance)


def _distinct_yaws(yaws: list[float], taken: list[float]) -> list[float]:
    """``yaws`` without repeats (and without those in ``taken``), in order."""
    out: list[float] = []
    for y in yaws:
        if all(abs(wrap_angle(y - s)) > 1e-6 for s in taken + out):
            out.append(y)
    return out


def _distinct_fits(fits: list[IcpResult], points: np.ndarray) -> list[IcpResult]:
    """``fits`` without those laying ``points`` within ``SAME_FIT_M`` of an earlier one (the same stop of ICP)."""
    out: list[IcpResult] = []
    for r in fits:
        if all(_displacement(r.transform, o.transform, points) > SAME_FIT_M for o in out):
            out.append(r)
    return out


def _displacement(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float:
    """RMS distance (m) between ``points`` moved by the 2-D transforms ``a`` and ``b`` (3x3)."""
    delta = points @ (a[:2, :2] - b[:2, :2]).T + (a[:2, 2] - b[:2, 2])
    return float(np.sqrt(np.mean(np.sum(delta**2, axis=1))))


def position_only_loop(
    relative: np.ndarray, centre: np.ndarray, turn: float, sigma2: float, free_sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """A position-only loop: ``relative`` turned to ``turn`` about the marking at ``centre``, and its covariance.

    ``centre`` is the marking's (x, y) in the later frame; the loop keeps where ``relative`` puts
    it, with variance ``sigma2`` on that place and sigma ``free_sigma`` on the turn.
    ``relative = A(seen) Rot(turn) A(centre)^-1`` with ``A`` a translation; a perturbation of the
    turn about the marking, ``eta``, is the later frame's ``Ad(A(centre)) eta`` (GTSAM's Pose2 adjoint),
    so the covariance is that adjoint applied to ``diag(sigma2, sigma2, free_sigma^2)``. Where the two
    poses see the marking at one place, the factor's error is the turn alone, whitened by ``free_sigma``.
    """
    c = np.asarray(centre, dtype=np.float64)[:2]
    seen = relative[:2, :2] @ c + relative[:2, 3]
    out = np.eye(4)
    out[:2, :2] = [[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]]
    out[:2, 3] = seen - out[:2, :2] @ c
    adjoint = np.array([[1.0, 0.0, c[1]], [0.0, 1.0, -c[0]], [0.0, 0.0, 1.0]])
    return out, adjoint @ np.diag([sigma2, sigma2, free_sigma**2]) @ adjoint.T


def _pose4(r: IcpResult) -> np.ndarray:
    """The 4x4 planar pose of an ICP result."""
    x, y, yaw = se2_params(r.transform)
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:2, 3] = (x, y)
    return pose
