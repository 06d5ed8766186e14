"""Distance travelled shortened by absorbed loop closures (the drift both gates allow for)."""

from __future__ import annotations

import numpy as np
import pytest
from sgf_plugins.shared.anchoring import anchored_distances


def test_without_shortcuts_it_is_the_distance_along_the_path() -> None:
    out = anchored_distances(10.0, np.array([0.0, 10.0, 25.0]), [])
    np.testing.assert_allclose(out, [10.0, 0.0, 15.0])


def test_a_closed_loop_joins_its_two_frames_at_no_cost() -> None:
    # a loop closed between 100 m and 900 m of travel: 905 m is 5 m from 100 m and 15 m from 120 m
    out = anchored_distances(905.0, np.array([100.0, 120.0, 880.0, 500.0]), [(100.0, 900.0)])
    np.testing.assert_allclose(out, [5.0, 25.0, 25.0, 405.0])


def test_shortcuts_chain_and_the_direct_path_wins_when_shorter() -> None:
    shortcuts = [(0.0, 500.0), (520.0, 1000.0)]
    out = anchored_distances(1003.0, np.array([2.0, 510.0, 990.0]), shortcuts)
    # 1003 -> 1000 -> 520 -> 500 -> 0 -> 2: 3 + 20 + 2 = 25; 510: 3 + 10 = 13; 990: direct 13
    np.testing.assert_allclose(out, [25.0, 13.0, 13.0])


def test_unknown_targets_stay_unknown() -> None:
    out = anchored_distances(5.0, np.array([np.nan, 1.0]), [(0.0, 4.0)])
    assert np.isnan(out[0])
    assert out[1] == pytest.approx(2.0)  # 5 -> 4, the loop to 0, then 1 m: shorter than the direct 4 m


def test_it_matches_a_brute_force_shortest_path() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        shortcuts = [tuple(sorted(rng.uniform(0, 1000, 2))) for _ in range(rng.integers(1, 6))]
        start = float(rng.uniform(0, 1000))
        targets = rng.uniform(0, 1000, 20)
        points = np.unique([start, *(s for pair in shortcuts for s in pair), *targets])
        n = len(points)
        d = np.abs(points[:, None] - points[None, :])
        where = {v: k for k, v in enumerate(points)}
        for a, b in shortcuts:
            d[where[a], where[b]] = d[where[b], where[a]] = 0.0
        for k in range(n):  # Floyd-Warshall
            d = np.minimum(d, d[:, k : k + 1] + d[k : k + 1, :])
        expected = [d[where[start], where[t]] for t in targets]
        np.testing.assert_allclose(anchored_distances(start, targets, shortcuts), expected, atol=1e-9)
