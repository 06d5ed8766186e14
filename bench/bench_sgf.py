"""SGF benchmark: eq. 10 search speed, stage costs, and the measurements behind the SGF defaults.

Run: ``.venv/bin/python bench/bench_sgf.py [--quick]``. Prints ratios measured in this run; the
figures recorded in bench/RESULTS.md (section ``## sgf``) come from it.
"""

from __future__ import annotations

import argparse
import itertools
import math
import platform
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from sgf_plugins.sgf.association.stage import OnlineGroupsParams, OnlineSgfGroups
from sgf_plugins.sgf.descriptor import PolarContext, PolarContextParams
from sgf_plugins.sgf.detector import HuMomentDetector, HuWindowParams
from sgf_plugins.sgf.hu import HuScale, hu_distance, hu_moments
from sgf_plugins.sgf.regions import border_band
from sgf_plugins.shared.polar import (
    BinValue,
    ColumnSet,
    polar_context,
    shift_to_yaw,
    shifted_distances,
    symmetry_spread,
    voxel_downsample,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test suite's synthetic drive
from sgf_synthetic import (
    DEFAULT_GRID,
    Annulus,
    ConvexPart,
    GroundShape,
    SaliencyStream,
    arrow_shape,
    chevron_shape,
    ell_shape,
    fov_valid_mask,
    plus_shape,
    rectangle,
    render_saliency,
    straight_path,
    tee_shape,
    triangle_shape,
)

from sgf_pipeline import RunContext
from sgf_pipeline.geometry import pose_from_xy_yaw, wrap_angle

#: The two readings of eq. 8.
SCALES: tuple[HuScale, ...] = ("raw", "log")

#: Marking shapes and their order of rotational symmetry (0 = round).
SHAPES: dict[str, tuple[tuple, int]] = {
    "arrow": (arrow_shape(), 1),
    "arrow_small": (arrow_shape(1.2, 0.5, 0.15), 1),
    "ell": (ell_shape(), 1),
    "tee": (tee_shape(), 1),
    "chevron": (chevron_shape(), 1),
    "triangle": (triangle_shape(), 3),
    "rectangle": ((rectangle(1.5, 0.3),), 2),
    "bar": ((rectangle(0.4, 1.8),), 2),
    "diamond": ((ConvexPart(np.array([[-0.8, 0.0], [0.0, -0.4], [0.8, 0.0], [0.0, 0.4]])),), 2),
    "plus": (plus_shape(), 4),
    "disc": ((Annulus(0.3),), 0),
    "ring": ((Annulus(0.35, 0.25),), 0),
}


def best_of(fn: Callable[[], object], repeat: int = 5) -> float:
    """Fastest wall time of ``repeat`` calls (seconds)."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def noisy_mask(probability: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """Binarised saliency with a blurred edge and smooth noise (about one pixel of boundary jitter)."""
    if noise > 0.0:
        field = cv2.GaussianBlur(rng.normal(0.0, 1.0, probability.shape).astype(np.float32), (0, 0), 3.0)
        probability = cv2.GaussianBlur(probability, (0, 0), 1.0) + noise * field
    return probability >= 0.5


def largest_region(mask: np.ndarray) -> np.ndarray:
    """(N, 2) pixels (u, v) of the largest connected region."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    v, u = np.nonzero(labels == k)
    return np.stack([u, v], axis=1)


# -- 1. eq. 8: raw or log-scaled Hu invariants ----------------------------------------------------


def measure_hu_scale(rng: np.random.Generator, quick: bool) -> None:
    """Eq. 8 distances between consecutive views of rendered markings passing through the BEV."""
    print("\n## eq. 8: distance between consecutive views (robot 0.15 m/frame, heading jitter 0.3 deg)")
    valid = fov_valid_mask(DEFAULT_GRID)
    band = border_band(valid, 1)
    print(
        "| scale | noise | interior median | interior p90 | interior < 0.005 | entering/leaving < 0.005 "
        "| different shapes min |"
    )
    print("|---|---|---|---|---|---|---|")
    names = ["arrow", "ell", "tee", "rectangle", "diamond", "disc"] if not quick else ["arrow", "rectangle", "disc"]
    for noise in (0.0, 0.3):
        per_shape: dict[str, np.ndarray] = {}
        interior: dict[str, list[float]] = {"raw": [], "log": []}
        border: dict[str, list[float]] = {"raw": [], "log": []}
        for name in names:
            parts, _ = SHAPES[name]
            shape = GroundShape(parts, (8.0, 0.0, rng.uniform(-0.4, 0.4)))
            yaw, y = 0.0, rng.uniform(-0.3, 0.3)
            views = []
            for i in range(40 if not quick else 20):
                yaw += rng.normal(0.0, 0.005)
                x = 2.1 + i * (0.15 if not quick else 0.3)
                probability, _ = render_saliency([shape], pose_from_xy_yaw(x, y, yaw), DEFAULT_GRID, valid, 2)
                mask = noisy_mask(probability, rng, noise) & valid
                if mask.sum() < 150:
                    continue
                pixels = largest_region(mask)
                views.append((hu_moments(pixels), bool(band[pixels[:, 1], pixels[:, 0]].any())))
            for (ha, ta), (hb, tb) in itertools.pairwise(views):
                for scale in SCALES:
                    (border if ta or tb else interior)[scale].append(hu_distance(ha, hb, scale))
            per_shape[name] = next(h for h, t in views[len(views) // 2 :] if not t)
        for scale in SCALES:
            inner, edge = np.array(interior[scale]), np.array(border[scale])
            cross = [hu_distance(per_shape[a], per_shape[b], scale) for a, b in itertools.combinations(per_shape, 2)]
            print(
                f"| {scale} | {noise} | {np.median(inner):.4f} | {np.percentile(inner, 90):.4f} | "
                f"{np.mean(inner < 0.005):.2f} | {np.mean(edge < 0.005):.2f} | {min(cross):.4f} |"
            )


# -- 2. the descriptor's bin value ------------------------------------------------------------------


def measure_bin_values(rng: np.random.Generator, quick: bool) -> None:
    """Eq. 10 between views of the same marking from other headings, and between different markings."""
    print("\n## polar context bin value (12 markings x 5 headings, noisy masks, L_max 2 m, 10 x 90)")
    headings = [0.0, 0.7, math.pi, math.pi + 0.3, -1.9] if not quick else [0.0, math.pi + 0.3]
    views: dict[str, list[tuple[float, np.ndarray]]] = {}
    valid = np.ones((DEFAULT_GRID.height, DEFAULT_GRID.width), dtype=bool)
    for name, (parts, _) in SHAPES.items():
        shape = GroundShape(parts, (0.0, 0.0, rng.uniform(-math.pi, math.pi)))
        views[name] = []
        for heading in headings:
            d, lat = rng.uniform(2.6, 3.4), rng.uniform(-0.3, 0.3)
            px = -d * math.cos(heading) + lat * math.sin(heading)
            py = -d * math.sin(heading) - lat * math.cos(heading)
            probability, _ = render_saliency([shape], pose_from_xy_yaw(px, py, heading), DEFAULT_GRID, valid, 2)
            pixels = largest_region(noisy_mask(probability, rng, 0.3))
            x, y = DEFAULT_GRID.pixel_to_ground(pixels[:, 0], pixels[:, 1])
            views[name].append((heading, np.stack([x, y], axis=1)))
    print(
        "| bin value | columns | same p50 | same p95 | different p5 | different min | yaw error p50 / p95 (deg) "
        "| spread disc, ring | spread min other |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    settings: list[tuple[BinValue, ColumnSet]] = list(
        itertools.product(("density", "count", "occupancy"), ("union", "intersection"))
    )
    for bin_value, columns in settings:
        desc = {
            n: [(h, polar_context(p, p.mean(axis=0), bin_value=bin_value)) for h, p in vs] for n, vs in views.items()
        }
        same, cross, yaw_err = [], [], []
        for name, ds in desc.items():
            order = SHAPES[name][1]
            for (ha, a), (hb, b) in itertools.combinations(ds, 2):
                profile = shifted_distances(b, a[None], columns)[0]
                k = int(np.argmin(profile))
                same.append(profile[k])
                if order >= 1:
                    period = 2.0 * math.pi / order
                    err = abs(wrap_angle(shift_to_yaw(k, 90) - (hb - ha)))
                    yaw_err.append(math.degrees(min(err % period, period - err % period)))
        for name_a, name_b in itertools.combinations(desc, 2):
            for (_, da), (_, db) in itertools.product(desc[name_a][:2], desc[name_b][:2]):
                cross.append(shifted_distances(db, da[None], columns)[0].min())
        spread = {n: np.mean([symmetry_spread(d, columns) for _, d in ds]) for n, ds in desc.items()}
        other = min(v for n, v in spread.items() if SHAPES[n][1] != 0)
        print(
            f"| {bin_value} | {columns} | {np.median(same):.3f} | {np.percentile(same, 95):.3f} | "
            f"{np.percentile(cross, 5):.3f} | {np.min(cross):.3f} | {np.median(yaw_err):.1f} / "
            f"{np.percentile(yaw_err, 95):.1f} | {spread['disc']:.3f}, {spread['ring']:.3f} | {other:.3f} |"
        )
    print("\n| voxel (m), count bins, intersection | same p50 | same p95 | different p5 |")
    print("|---|---|---|---|")
    for voxel in (0.02, 0.04, 0.06):
        by_voxel: dict[str, list[np.ndarray]] = {
            n: [
                polar_context(q, q.mean(axis=0), bin_value="count") for q in (voxel_downsample(p, voxel) for _, p in vs)
            ]
            for n, vs in views.items()
        }
        same = [
            shifted_distances(b, a[None])[0].min() for ds in by_voxel.values() for a, b in itertools.combinations(ds, 2)
        ]
        cross = [
            shifted_distances(db, da[None])[0].min()
            for name_a, name_b in itertools.combinations(by_voxel, 2)
            for da, db in itertools.product(by_voxel[name_a][:2], by_voxel[name_b][:2])
        ]
        print(f"| {voxel} | {np.median(same):.3f} | {np.percentile(same, 95):.3f} | {np.percentile(cross, 5):.3f} |")


# -- 3. eq. 10 search: vectorised against a per-shift loop -------------------------------------------


def loop_distances(query: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """The baseline: eq. 10 (columns occupied in both) shift by shift and column by column in Python."""
    n_s = query.shape[1]
    out = np.ones((len(candidates), n_s))
    q_norm = [float(np.linalg.norm(query[:, j])) for j in range(n_s)]
    for g, cand in enumerate(candidates):
        c_norm = [float(np.linalg.norm(cand[:, j])) for j in range(n_s)]
        for k in range(n_s):
            total, used = 0.0, 0
            for j in range(n_s):
                a, b = q_norm[j], c_norm[(j + k) % n_s]
                if a > 0.0 and b > 0.0:
                    used += 1
                    total += 1.0 - float(query[:, j] @ cand[:, (j + k) % n_s]) / (a * b)
            out[g, k] = total / used if used else 1.0
    return out


def bench_search(rng: np.random.Generator, quick: bool) -> None:
    """Search one query against G group descriptors over all 90 shifts."""
    print("\n## eq. 10 search over all 90 column shifts (one query against G groups)")
    print("| groups | vectorised (ms) | per-shift loop (ms) | speed-up |")
    print("|---|---|---|---|")
    for groups in (100, 1000) if not quick else (100,):
        candidates = rng.random((groups, 10, 90)) * (rng.random((groups, 10, 90)) < 0.2)
        query = candidates[groups // 2] * rng.uniform(0.9, 1.1, (10, 90))
        fast = shifted_distances(query, candidates)
        base_groups = groups if groups <= 100 else 100
        slow = loop_distances(query, candidates[:base_groups])
        assert np.allclose(fast[:base_groups], slow, atol=1e-9), "vectorised eq. 10 differs from the loop"
        few = candidates[:base_groups]
        t_fast = best_of(partial(shifted_distances, query, candidates))
        t_slow = best_of(partial(loop_distances, query, few), 1) * groups / base_groups
        note = "" if base_groups == groups else f" (loop timed on {base_groups}, scaled)"
        print(f"| {groups} | {1e3 * t_fast:.2f} | {1e3 * t_slow:.0f}{note} | {t_slow / t_fast:.0f}x |")


# -- 4. stage costs ----------------------------------------------------------------------------------


def bench_stages(quick: bool) -> None:
    """Per-call time of the three stages on a synthetic drive past six markings."""
    print("\n## stage costs (synthetic drive, 256 x 256 BEV, 6 markings)")
    shapes = [
        GroundShape(SHAPES[n][0], (5.0 + 4.0 * i, 0.3 * (-1) ** i, 0.4 * i), i + 1)
        for i, n in enumerate(["arrow", "ell", "disc", "tee", "rectangle", "chevron"])
    ]
    poses = straight_path((0.0, 0.0, 0.0), 0.2, 150 if not quick else 60)
    frames = list(SaliencyStream(shapes, poses, supersample=2))
    context = RunContext(None)
    detector = HuMomentDetector(HuWindowParams())
    descriptor = PolarContext(PolarContextParams())
    association = OnlineSgfGroups(OnlineGroupsParams())
    for stage in (detector, descriptor, association):
        stage.begin(context)
    t_det = t_des = t_asc = 0.0
    n_sgf = 0
    for frame, bev, saliency in frames:
        t0 = time.perf_counter()
        sgfs = detector.process(frame, bev, saliency)
        t1 = time.perf_counter()
        descriptors = descriptor.process(frame, sgfs)
        t2 = time.perf_counter()
        association.process(frame, descriptors, None)
        t3 = time.perf_counter()
        t_det, t_des, t_asc = t_det + t1 - t0, t_des + t2 - t1, t_asc + t3 - t2
        n_sgf += len(sgfs.items)
    n = len(frames)
    print("| stage | per frame (ms) | per SGF (ms) |")
    print("|---|---|---|")
    print(f"| detector=hu_window | {1e3 * t_det / n:.2f} | - |")
    print(f"| descriptor=polar_context | {1e3 * t_des / n:.3f} | {1e3 * t_des / max(n_sgf, 1):.2f} |")
    print(f"| association=online_groups | {1e3 * t_asc / n:.3f} | {1e3 * t_asc / max(n_sgf, 1):.2f} |")
    print(f"({n} frames, {n_sgf} SGFs selected)")


def bench_ground_lift(quick: bool) -> None:
    """Per-SGF cost of eq. 9 on the BEV's plane against the lift onto the driven ground (``descriptor.ground``)."""
    from sgf_plugins.sgf.descriptor import describe, lift_driven
    from sgf_plugins.shared.bev_homography import bev_to_image_homography
    from sgf_synthetic import toy_calibration

    from sgf_pipeline.types import SalientGroundFeature

    print("\n## SGF lift: BEV plane vs driven ground (one SGF, 1.5 x 0.9 m marking 3.5-5 m ahead)")
    calibration = toy_calibration()
    u, v = np.meshgrid(np.arange(DEFAULT_GRID.width), np.arange(DEFAULT_GRID.height))
    x, y = DEFAULT_GRID.pixel_to_ground(u.ravel(), v.ravel())
    inside = (x >= 3.5) & (x <= 5.0) & (np.abs(y) <= 0.45)
    pixels = np.stack([u.ravel()[inside], v.ravel()[inside]], axis=1)
    homography = bev_to_image_homography(calibration, DEFAULT_GRID)
    sgf = SalientGroundFeature(0, 0, 0.0, np.eye(4), pixels, DEFAULT_GRID, 1.0, np.zeros(7), 3, homography=homography)
    grade = 0.05
    driven = np.array([pose_from_xy_yaw(0.25 * k, 0.0, 0.0) for k in range(30)])  # 7.5 m driven
    driven[16:, 2, 3] = (np.arange(14) + 1) * 0.25 * grade  # rising 5 % from 4 m on (heights only: timing)
    params = PolarContextParams()
    repeat = 3 if quick else 20
    t_plane = best_of(lambda: describe(sgf, params), repeat)
    contacts = params.ground_contacts
    t_base = best_of(lambda: describe(sgf, params, lift_driven(sgf, calibration, driven, 3.0, 3.0)), repeat)
    t_wheels = best_of(lambda: describe(sgf, params, lift_driven(sgf, calibration, driven, 3.0, 3.0, contacts)), repeat)
    print("| lift | per SGF (ms) |")
    print("|---|---|")
    print(f"| plane (eq. 9) | {1e3 * t_plane:.2f} |")
    print(f"| driven ground, ground_model=base (nearest tangent plane) | {1e3 * t_base:.2f} |")
    print(f"| driven ground, ground_model=wheels (tracks at {contacts} m, marched rays) | {1e3 * t_wheels:.2f} |")
    print(
        f"({len(pixels)} pixels, {len(driven)} poses; base / plane = {t_base / t_plane:.1f}x, "
        f"wheels / plane = {t_wheels / t_plane:.1f}x)"
    )


def main() -> None:
    """Run every section."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="smaller runs (a smoke test of the bench)")
    args = parser.parse_args()
    rng = np.random.default_rng(7)
    print(
        f"machine: {platform.machine()}, {platform.processor() or 'cpu'}, numpy {np.__version__}, "
        f"python {platform.python_version()}"
    )
    bench_search(rng, args.quick)
    bench_stages(args.quick)
    bench_ground_lift(args.quick)
    measure_hu_scale(rng, args.quick)
    measure_bin_values(rng, args.quick)


if __name__ == "__main__":
    main()
