"""2-D ICP between two SGF point sets (paper Sec. III-D), vectorised over points with a k-d tree.

A rigid 2-D transform is a 3x3 homogeneous matrix ``T`` (:mod:`sgf_plugins.shared.se2`) that maps source
points into the target frame: ``q = R p + t``. The covariance of a result is over the local (right)
perturbation of ``T``, ``T Exp(xi)`` with ``xi = (x, y, yaw)``: the tangent convention of GTSAM's ``Pose2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from sgf_plugins.shared.se2 import apply, se2, se2_params

Metric = Literal["point_to_point", "point_to_line"]


def _perp(points: np.ndarray) -> np.ndarray:
    """``(-y, x)``: the derivative of a rotation by a small angle about the origin."""
    return np.stack([-points[:, 1], points[:, 0]], axis=1)


def line_normals(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Unit normals (N, 2) of the local line through each point's ``neighbours`` nearest points (PCA)."""
    from scipy.spatial import cKDTree

    k = min(max(neighbours, 2), len(points))
    _, idx = cKDTree(points).query(points, k=k)
    local = points[idx] - points[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", local, local)
    _, vectors = np.linalg.eigh(cov)
    return vectors[:, :, 0]  # eigenvector of the smallest eigenvalue


@dataclass(frozen=True)
class IcpResult:
    """The outcome of one ICP alignment of a source point set onto a target point set."""

    transform: np.ndarray
    converged: bool
    iterations: int
    fitness: float
    inlier_ratio: float
    covariance: np.ndarray
    correspondences: int

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, yaw)`` of the transform."""
        return se2_params(self.transform)


@dataclass(frozen=True)
class IcpSettings:
    """How ICP pairs points, when it stops, and what it calls an inlier."""

    metric: Metric = "point_to_point"
    max_iterations: int = 100
    max_correspondence_distance: float = 0.5
    inlier_distance: float = 0.1
    tolerance: float = 1e-6
    normal_neighbours: int = 8


class Icp2d:
    """ICP of source point sets onto one target point set (its k-d tree and normals built once)."""

    def __init__(self, target: np.ndarray, settings: IcpSettings) -> None:
        self.target = np.asarray(target, dtype=np.float64)
        if self.target.ndim != 2 or self.target.shape[1] != 2 or len(self.target) < 3:
            raise ValueError(f"ICP target must be (N>=3, 2) points, got shape {self.target.shape}")
        from scipy.spatial import cKDTree  # imported here, so that listing plugins stays fast

        self.settings = settings
        self.tree = cKDTree(self.target)
        self.normals = line_normals(self.target, settings.normal_neighbours)

    def _step(self, moved: np.ndarray, matched: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The increment (3x3, applied on the left) that best aligns ``moved`` onto its matches."""
        if self.settings.metric == "point_to_point":
            # Closed-form 2-D Kabsch on the paired points.
            mp, mq = moved.mean(axis=0), matched.mean(axis=0)
            h = (moved - mp).T @ (matched - mq)
            yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
            c, s = math.cos(yaw), math.sin(yaw)
            rot = np.array([[c, -s], [s, c]])
            step = np.eye(3)
            step[:2, :2] = rot
            step[:2, 2] = mq - rot @ mp
            return step
        normals = self.normals[rows]
        residual = np.einsum("ni,ni->n", normals, moved - matched)
        jac = np.concatenate([normals, np.einsum("ni,ni->n", normals, _perp(moved))[:, None]], axis=1)
        hessian = jac.T @ jac + 1e-9 * np.eye(3)
        dx, dy, dyaw = np.linalg.solve(hessian, -jac.T @ residual)
        return se2(float(dx), float(dy), float(dyaw))

    def align(self, source: np.ndarray, initial: np.ndarray) -> IcpResult:
        """Align ``source`` (N, 2) onto the target starting from the 3x3 transform ``initial``."""
        source = np.asarray(source, dtype=np.float64)
        if source.ndim != 2 or source.shape[1] != 2 or len(source) < 3:
            raise ValueError(f"ICP source must be (N>=3, 2) points, got shape {source.shape}")
        cfg = self.settings
        transform = np.array(initial, dtype=np.float64)
        converged = starved = False
        iterations = 0
        # Two rounds: pair within the coarse distance, then refine with inliers only. Convergence is the
        # inlier round's: on two 2 cm voxel grids the coarse pairs keep changing and the pose wanders by
        # fractions of a millimetre without settling, which says nothing about the fit.
        for gate in (cfg.max_correspondence_distance, cfg.inlier_distance):
            for _ in range(cfg.max_iterations):
                iterations += 1
                moved = apply(transform, source)
                dist, rows = self.tree.query(moved, k=1, distance_upper_bound=gate)
                keep = np.isfinite(dist)
                if keep.sum() < 3:
                    converged, starved = False, True
                    break
                step = self._step(moved[keep], self.target[rows[keep]], rows[keep])
                transform = step @ transform
                dx, dy, dyaw = se2_params(step)
                converged = math.hypot(dx, dy) < cfg.tolerance and abs(dyaw) < cfg.tolerance
                if converged:
                    break
            if starved:
                break
        return self._evaluate(source, transform, converged, iterations)

    def _evaluate(self, source: np.ndarray, transform: np.ndarray, converged: bool, iterations: int) -> IcpResult:
        """Fitness, two-way inlier ratio and the Hessian covariance of a final transform."""
        from scipy.spatial import cKDTree

        cfg = self.settings
        moved = apply(transform, source)
        dist, rows = self.tree.query(moved, k=1)
        inlier = dist < cfg.inlier_distance
        back, _ = cKDTree(moved).query(self.target, k=1)
        ratio = min(float(inlier.mean()), float((back < cfg.inlier_distance).mean()))
        n = int(inlier.sum())
        if n < 4:
            return IcpResult(transform, False, iterations, math.inf, ratio, np.full((3, 3), np.inf), n)
        fitness = float(np.sqrt(np.mean(dist[inlier] ** 2)))
        # Covariance from the point-to-line Hessian at the solution, whatever the metric: residuals
        # along the target's normals see the geometry's degeneracies (a straight bar slides along
        # itself), which point-to-point residuals with fixed pairs hide.
        rot = transform[:2, :2]
        normals = self.normals[rows[inlier]]
        residual = np.einsum("ni,ni->n", normals, moved[inlier] - self.target[rows[inlier]])
        # Jacobian of n . (T Exp(xi) p) with respect to the local perturbation xi: n^T [R, R perp(p)].
        jac = np.concatenate(
            [normals @ rot, np.einsum("ni,ni->n", normals, _perp(source[inlier]) @ rot.T)[:, None]], axis=1
        )
        hessian = jac.T @ jac
        sigma2 = float(residual @ residual) / max(n - 3, 1)
        covariance = np.full((3, 3), np.inf)
        if np.linalg.cond(hessian) < 1e8:
            covariance = sigma2 * np.linalg.inv(hessian)
        return IcpResult(transform, converged, iterations, fitness, ratio, covariance, n)


def centroid_seed(source_centroid: np.ndarray, target_centroid: np.ndarray, yaw: float) -> np.ndarray:
    """The transform that turns the source by ``yaw`` about its centroid and lays it on the target's."""
    seed = se2(0.0, 0.0, yaw)
    seed[:2, 2] = np.asarray(target_centroid, dtype=np.float64) - seed[:2, :2] @ np.asarray(source_centroid)
    return seed
