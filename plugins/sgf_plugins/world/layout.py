"""The campus: its path network, plazas, buildings, trees, lamps, terrain features, markings and people.

Everything is laid out once per ``(seed, scale)``: the network's node positions (and the hills)
are multiplied by ``scale`` so that a route keeps its shape and its revisits at any scale, while
path widths, markings, bumps and buildings keep their physical size.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from sgf_plugins.world.designs import MarkingDesign, rasterise
from sgf_plugins.world.noise import rng_for

MATERIALS = ("asphalt", "slabs", "bricks", "lawn", "curb", "soil")
MATERIAL_ID = {m: i for i, m in enumerate(MATERIALS)}

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


#: Nodes of the busy middle of the campus (dormitories, student centre): markings are denser on
#: the paths that meet them.
BUSY_NODES = frozenset({"B1", "BC1", "B2", "C1", "H"})
BUSY_SPACING = 0.6
#: The footpaths to the dormitory drop-off are painted most densely (delivery markers, signs).
DORM_NODES = frozenset({"DO"})
DORM_SPACING = 0.35


# --- layout records ----------------------------------------------------------------------------


@dataclass(frozen=True)
class PathEdge:
    """One path of the network as a polyline from node ``a`` to node ``b``."""

    index: int
    a: str
    b: str
    points: np.ndarray
    width: float
    material: str

    @property
    def length(self) -> float:
        """Centre-line length (m)."""
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Point and unit tangent at arc length ``s`` from ``a``."""
        seg = np.diff(self.points, axis=0)
        lengths = np.linalg.norm(seg, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(lengths)])
        i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
        t = (s - cum[i]) / max(lengths[i], 1e-9)
        return self.points[i] + t * seg[i], seg[i] / max(lengths[i], 1e-9)


@dataclass(frozen=True)
class Plaza:
    """A paved open area: a square (``half`` = half side) or a disc (``half`` = radius)."""

    centre: np.ndarray
    half: float
    round: bool
    material: str
    yaw: float = 0.0


@dataclass(frozen=True)
class Building:
    """A building: footprint corners (4, 2) counter-clockwise, height (m) and facade style."""

    corners: np.ndarray
    height: float
    style: int


@dataclass(frozen=True)
class Tree:
    """A tree: trunk position, trunk height, canopy radius and the height of the canopy's centre."""

    position: np.ndarray
    trunk_height: float
    canopy_radius: float
    canopy_height: float
    variant: int


@dataclass(frozen=True)
class Lamp:
    """A street lamp beside a path."""

    position: np.ndarray
    height: float


@dataclass(frozen=True)
class SpeedBump:
    """A speed bump across a path: a cos^2 hump ``height`` high, ``2 * half_length`` long."""

    centre: np.ndarray
    direction: np.ndarray
    half_length: float
    half_width: float
    height: float


@dataclass(frozen=True)
class RoughPatch:
    """A patch of uneven paving: a sum of short waves ``amplitude`` high, faded out at ``radius``."""

    centre: np.ndarray
    radius: float
    amplitude: float
    wavevectors: np.ndarray
    phases: np.ndarray


@dataclass(frozen=True)
class Hill:
    """A smooth rise or dip of the ground: an anisotropic Gaussian ``amplitude`` m high."""

    centre: np.ndarray
    sigma_along: float
    sigma_across: float
    yaw: float
    amplitude: float


@dataclass
class MarkingInstance:
    """A marking painted (or set) into the ground at a world pose, with its rasterisation recipe."""

    instance_id: int
    design: MarkingDesign
    x: float
    y: float
    yaw: float
    length: float
    width: float
    colour: tuple[int, int, int]
    content_seed: int
    wear: float
    wear_seed: int
    edge: int
    outline: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def radius(self) -> float:
        """Radius of the disc that holds the marking (m)."""
        return 0.5 * math.hypot(self.length, self.width)

    def local_to_world(self, points: np.ndarray) -> np.ndarray:
        """World ``(x, y)`` of local marking points ``(N, 2)``."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        pts = np.asarray(points, np.float64)
        return np.stack([self.x + c * pts[:, 0] - s * pts[:, 1], self.y + s * pts[:, 0] + c * pts[:, 1]], axis=1)

    def footprint(self) -> np.ndarray:
        """World corners (4, 2) of the marking's box."""
        h, w = self.length / 2, self.width / 2
        return self.local_to_world(np.array([[h, w], [-h, w], [-h, -w], [h, -w]]))


@dataclass(frozen=True)
class Agent:
    """A person or vehicle moving back and forth along a polyline (or standing still)."""

    kind: str
    points: np.ndarray
    speed: float
    phase: float
    lateral: float
    size: tuple[float, float, float]
    colours: tuple[tuple[int, int, int], ...]

    def __post_init__(self) -> None:
        seg = np.diff(self.points, axis=0)
        lengths = np.linalg.norm(seg, axis=1)
        object.__setattr__(self, "_seg", seg)
        object.__setattr__(self, "_lengths", lengths)
        object.__setattr__(self, "_cum", np.concatenate([[0.0], np.cumsum(lengths)]))

    def state(self, t: float) -> tuple[np.ndarray, float, float]:
        """Position, heading (rad) and distance walked at time ``t`` (s)."""
        seg, lengths, cum = self._seg, self._lengths, self._cum  # type: ignore[attr-defined]
        total = float(cum[-1])
        walked = self.phase + self.speed * t
        u = walked % (2 * total) if total > 0 else 0.0
        forward = u <= total
        s = u if forward else 2 * total - u
        i = min(max(int(np.searchsorted(cum, s, side="right")) - 1, 0), len(seg) - 1)
        tangent = seg[i] / max(lengths[i], 1e-9)
        p = self.points[i] + (s - cum[i]) * tangent
        if not forward:
            tangent = -tangent
        normal = np.array([-tangent[1], tangent[0]])
        heading = math.atan2(tangent[1], tangent[0])
        return p - self.lateral * normal, heading, walked


class SpatialIndex:
    """Integer ids bucketed by the square cells their bounding boxes touch."""

    def __init__(self, cell: float) -> None:
        self.cell = cell
        self.cells: dict[tuple[int, int], list[int]] = {}

    def add(self, ident: int, xmin: float, ymin: float, xmax: float, ymax: float) -> None:
        """Register ``ident`` over a bounding box."""
        c = self.cell
        for i in range(math.floor(xmin / c), math.floor(xmax / c) + 1):
            for j in range(math.floor(ymin / c), math.floor(ymax / c) + 1):
                self.cells.setdefault((i, j), []).append(ident)

    def query(self, xmin: float, ymin: float, xmax: float, ymax: float) -> list[int]:
        """Ids whose boxes may touch the query box, each once, sorted."""
        c = self.cell
        found: set[int] = set()
        for i in range(math.floor(xmin / c), math.floor(xmax / c) + 1):
            for j in range(math.floor(ymin / c), math.floor(ymax / c) + 1):
                found.update(self.cells.get((i, j), ()))
        return sorted(found)


@dataclass
class Segment:
    """A straight piece of a path edge (for distance queries)."""

    p0: np.ndarray
    p1: np.ndarray
    half_width: float
    material: int
    edge: int
    s0: float

    @property
    def direction(self) -> np.ndarray:
        """Unit vector from ``p0`` to ``p1``."""
        d = self.p1 - self.p0
        return d / max(float(np.linalg.norm(d)), 1e-9)

    @property
    def length(self) -> float:
        """Length (m)."""
        return float(np.linalg.norm(self.p1 - self.p0))


@dataclass
class CampusLayout:
    """Everything placed in the campus, with spatial indices for fast local queries."""

    seed: int
    scale: float
    nodes: dict[str, np.ndarray]
    edges: list[PathEdge]
    segments: list[Segment]
    plazas: list[Plaza]
    buildings: list[Building]
    trees: list[Tree]
    lamps: list[Lamp]
    bumps: list[SpeedBump]
    rough: list[RoughPatch]
    hills: list[Hill]
    markings: list[MarkingInstance]
    agents: list[Agent]
    bounds: tuple[float, float, float, float]
    segment_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(16.0))
    plaza_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(32.0))
    marking_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(16.0))
    tree_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(32.0))
    building_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(32.0))
    lamp_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(32.0))
    bump_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(16.0))
    rough_index: SpatialIndex = field(default_factory=lambda: SpatialIndex(16.0))

    def build_indices(self) -> None:
        """(Re)build the spatial indices after the records are placed."""
        self.segment_index = SpatialIndex(16.0)
        for i, s in enumerate(self.segments):
            lo = np.minimum(s.p0, s.p1) - s.half_width - 0.5
            hi = np.maximum(s.p0, s.p1) + s.half_width + 0.5
            self.segment_index.add(i, lo[0], lo[1], hi[0], hi[1])
        self.plaza_index = SpatialIndex(32.0)
        for i, p in enumerate(self.plazas):
            r = p.half * (math.sqrt(2) if not p.round else 1.0) + 0.5
            self.plaza_index.add(i, p.centre[0] - r, p.centre[1] - r, p.centre[0] + r, p.centre[1] + r)
        self.marking_index = SpatialIndex(16.0)
        for i, m in enumerate(self.markings):
            self.marking_index.add(i, m.x - m.radius, m.y - m.radius, m.x + m.radius, m.y + m.radius)
        self.tree_index = SpatialIndex(32.0)
        for i, t in enumerate(self.trees):
            r = t.canopy_radius
            self.tree_index.add(i, t.position[0] - r, t.position[1] - r, t.position[0] + r, t.position[1] + r)
        self.building_index = SpatialIndex(32.0)
        for i, b in enumerate(self.buildings):
            lo, hi = b.corners.min(axis=0), b.corners.max(axis=0)
            self.building_index.add(i, lo[0], lo[1], hi[0], hi[1])
        self.lamp_index = SpatialIndex(32.0)
        for i, lamp in enumerate(self.lamps):
            self.lamp_index.add(i, *lamp.position, *lamp.position)
        self.bump_index = SpatialIndex(16.0)
        for i, bump in enumerate(self.bumps):
            r = max(bump.half_length, bump.half_width) + 0.5
            self.bump_index.add(i, bump.centre[0] - r, bump.centre[1] - r, bump.centre[0] + r, bump.centre[1] + r)
        self.rough_index = SpatialIndex(16.0)
        for i, patch in enumerate(self.rough):
            c, r = patch.centre, patch.radius
            self.rough_index.add(i, c[0] - r, c[1] - r, c[0] + r, c[1] + r)

    def edge_between(self, a: str, b: str) -> tuple[PathEdge, bool]:
        """The edge joining two nodes and whether it runs from ``b`` to ``a`` (reversed)."""
        for e in self.edges:
            if (e.a, e.b) == (a, b):
                return e, False
            if (e.a, e.b) == (b, a):
                return e, True
        raise KeyError(f"no path joins {a} and {b}")

    def path_distance(self, xy: np.ndarray) -> np.ndarray:
        """Distance (m) from each point (N, 2) to the nearest path surface edge (negative inside)."""
        pts = np.asarray(xy, np.float64).reshape(-1, 2)
        best = np.full(len(pts), np.inf)
        lo, hi = pts.min(axis=0) - 30.0, pts.max(axis=0) + 30.0
        for i in self.segment_index.query(lo[0], lo[1], hi[0], hi[1]):
            s = self.segments[i]
            np.minimum(best, _segment_distance(pts, s.p0, s.p1) - s.half_width, out=best)
        for i in self.plaza_index.query(lo[0], lo[1], hi[0], hi[1]):
            np.minimum(best, _plaza_sdf(pts, self.plazas[i]), out=best)
        return np.minimum(best, 30.0)


def _segment_distance(pts: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    d = p1 - p0
    ll = float(d @ d)
    t = np.clip(((pts - p0) @ d) / max(ll, 1e-12), 0.0, 1.0)
    return np.linalg.norm(pts - (p0 + t[:, None] * d), axis=1)


def _plaza_sdf(pts: np.ndarray, p: Plaza) -> np.ndarray:
    q = pts - p.centre
    if p.round:
        return np.linalg.norm(q, axis=1) - p.half
    c, s = math.cos(p.yaw), math.sin(p.yaw)
    lx, ly = np.abs(c * q[:, 0] + s * q[:, 1]) - p.half, np.abs(-s * q[:, 0] + c * q[:, 1]) - p.half
    outside = np.linalg.norm(np.stack([np.maximum(lx, 0), np.maximum(ly, 0)], axis=1), axis=1)
    return outside + np.minimum(np.maximum(lx, ly), 0.0)


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


def _trim(points: np.ndarray, start: float, end: float) -> np.ndarray:
    """The part of a polyline between arc lengths ``start`` and ``length - end``."""
    seg = np.diff(points, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    total = cum[-1]
    s0, s1 = min(start, total / 2), max(total - end, total / 2)

    def at(s: float) -> np.ndarray:
        i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
        return points[i] + (s - cum[i]) / max(lengths[i], 1e-9) * seg[i]

    inner = [points[i] for i in range(len(points)) if s0 < cum[i] < s1]
    return np.stack([at(s0), *inner, at(s1)])


# --- building the campus -----------------------------------------------------------------------


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
    layout.markings = _place_markings(layout, rng_for(seed, 6), options)
    layout.agents = _place_agents(layout, rng_for(seed, 7), options)
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


def _pick(rng: np.random.Generator, designs: Sequence[MarkingDesign]) -> MarkingDesign | None:
    weights = np.array([d.weight for d in designs], np.float64)
    if len(designs) == 0 or weights.sum() <= 0:
        return None
    return designs[int(rng.choice(len(designs), p=weights / weights.sum()))]


def _place_markings(layout: CampusLayout, rng: np.random.Generator, options: LayoutOptions) -> list[MarkingInstance]:
    """Markings along every path: standard ones repeating, custom ones unique, chevrons on bumps."""
    designs = list(options.designs)
    by_place: dict[str, list[MarkingDesign]] = {}
    for d in designs:
        by_place.setdefault(d.placement, []).append(d)
    standard_regular = [d for d in designs if d.category == "standard" and d.placement in ("lane", "along")]
    custom_regular = [d for d in designs if d.category == "custom" and d.placement in ("free", "edge")]
    across = by_place.get("across", [])
    placed: list[MarkingInstance] = []

    def fits(x: float, y: float, radius: float) -> bool:
        return all(math.hypot(m.x - x, m.y - y) > radius + m.radius + 0.6 for m in placed)

    def add(design: MarkingDesign, x: float, y: float, yaw: float, length: float, width: float, edge: int) -> None:
        ident = len(placed) + 1
        colour = design.colours[int(rng.integers(len(design.colours)))]
        if design.category == "standard":
            colour = design.colours[0] if rng.random() < 0.8 else colour
        wear = float(rng.uniform(0.0, 0.45)) if design.material == "paint" else float(rng.uniform(0.0, 0.3))
        m = MarkingInstance(
            ident,
            design,
            x,
            y,
            yaw,
            length,
            width,
            colour,
            int(rng.integers(1 << 30)),
            wear,
            int(rng.integers(1 << 30)),
            edge,
        )
        placed.append(m)

    # 1. chevrons painted on every speed bump
    chevrons = [d for d in designs if d.placement == "bump"]
    for b in layout.bumps:
        if chevrons:
            d = chevrons[0]
            width = min(2 * b.half_width - 0.4, d.size[1] * 1.6)
            add(
                d,
                float(b.centre[0]),
                float(b.centre[1]),
                math.atan2(b.direction[1], b.direction[0]),
                min(d.size[0], 2 * b.half_length * 0.9),
                width,
                -1,
            )
    for e in layout.edges:
        length = e.length
        # 2. crossings and stop lines just before the plazas at both ends
        for end in (0, 1):
            if across and length > 24.0 and rng.random() < 0.45:
                crossing = _pick(rng, across)
                if crossing is None:
                    continue
                d = crossing
                s = 7.5 if end == 0 else length - 7.5
                p, t = e.at(s)
                yaw = math.atan2(t[1], t[0]) + (0.0 if end == 1 else math.pi)
                width = min(d.size[1], e.width - 0.3) if d.name != "tactile_bars" else d.size[1]
                if fits(p[0], p[1], 0.5 * math.hypot(d.size[0], width)):
                    add(d, float(p[0]), float(p[1]), yaw, d.size[0], width, e.index)
        # 3. regular sites along the path (closer together in the busy middle of the campus)
        nodes = {e.a, e.b}
        factor = DORM_SPACING if nodes & DORM_NODES else (BUSY_SPACING if nodes & BUSY_NODES else 1.0)
        spacing = options.marking_spacing * factor
        if length < 30.0:
            sites = [0.5 * length]
        else:
            sites = []
            s = rng.uniform(9.0, 9.0 + spacing * 0.6)
            while s < length - 9.0:
                sites.append(s)
                s += spacing * rng.uniform(0.6, 1.4)
        for s in sites:
            custom = rng.random() < options.custom_fraction or length < 30.0
            pool = custom_regular if custom else standard_regular
            picked = _pick(rng, pool) or _pick(rng, standard_regular or custom_regular)
            if picked is None:
                continue
            d = picked
            p, t = e.at(s)
            n = np.array([-t[1], t[0]])
            heading = math.atan2(t[1], t[0])
            jitter = 1.0 + d.size_jitter * rng.uniform(-1.0, 1.0)
            length_m, width_m = d.size[0] * jitter, d.size[1] * jitter
            hw = e.width / 2
            if d.placement == "lane":
                lane = 0.0 if e.width < 4.5 else e.width / 4
                direction = 1.0 if rng.random() < 0.5 else -1.0
                lateral = -direction * lane + rng.normal(0.0, 0.05)
                yaw = heading + (0.0 if direction > 0 else math.pi)
            elif d.placement == "along":
                lateral = 0.0 if rng.random() < 0.7 else (hw - 0.25) * (1 if rng.random() < 0.5 else -1)
                yaw = heading
            elif d.placement == "edge":
                side = 1.0 if rng.random() < 0.5 else -1.0
                lateral = side * max(0.0, hw - width_m / 2 - 0.15)
                yaw = heading + (math.pi / 2 if d.name == "parking_number" else 0.0) * side
            else:  # free
                room = max(0.0, hw - 0.5 * math.hypot(length_m, width_m) - 0.1)
                lateral = float(rng.uniform(-room, room)) if room > 0 else 0.0
                lateral = float(np.clip(lateral, -1.2, 1.2))
                yaw = float(rng.uniform(-math.pi, math.pi))
            q = p + lateral * n
            if fits(q[0], q[1], 0.5 * math.hypot(length_m, width_m)):
                add(d, float(q[0]), float(q[1]), yaw, length_m, width_m, e.index)
    # 4. a few custom markings on the big plazas
    custom_any = [d for d in designs if d.category == "custom" and d.placement == "free"]
    for pz in layout.plazas:
        if pz.half < 6.0 or not custom_any:
            continue
        for _ in range(int(rng.integers(1, 4))):
            chosen = _pick(rng, custom_any)
            if chosen is None:
                break
            d = chosen
            q = pz.centre + rng.uniform(-0.6, 0.6, 2) * pz.half
            if fits(q[0], q[1], 0.5 * math.hypot(*d.size)):
                add(d, float(q[0]), float(q[1]), float(rng.uniform(-math.pi, math.pi)), d.size[0], d.size[1], -1)
    # Keep only markings that lie on paved ground (none half on the lawn or inside a building).
    kept: list[MarkingInstance] = []
    for m in placed:
        corners = m.footprint()
        if layout.path_distance(corners).max() <= 0.05:
            kept.append(m)
    for i, m in enumerate(kept, start=1):
        m.instance_id = i
        m.outline = marking_outline(m)
    return kept


def marking_outline(m: MarkingInstance, res: float = 0.02) -> np.ndarray:
    """Convex hull (N, 2) of the marking's mask in its local frame, with points every 0.25 m."""
    r = rasterise(m.design, m.length, m.width, res, m.colour, m.content_seed)
    rows, cols = np.nonzero(r.mask)
    if rows.size == 0:
        h, w = m.length / 2, m.width / 2
        return np.array([[h, w], [-h, w], [-h, -w], [h, -w]])
    # Pixel corners, so that the hull covers whole pixels.
    cc = np.concatenate([cols - 0.5, cols + 0.5, cols - 0.5, cols + 0.5])
    rr = np.concatenate([rows - 0.5, rows - 0.5, rows + 0.5, rows + 0.5])
    pts = np.stack([cc, rr], axis=1).astype(np.float32)
    hull = cv2.convexHull(pts)[:, 0, :].astype(np.float64)
    x = r.x_top - (hull[:, 1] + 0.5) * res
    y = r.y_left - (hull[:, 0] + 0.5) * res
    ring = np.stack([x, y], axis=1)
    dense = []
    for a, b in zip(ring, np.roll(ring, -1, axis=0), strict=True):
        n = max(1, math.ceil(float(np.linalg.norm(b - a)) / 0.25))
        t = np.arange(n)[:, None] / n
        dense.append(a + t * (b - a))
    return np.concatenate(dense)


def _place_agents(layout: CampusLayout, rng: np.random.Generator, options: LayoutOptions) -> list[Agent]:
    """People walking (and standing) along the paths, and service vehicles on the wide ones."""
    agents: list[Agent] = []
    shirts = [
        (200, 60, 50),
        (40, 80, 160),
        (230, 230, 225),
        (30, 30, 34),
        (90, 140, 70),
        (220, 170, 40),
        (150, 90, 160),
    ]
    trousers = [(40, 50, 80), (30, 30, 32), (110, 100, 85), (70, 80, 110), (150, 140, 120)]
    skins = [(224, 188, 160), (200, 150, 115), (150, 100, 70), (236, 205, 180)]
    cars = [(210, 210, 215), (30, 32, 36), (150, 20, 24), (40, 70, 130), (120, 125, 130), (230, 225, 210)]
    for e in layout.edges:
        length = e.length
        n_ped = rng.poisson(length / 1000.0 * options.pedestrians_per_km)
        for _ in range(n_ped):
            side = 1.0 if rng.random() < 0.5 else -1.0
            lateral = side * max(0.45, e.width / 2 - rng.uniform(0.35, 0.8))
            speed = 0.0 if rng.random() < 0.12 else float(rng.uniform(0.9, 1.5))
            height = float(rng.uniform(1.55, 1.9))
            colours = (
                shirts[int(rng.integers(len(shirts)))],
                trousers[int(rng.integers(len(trousers)))],
                skins[int(rng.integers(len(skins)))],
                (int(rng.integers(20, 60)),) * 3,
            )
            pts = _trim(e.points, 3.0, 3.0)
            agents.append(
                Agent(
                    "pedestrian", pts, speed, float(rng.uniform(0, 2 * length)), lateral, (0.3, 0.45, height), colours
                )
            )
        if e.width >= 4.0:
            n_car = rng.poisson(length / 1000.0 * options.vehicles_per_km)
            for _ in range(n_car):
                kind = str(rng.choice(["car", "van", "cart"]))
                size = {"car": (4.3, 1.8, 1.45), "van": (5.0, 2.0, 2.1), "cart": (2.4, 1.2, 1.8)}[kind]
                parked = rng.random() < 0.35
                speed = 0.0 if parked else float(rng.uniform(1.5, 3.5))
                side = 1.0 if rng.random() < 0.5 else -1.0
                lateral = side * max(0.0, e.width / 2 - size[1] / 2 - (0.1 if parked else 0.4))
                colour = cars[int(rng.integers(len(cars)))]
                pts = _trim(e.points, 6.0, 6.0)
                agents.append(Agent(kind, pts, speed, float(rng.uniform(0, 2 * length)), lateral, size, (colour,)))
    return agents
