"""The campus layout's data model: paths, plazas, buildings, trees, lamps, terrain features, markings and people.

A :class:`CampusLayout` holds the records of everything placed in the campus, with spatial
indices for fast local queries (:mod:`~sgf_plugins.world.layout_generator` lays it out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sgf_plugins.world.designs import MarkingDesign

MATERIALS = ("asphalt", "slabs", "bricks", "lawn", "curb", "soil")
MATERIAL_ID = {m: i for i, m in enumerate(MATERIALS)}


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
