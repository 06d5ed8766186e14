"""Laying out a campus: the path network, plazas, hills, buildings, trees, lamps, speed bumps and rough paving.

Everything is laid out once per ``(seed, scale)``: the network's node positions (and the hills)
are multiplied by ``scale`` so that a route keeps its shape and its revisits at any scale, while
path widths, markings, bumps and buildings keep their physical size. The markings and the people
and vehicles are placed by :mod:`~sgf_plugins.world.marking_placement` and
:mod:`~sgf_plugins.world.agent_placement`.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_plugins.world.agent_placement import place_agents
from sgf_plugins.world.designs import MarkingDesign
from sgf_plugins.world.layout import (
    MATERIAL_ID,
    Building,
    CampusLayout,
    Hill,
    Lamp,
    PathEdge,
    Plaza,
    RoughPatch,
    Segment,
    SpeedBump,
    Tree,
)
from sgf_plugins.world.marking_placement import place_markings
from sgf_plugins.world.noise import rng_for

# --- the network (scale-1 coordinates, metres; x east, y north) ---------------------------------

_COLS = {"A": 0.0, "B": 130.0, "C": 260.0, "D": 390.0, "E": 520.0}
_ROWS = {"0": 0.0, "1": 110.0, "2": 220.0, "3": 330.0}
NODES: dict[str, tuple[float, float]] = {c + r: (x, y) for c, x in _COLS.items() for r, y in _ROWS.items()}
NODES["BC1"] = (195.0, 110.0)
NODES["H"] = (114.0, 93.0)
NODES["DO"] = (160.0, 166.0)


@dataclass(frozen=True)
class EdgeSpec:
    """A path between two nodes: width (m), surface, and a sideways bow of its middle (m)."""

    a: str
    b: str
    width: float
    material: str | None = None
    bow: float = 0.0


def _edge_specs() -> list[EdgeSpec]:
    specs: list[EdgeSpec] = []
    cols = list(_COLS)
    for r in _ROWS:
        for c0, c1 in itertools.pairwise(cols):
            a, b = c0 + r, c1 + r
            if r == "1":
                if a == "B1":
                    specs += [EdgeSpec("B1", "BC1", 6.0, "asphalt"), EdgeSpec("BC1", "C1", 6.0, "asphalt")]
                    continue
                specs.append(EdgeSpec(a, b, 6.0, "asphalt"))
            elif r in ("0", "3"):
                specs.append(EdgeSpec(a, b, 4.0))
            else:
                specs.append(EdgeSpec(a, b, 3.0, bow=7.0 if c0 in "BD" else 0.0))
    for c in cols:
        rows = list(_ROWS)
        for r0, r1 in itertools.pairwise(rows):
            width = 5.0 if c == "C" else (4.0 if c in "AE" else 3.0)
            specs.append(EdgeSpec(c + r0, c + r1, width, "asphalt" if c == "C" else None, bow=5.0 if c == "B" else 0.0))
    specs += [
        EdgeSpec("BC1", "B2", 2.5, "bricks", bow=-6.0),
        EdgeSpec("D0", "E1", 2.2, "slabs", bow=8.0),
        EdgeSpec("C2", "D3", 2.5, "bricks", bow=-10.0),
        EdgeSpec("A2", "B3", 2.2, "slabs", bow=6.0),
        EdgeSpec("H", "B1", 2.6, "slabs"),
        EdgeSpec("BC1", "DO", 2.6, "bricks", bow=4.0),
        EdgeSpec("DO", "B1", 2.4, "slabs", bow=-5.0),
    ]
    return specs


EDGE_SPECS: tuple[EdgeSpec, ...] = tuple(_edge_specs())


#: Paths longer than this (m) may have rough paving.
ROUGH_PATH_LENGTH = 20.0


@dataclass(frozen=True)
class LayoutOptions:
    """Knobs of the layout that the dataset exposes as parameters."""

    marking_spacing: float = 26.0
    custom_fraction: float = 0.5
    pedestrians_per_km: float = 30.0
    vehicles_per_km: float = 4.0
    bump_probability: float = 0.3
    rough_paving_per_km: float = 0.0  # more rough patches, per km of every path over 20 m
    designs: tuple[MarkingDesign, ...] = ()


def build_layout(seed: int, scale: float, options: LayoutOptions) -> CampusLayout:
    """Lay out the campus for a seed and a scale."""
    rng = rng_for(seed, 1)
    nodes = {k: np.array(v, np.float64) * scale for k, v in NODES.items()}
    # Small seeded jitter of the inner nodes keeps every seed's campus a little different.
    for k in nodes:
        if k not in ("H",) and k[0] in "BCD" and k[-1] in "12":
            nodes[k] = nodes[k] + rng.uniform(-4.0, 4.0, 2) * scale
    nodes["H"] = nodes["B1"] + (np.array(NODES["H"]) - np.array(NODES["B1"]))

    edges: list[PathEdge] = []
    for i, spec in enumerate(EDGE_SPECS):
        material = spec.material or str(rng.choice(["slabs", "bricks", "slabs", "asphalt"]))
        pts = _bowed(nodes[spec.a], nodes[spec.b], spec.bow * scale)
        edges.append(PathEdge(i, spec.a, spec.b, pts, spec.width, material))

    plazas: list[Plaza] = []
    for name, pos in nodes.items():
        widths = [e.width for e in edges if name in (e.a, e.b)]
        if name == "H":
            plazas.append(Plaza(pos, 2.4, False, "slabs"))
            continue
        if name == "DO":  # the drop-off: a small square at a dormitory entrance
            plazas.append(Plaza(pos, 4.0, False, "bricks"))
            continue
        big = name in ("C1", "A0", "B2", "D2")
        half = max(widths) / 2 + (6.0 if big else 1.6)
        material = "bricks" if big else str(rng.choice(["slabs", "bricks"]))
        plazas.append(Plaza(pos, half, big and name in ("C1", "D2"), material))

    segments: list[Segment] = []
    for e in edges:
        trimmed = e.points
        for a, b in itertools.pairwise(trimmed):
            s0 = float(np.linalg.norm(a - e.points[0]))
            segments.append(Segment(a.copy(), b.copy(), e.width / 2, MATERIAL_ID[e.material], e.index, s0))

    lo = np.min([p for p in nodes.values()], axis=0) - 60.0
    hi = np.max([p for p in nodes.values()], axis=0) + 60.0
    layout = CampusLayout(
        seed=seed,
        scale=scale,
        nodes=nodes,
        edges=edges,
        segments=segments,
        plazas=plazas,
        buildings=[],
        trees=[],
        lamps=[],
        bumps=[],
        rough=[],
        hills=[],
        markings=[],
        agents=[],
        bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
    )
    layout.build_indices()
    layout.hills = _place_hills(rng_for(seed, 2), scale)
    layout.buildings = _place_buildings(layout, rng_for(seed, 3))
    layout.build_indices()
    layout.trees, layout.lamps = _place_trees_and_lamps(layout, rng_for(seed, 4))
    layout.bumps, layout.rough = _place_bumps_and_rough(layout, rng_for(seed, 5), options)
    if options.rough_paving_per_km > 0:  # a stream of its own: the rest of the campus stays as it is
        layout.rough += _more_rough_paving(layout, rng_for(seed, 8), options.rough_paving_per_km)
    layout.markings = place_markings(
        layout, rng_for(seed, 6), options.designs, options.marking_spacing, options.custom_fraction
    )
    layout.agents = place_agents(layout, rng_for(seed, 7), options.pedestrians_per_km, options.vehicles_per_km)
    layout.build_indices()
    return layout


def _place_hills(rng: np.random.Generator, scale: float) -> list[Hill]:
    """A gently rolling campus with two steeper hills on the east side (the slope sequences)."""
    hills = [
        Hill(np.array([300.0, 238.0]), 42.0, 42.0, 0.0, 6.0),
        Hill(np.array([470.0, 292.0]), 36.0, 30.0, 0.6, -4.2),
        Hill(np.array([120.0, 40.0]), 90.0, 60.0, 0.3, 2.5),
        Hill(np.array([420.0, 60.0]), 110.0, 70.0, -0.4, -2.5),
        Hill(np.array([60.0, 280.0]), 80.0, 80.0, 0.0, 2.0),
    ]
    out = []
    for h in hills:
        jitter = rng.uniform(-6.0, 6.0, 2)
        amp = h.amplitude * rng.uniform(0.88, 1.0)
        out.append(Hill((h.centre + jitter) * scale, h.sigma_along * scale, h.sigma_across * scale, h.yaw, amp * scale))
    return out


def _place_buildings(layout: CampusLayout, rng: np.random.Generator) -> list[Building]:
    """Buildings inside the blocks between paths and around the campus, clear of every path.

    Free space is a 1 m occupancy raster of the paths and plazas grown by the set-back; a
    candidate is accepted when its rectangle covers no occupied cell.
    """
    s = layout.scale
    setback, gap, res = 7.0, 6.0, 1.0
    x_lo, y_lo, x_hi, y_hi = layout.bounds
    w_px, h_px = math.ceil((x_hi - x_lo) / res) + 1, math.ceil((y_hi - y_lo) / res) + 1
    occupied = np.zeros((h_px, w_px), np.uint8)

    def px(p: np.ndarray) -> tuple[int, int]:
        return round((p[0] - x_lo) / res), round((p[1] - y_lo) / res)

    for e in layout.edges:
        pts = np.array([px(p) for p in e.points], np.int32)
        cv2.polylines(occupied, [pts], False, 1, max(1, round((e.width + 2 * setback) / res)))
    for pz in layout.plazas:
        cv2.circle(occupied, px(pz.centre), round((pz.half * math.sqrt(2) + setback) / res), 1, -1)

    def free(x0: float, y0: float, x1: float, y1: float) -> bool:
        c0, r0 = max(0, math.floor((x0 - x_lo) / res)), max(0, math.floor((y0 - y_lo) / res))
        c1, r1 = min(w_px, math.ceil((x1 - x_lo) / res) + 1), min(h_px, math.ceil((y1 - y_lo) / res) + 1)
        return c1 > c0 and r1 > r0 and not occupied[r0:r1, c0:c1].any()

    xs = sorted({float(v[0]) for k, v in layout.nodes.items() if k not in ("H", "BC1", "DO")})
    ys = sorted({float(v[1]) for k, v in layout.nodes.items() if k not in ("H", "BC1", "DO")})
    blocks = []
    for x0, x1 in zip([xs[0] - 90 * s, *xs], [*xs, xs[-1] + 90 * s], strict=True):
        for y0, y1 in zip([ys[0] - 80 * s, *ys], [*ys, ys[-1] + 80 * s], strict=True):
            blocks.append((x0, x1, y0, y1))
    buildings: list[Building] = []
    for x0, x1, y0, y1 in blocks:
        for _ in range(int(rng.integers(3, 6))):
            for _attempt in range(15):
                w = rng.uniform(0.18, 0.42) * (x1 - x0)
                d = rng.uniform(0.18, 0.42) * (y1 - y0)
                cx = rng.uniform(x0 + w / 2, x1 - w / 2)
                cy = rng.uniform(y0 + d / 2, y1 - d / 2)
                if w < 8.0 or d < 8.0 or not free(cx - w / 2, cy - d / 2, cx + w / 2, cy + d / 2):
                    continue
                corners = np.array(
                    [
                        [cx - w / 2, cy - d / 2],
                        [cx + w / 2, cy - d / 2],
                        [cx + w / 2, cy + d / 2],
                        [cx - w / 2, cy + d / 2],
                    ]
                )
                c0, r0 = px(np.array([cx - w / 2 - gap, cy - d / 2 - gap]))
                c1, r1 = px(np.array([cx + w / 2 + gap, cy + d / 2 + gap]))
                occupied[max(0, r0) : r1 + 1, max(0, c0) : c1 + 1] = 1
                buildings.append(Building(corners, float(rng.uniform(7.0, 26.0)), int(rng.integers(0, 6))))
                break
    return buildings


def point_in_buildings(layout: CampusLayout, pts: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Whether each point (N, 2) is inside (or within ``margin`` of) a building."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    inside = np.zeros(len(pts), bool)
    for b in layout.buildings:
        corners = b.corners
        ok = np.ones(len(pts), bool)
        for a, c in zip(corners, np.roll(corners, -1, axis=0), strict=True):
            edge = c - a
            normal = np.array([edge[1], -edge[0]]) / max(float(np.linalg.norm(edge)), 1e-9)  # outward (CCW)
            ok &= (pts - a) @ normal <= margin
        inside |= ok
    return inside


def _place_trees_and_lamps(layout: CampusLayout, rng: np.random.Generator) -> tuple[list[Tree], list[Lamp]]:
    """Rows of trees and lamps beside the paths, and tree groups on the lawns."""
    trees: list[Tree] = []
    lamps: list[Lamp] = []
    for e in layout.edges:
        length = e.length
        side_offsets = (e.width / 2 + rng.uniform(1.6, 3.2), -(e.width / 2 + rng.uniform(1.6, 3.2)))
        spacing = rng.uniform(11.0, 18.0)
        s = rng.uniform(4.0, spacing)
        while s < length - 4.0:
            p, t = e.at(s)
            n = np.array([-t[1], t[0]])
            for off in side_offsets:
                if rng.random() < 0.6:
                    q = p + n * (off + rng.normal(0, 0.3))
                    trees.append(_tree(q, rng))
            s += spacing * rng.uniform(0.85, 1.15)
        s = rng.uniform(5.0, 25.0)
        side = 1.0 if rng.random() < 0.5 else -1.0
        while s < length - 5.0:
            p, t = e.at(s)
            n = np.array([-t[1], t[0]])
            lamps.append(Lamp(p + side * n * (e.width / 2 + 0.6), float(rng.uniform(3.8, 4.6))))
            s += rng.uniform(24.0, 34.0)
    lo_x, lo_y, hi_x, hi_y = layout.bounds
    for _ in range(int((hi_x - lo_x) * (hi_y - lo_y) / 900.0)):
        centre = np.array([rng.uniform(lo_x, hi_x), rng.uniform(lo_y, hi_y)])
        for _k in range(int(rng.integers(2, 6))):
            trees.append(_tree(centre + rng.normal(0.0, 5.0, 2), rng))
    if trees:
        pos = np.array([t.position for t in trees])
        keep = layout.path_distance(pos) > 0.9
        keep &= ~point_in_buildings(layout, pos, margin=2.0)
        trees = [t for t, k in zip(trees, keep, strict=True) if k]
    if lamps:
        pos = np.array([lamp.position for lamp in lamps])
        keep = layout.path_distance(pos) > 0.2
        lamps = [lamp for lamp, k in zip(lamps, keep, strict=True) if k]
    return trees, lamps


def _tree(position: np.ndarray, rng: np.random.Generator) -> Tree:
    trunk = float(rng.uniform(1.8, 3.2))
    radius = float(rng.uniform(1.8, 3.6))
    return Tree(np.asarray(position, np.float64), trunk, radius, trunk + radius * 0.8, int(rng.integers(0, 4)))


def _place_bumps_and_rough(
    layout: CampusLayout, rng: np.random.Generator, options: LayoutOptions
) -> tuple[list[SpeedBump], list[RoughPatch]]:
    """Speed bumps across some paths (always one on the home stretch) and rough paving patches."""
    bumps: list[SpeedBump] = []
    rough: list[RoughPatch] = []
    for e in layout.edges:
        length = e.length
        forced = (e.a, e.b) in (("B1", "BC1"), ("A0", "A1"), ("C2", "D2"))
        if length > 30.0 and (forced or rng.random() < options.bump_probability):
            s = float(rng.uniform(0.3, 0.7) * length) if not forced else 0.5 * length
            p, t = e.at(s)
            bumps.append(
                SpeedBump(p, t, float(rng.uniform(0.22, 0.5)), e.width / 2 + 0.2, float(rng.uniform(0.05, 0.12)))
            )
        if length > ROUGH_PATH_LENGTH and rng.random() < 0.3:
            s = float(rng.uniform(0.2, 0.8) * length)
            rough.append(_rough_patch(e.at(s)[0], rng))
    return bumps, rough


def _more_rough_paving(layout: CampusLayout, rng: np.random.Generator, per_km: float) -> list[RoughPatch]:
    """``per_km`` rough patches per km of every path over 20 m (at least one), one in each equal stretch of it."""
    rough: list[RoughPatch] = []
    for e in layout.edges:
        if e.length <= ROUGH_PATH_LENGTH:
            continue
        n = max(1, round(e.length * per_km / 1000.0))
        for k in range(n):
            rough.append(_rough_patch(e.at(float((k + rng.uniform(0.2, 0.8)) / n * e.length))[0], rng))
    return rough


def _rough_patch(centre: np.ndarray, rng: np.random.Generator) -> RoughPatch:
    """Uneven paving around ``centre``: six short waves (0.3 to 0.9 m) 8 to 18 mm high, 5 to 12 m across."""
    k = rng.uniform(2 * math.pi / 0.9, 2 * math.pi / 0.3, 6)
    a = rng.uniform(0, 2 * math.pi, 6)
    waves = np.stack([k * np.cos(a), k * np.sin(a)], axis=1)
    radius = float(rng.uniform(5.0, 12.0))
    amplitude = float(rng.uniform(0.008, 0.018))
    return RoughPatch(centre, radius, amplitude, waves, rng.uniform(0, 2 * math.pi, 6))


def _bowed(p0: np.ndarray, p1: np.ndarray, bow: float, step: float = 4.0) -> np.ndarray:
    """Polyline of a quadratic curve from ``p0`` to ``p1`` whose middle is pushed ``bow`` m sideways."""
    d = p1 - p0
    length = float(np.linalg.norm(d))
    if abs(bow) < 1e-6 or length < 1e-6:
        return np.stack([p0, p1])
    normal = np.array([-d[1], d[0]]) / length
    ctrl = 0.5 * (p0 + p1) + 2.0 * bow * normal
    n = max(2, math.ceil(length / step) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * ctrl + t**2 * p1
