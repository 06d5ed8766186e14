"""The polar context of SGF points (Sec. III-C, after Scan Context) and its column-shifted cosine distance (eq. 10)."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

BinValue = Literal["density", "count", "occupancy"]
ColumnSet = Literal["union", "intersection", "all"]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The mean of the (N, 2) points falling in each ``voxel``-sized square cell (``voxel <= 0``: unchanged)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if voxel <= 0.0 or len(pts) == 0:
        return pts.copy()
    cells = np.floor(pts / voxel).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 2))
    np.add.at(sums, inverse, pts)
    return sums / counts[:, None]


def polar_context(
    points: np.ndarray,
    centroid: np.ndarray,
    num_rings: int = 10,
    num_sectors: int = 90,
    max_radius: float = 2.0,
    bin_value: BinValue = "count",
) -> np.ndarray:
    """The (N_r, N_s) polar descriptor of ground points around ``centroid`` within ``max_radius`` (L_max).

    Ring i spans radii [i, i + 1) * L_max / N_r; sector j spans angles [j, j + 1) * 2 pi / N_s,
    counter-clockwise from the base frame's x axis (the robot's heading). ``density`` is points per
    square metre of the bin, ``count`` the number of points, ``occupancy`` 1 where a bin has any.
    """
    if num_rings < 1 or num_sectors < 1 or not max_radius > 0.0:
        raise ValueError(
            f"need num_rings, num_sectors >= 1 and max_radius > 0, got {num_rings}, {num_sectors}, {max_radius}"
        )
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    rel = pts - np.asarray(centroid, dtype=np.float64).reshape(1, 2)
    radius = np.hypot(rel[:, 0], rel[:, 1])
    keep = radius < max_radius
    rel, radius = rel[keep], radius[keep]
    angle = np.mod(np.arctan2(rel[:, 1], rel[:, 0]), 2.0 * math.pi)
    ring = np.minimum((radius * (num_rings / max_radius)).astype(np.int64), num_rings - 1)
    sector = np.minimum((angle * (num_sectors / (2.0 * math.pi))).astype(np.int64), num_sectors - 1)
    counts = np.bincount(ring * num_sectors + sector, minlength=num_rings * num_sectors).astype(np.float64)
    matrix = counts.reshape(num_rings, num_sectors)
    if bin_value == "count":
        return matrix
    if bin_value == "occupancy":
        return (matrix > 0).astype(np.float64)
    if bin_value == "density":
        edges = np.arange(num_rings + 1) * (max_radius / num_rings)
        area = math.pi * (edges[1:] ** 2 - edges[:-1] ** 2) / num_sectors
        return matrix / area[:, None]
    raise ValueError(f"unknown bin value {bin_value!r}; expected density, count or occupancy")


def ring_key(matrix: np.ndarray) -> np.ndarray:
    """The rotation-invariant ring key: the mean of each ring over its sectors."""
    return np.asarray(matrix, dtype=np.float64).mean(axis=-1)


def _unit_columns(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns scaled to unit length (zero columns stay zero) and the mask of non-empty columns."""
    norms = np.linalg.norm(matrices, axis=-2, keepdims=True)
    occupied = norms > 0.0
    unit = np.divide(matrices, norms, out=np.zeros_like(matrices), where=occupied)
    return unit, occupied[..., 0, :]


def shifted_distances(
    query: np.ndarray, candidates: np.ndarray, columns: ColumnSet = "intersection", min_overlap: float = 0.0
) -> np.ndarray:
    """Eq. 10 at every column shift: a (G, N_s) array for a (N_r, N_s) query and (G, N_r, N_s) candidates.

    Entry ``[g, k]`` compares query column j with candidate column (j + k) mod N_s, so shift k
    means the query's frame is turned by ``k * 2 pi / N_s`` from the candidate's (its yaw in the
    candidate's frame). All shifts of all candidates come from two matrix products. ``columns``
    sets N_c and what an empty column counts: ``intersection`` averages over columns occupied in
    both descriptors (Scan Context's choice); ``union`` over columns occupied in either, a column
    empty on one side counting distance 1; ``all`` over all N_s columns, empty ones counting 1
    (eq. 10 read literally). With nothing to compare the distance is 1, and so it is at a shift where
    the columns occupied in both are fewer than ``min_overlap`` times those of the emptier
    descriptor: with ``intersection``, two columns that happen to line up would otherwise make
    a sliver match any marking at distance near 0.
    """
    q = np.asarray(query, dtype=np.float64)
    c = np.asarray(candidates, dtype=np.float64)
    if c.ndim == 2:
        c = c[None]
    if q.ndim != 2 or c.shape[1:] != q.shape:
        raise ValueError(f"query {q.shape} and candidates {c.shape} must be (N_r, N_s) and (G, N_r, N_s)")
    n_r, n_s = q.shape
    q_unit, q_occ = _unit_columns(q)
    c_unit, c_occ = _unit_columns(c)
    # Row k of the stacks is the query rolled by k columns: entry m holds query column m - k.
    index = (np.arange(n_s)[None, :] - np.arange(n_s)[:, None]) % n_s
    q_stack = q_unit[:, index].transpose(1, 0, 2).reshape(n_s, n_r * n_s)
    similarity = c_unit.reshape(len(c), n_r * n_s) @ q_stack.T
    both = c_occ.astype(np.float64) @ q_occ[index].astype(np.float64).T  # columns occupied in both, per shift
    if columns == "all":
        count = np.full(similarity.shape, float(n_s))
    elif columns == "union":
        count = q_occ.sum() + c_occ.sum(axis=1, keepdims=True) - both
    elif columns == "intersection":
        count = both
    else:
        raise ValueError(f"unknown column set {columns!r}; expected union, intersection or all")
    distance = np.ones_like(similarity)
    valid = count > 0
    if min_overlap > 0.0:
        valid &= both >= min_overlap * np.minimum(c_occ.sum(axis=1, keepdims=True), q_occ.sum())
    np.divide(count - similarity, count, out=distance, where=valid)
    return np.clip(distance, 0.0, 1.0)


def best_shift(profile: np.ndarray, prior_shift: float | None = None, tolerance: float = 0.0) -> int:
    """The shift of smallest distance; among shifts within ``tolerance`` of it, the closest to ``prior_shift``."""
    p = np.asarray(profile, dtype=np.float64)
    k = int(np.argmin(p))
    if prior_shift is None or tolerance <= 0.0:
        return k
    near = np.flatnonzero(p <= p[k] + tolerance)
    n = len(p)
    gap = np.abs((near - prior_shift + n / 2.0) % n - n / 2.0)
    return int(near[int(np.argmin(gap))])


def shift_to_yaw(shift: int, num_sectors: int) -> float:
    """The relative yaw (rad, in [-pi, pi)) of a column shift: ``shift * 2 pi / N_s``."""
    return (shift * 2.0 * math.pi / num_sectors + math.pi) % (2.0 * math.pi) - math.pi


def yaw_to_shift(yaw: float, num_sectors: int) -> float:
    """The (fractional) column shift in [0, N_s) of a relative yaw."""
    return (yaw * num_sectors / (2.0 * math.pi)) % num_sectors


def symmetry_spread(matrix: np.ndarray, columns: ColumnSet = "intersection") -> float:
    """Max minus min of a descriptor's distance to its own column shifts: near 0 for a disc or a ring."""
    profile = shifted_distances(matrix, matrix[None], columns)[0]
    return float(profile.max() - profile.min())


def align(matrix: np.ndarray, shift: int) -> np.ndarray:
    """A descriptor turned by ``shift`` columns, so that its column j lands on column j + shift."""
    return np.roll(np.asarray(matrix), shift, axis=-1)
