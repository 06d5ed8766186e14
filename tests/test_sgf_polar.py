"""The polar context (Sec. III-C) and the column-shifted cosine distance of eq. 10."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sgf_plugins.sgf.association.stage import OnlineGroupsParams
from sgf_plugins.shared.polar import (
    ColumnSet,
    align,
    best_shift,
    polar_context,
    ring_key,
    shift_to_yaw,
    shifted_distances,
    symmetry_spread,
    voxel_downsample,
    yaw_to_shift,
)


def rotate(points: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return points @ np.array([[c, -s], [s, c]]).T


def grid_points(inside, yaw: float = 0.0, offset=(0.0, 0.0), step: float = 0.02, extent: float = 2.0) -> np.ndarray:
    """BEV-like lattice points on a marking seen from a frame turned by ``yaw`` (and moved by ``offset``).

    A lattice point p of the viewing frame lies on the marking when R(yaw) p + offset does.
    """
    xs = np.arange(-extent, extent, step) + step / 2
    x, y = np.meshgrid(xs, xs)
    c, s = math.cos(yaw), math.sin(yaw)
    keep = inside(c * x - s * y + offset[0], s * x + c * y + offset[1])
    return np.stack([x[keep], y[keep]], axis=1)


def arrow(x, y):
    shaft = (np.abs(y) < 0.09) & (x > -0.8) & (x < 0.16)
    head = (x >= 0.16) & (x < 0.8) & (np.abs(y) < 0.3 * (0.8 - x) / 0.64)
    return shaft | head


def ell(x, y):
    return ((x > -0.4) & (x < 0.8) & (y > -0.27) & (y < -0.07)) | ((x > -0.4) & (x < -0.2) & (y > -0.27) & (y < 0.53))


def disc(x, y):
    return x**2 + y**2 < 0.3**2


def ring(x, y):
    r2 = x**2 + y**2
    return (r2 < 0.35**2) & (r2 > 0.25**2)


def describe(points: np.ndarray, bin_value="count") -> np.ndarray:
    return polar_context(points, points.mean(axis=0), 10, 90, 2.0, bin_value)


def eq10_loop(q: np.ndarray, c: np.ndarray, k: int, columns: str) -> float:
    """Eq. 10 written out column by column for shift k (query column j against candidate column j + k)."""
    n_s = q.shape[1]
    terms, compared = 0.0, 0
    for j in range(n_s):
        a, b = q[:, j], c[:, (j + k) % n_s]
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if columns == "intersection" and (na == 0 or nb == 0):
            continue
        if columns == "union" and na == 0 and nb == 0:
            continue
        compared += 1
        terms += 1.0 - (a @ b) / (na * nb) if na > 0 and nb > 0 else 1.0
    return terms / compared if compared else 1.0


def test_bins_of_hand_placed_points():
    centroid = np.zeros(2)
    points = np.array([[0.1, 0.0], [0.1, 0.001], [0.0, 0.5], [-1.9, -0.01], [2.5, 0.0]])
    m = polar_context(points, centroid, 10, 90, 2.0, "count")
    assert m.shape == (10, 90)
    assert m[0, 0] == 2  # 0.1 m ahead: ring 0, sector 0
    assert m[2, 22] == 1  # 0.5 m to the left: ring 2 (0.4-0.6 m), sector 90 deg / 4 deg = 22
    assert m[9, 45] == 1  # just below the -x axis: angle ~180.3 deg, sector 45
    assert m.sum() == 4  # the point 2.5 m away is outside L_max
    occupancy = polar_context(points, centroid, 10, 90, 2.0, "occupancy")
    assert occupancy[0, 0] == 1 and occupancy.sum() == 3
    density = polar_context(points, centroid, 10, 90, 2.0, "density")
    ring0_area = math.pi * 0.2**2 / 90
    assert density[0, 0] == pytest.approx(2 / ring0_area)
    with pytest.raises(ValueError, match="unknown bin value"):
        polar_context(points, centroid, bin_value="height")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="max_radius"):
        polar_context(points, centroid, max_radius=0.0)


def test_ring_key_is_rotation_invariant():
    pts = grid_points(arrow)
    key = ring_key(describe(pts))
    assert key.shape == (10,)
    # A rotation by whole sectors permutes columns exactly; the ring key does not change.
    turned = rotate(pts, 8 * 2 * math.pi / 90 + 1e-9)
    assert np.allclose(ring_key(describe(turned)), key)


def test_voxel_downsample():
    pts = np.array([[0.01, 0.01], [0.03, 0.03], [0.11, 0.01], [-0.01, 0.0]])
    down = voxel_downsample(pts, 0.05)
    assert len(down) == 3
    assert any(np.allclose(p, [0.02, 0.02]) for p in down)
    assert np.array_equal(voxel_downsample(pts, 0.0), pts)
    assert voxel_downsample(np.zeros((0, 2)), 0.05).shape == (0, 2)


@pytest.mark.parametrize("columns", ["intersection", "union", "all"])
def test_vectorised_eq10_equals_the_column_loop(columns: ColumnSet):
    rng = np.random.default_rng(3)
    q = rng.random((10, 90)) * (rng.random((10, 90)) < 0.3)
    q[:, 5] = 0.0
    cands = rng.random((3, 10, 90)) * (rng.random((3, 10, 90)) < 0.3)
    cands[1, :, 40:60] = 0.0
    d = shifted_distances(q, cands, columns)
    assert d.shape == (3, 90)
    for g in range(3):
        for k in (0, 1, 17, 45, 89):
            assert d[g, k] == pytest.approx(eq10_loop(q, cands[g], k, columns), abs=1e-12)


@pytest.mark.parametrize("yaw_deg", [0.0, 37.0, 90.0, 178.0, 180.0, -120.0])
def test_a_rotated_copy_matches_at_the_right_shift(yaw_deg):
    """The query is the marking rasterised again from a frame turned by ``yaw``."""
    yaw = math.radians(yaw_deg)
    member = describe(grid_points(arrow))
    query = describe(grid_points(arrow, yaw, (0.013, -0.021)))
    profile = shifted_distances(query, member[None])[0]
    k = int(np.argmin(profile))
    assert profile[k] < 0.05
    err = abs((shift_to_yaw(k, 90) - yaw + math.pi) % (2 * math.pi) - math.pi)
    assert math.degrees(err) <= 4.0 + 1e-9  # one sector
    # The wrong orientation is clearly worse: a reverse view is told apart from a forward one.
    wrong = int((k + 45) % 90)
    assert profile[wrong] > profile[k] + 0.1


def test_reverse_loop_on_a_chiral_marking_gives_180_degrees():
    member = describe(grid_points(ell))
    query = describe(grid_points(ell, math.pi + 0.03, (0.2, 0.1)))
    k = int(np.argmin(shifted_distances(query, member[None])[0]))
    assert abs(abs(math.degrees(shift_to_yaw(k, 90))) - 180.0) <= 4.0


def test_a_sliver_of_shared_columns_is_no_match_with_min_overlap():
    """Two columns of one marking line up with two of another: `intersection` alone calls it a perfect match."""
    candidate = np.zeros((10, 90))
    candidate[0, 0:30] = 1.0  # 30 columns, all ring 0
    query = np.zeros((10, 90))
    query[0, 28:30] = 1.0  # the query's 20 columns: 2 that look like the candidate's...
    query[5, 30:48] = 1.0  # ...and 18 that look like nothing in it
    assert shifted_distances(query, candidate).min() == pytest.approx(0.0)
    guarded = shifted_distances(query, candidate, min_overlap=0.5)
    # A shift must share at least 10 columns (half the query's 20); at best 2 of them are alike.
    assert guarded.min() == pytest.approx(0.8)
    assert guarded[0, 0] == 1.0  # shift 0 shares 2 columns: refused
    # A true match keeps its distance: the candidate against itself turned by 7 columns.
    turned = np.roll(candidate, 7, axis=1)
    assert shifted_distances(turned, candidate, min_overlap=0.5).min() == pytest.approx(0.0)


def test_identical_descriptors_have_zero_distance_and_empty_ones_one():
    m = describe(grid_points(arrow))
    d = shifted_distances(m, np.stack([m, m]))
    assert np.allclose(d[:, 0], 0.0)
    empty = np.zeros((10, 90))
    assert np.all(shifted_distances(empty, m[None]) == 1.0)
    assert np.all(shifted_distances(empty, empty[None]) == 1.0)
    with pytest.raises(ValueError, match="must be"):
        shifted_distances(m, np.zeros((2, 10, 60)))


SYMMETRY_THRESHOLD = OnlineGroupsParams().match.symmetry_threshold


@pytest.mark.parametrize("shape,symmetric", [(disc, True), (ring, True), (arrow, False), (ell, False)])
def test_symmetric_shapes_have_a_flat_profile(shape, symmetric):
    pts = grid_points(shape) + np.array([0.013, -0.007])  # off the lattice's own symmetry
    spread = symmetry_spread(describe(pts), "intersection")
    assert (spread < SYMMETRY_THRESHOLD) == symmetric, spread


@pytest.mark.parametrize(
    "design,spread",
    [("wheelchair", 0.072), ("coloured_zone", 0.082), ("campus_logo_ring", 0.074), ("arrow_straight", 0.580)],
)
def test_compact_shaped_markings_are_not_flagged_symmetric(design: str, spread: float):
    """The world's compact custom markings turn a profile flatter than an arrow's, but not flat: each fixes its yaw.

    A round manhole, filled by the saliency network (a disc), stays flagged (above).
    """
    from sgf_plugins.world.designs import DESIGNS
    from sgf_plugins.world.marking_raster import rasterise

    d = DESIGNS[design]
    raster = rasterise(d, *d.size, 0.02, d.colours[0], content_seed=0)
    rows, cols = np.nonzero(raster.mask)
    pts = np.stack([raster.x_top - (rows + 0.5) * 0.02, raster.y_left - (cols + 0.5) * 0.02], axis=1)
    measured = symmetry_spread(describe(pts), "intersection")
    assert measured == pytest.approx(spread, abs=0.002)
    assert measured > SYMMETRY_THRESHOLD


def test_align_and_best_shift():
    m = np.zeros((2, 90))
    m[0, 3] = 1.0
    assert align(m, 5)[0, 8] == 1.0
    assert align(m, -4)[0, 89] == 1.0
    profile = np.full(90, 0.5)
    profile[[0, 45]] = [0.10, 0.105]  # a 2-fold symmetric marking: two near-equal minima
    assert best_shift(profile) == 0
    assert best_shift(profile, prior_shift=44.0, tolerance=0.02) == 45
    assert best_shift(profile, prior_shift=44.0, tolerance=0.001) == 0
    assert best_shift(profile, prior_shift=89.5, tolerance=0.02) == 0  # circular: 89.5 is next to 0
    assert yaw_to_shift(math.pi, 90) == pytest.approx(45.0)
    assert yaw_to_shift(-math.pi / 2, 90) == pytest.approx(67.5)
    assert shift_to_yaw(45, 90) == pytest.approx(-math.pi)
