"""Placing the markings of a campus layout: crossings, regular sites along every path, chevrons, plaza markings."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from sgf_plugins.world.designs import MarkingDesign
from sgf_plugins.world.layout import CampusLayout, MarkingInstance
from sgf_plugins.world.marking_raster import rasterise

#: Nodes of the busy middle of the campus (dormitories, student centre): markings are denser on
#: the paths that meet them.
BUSY_NODES = frozenset({"B1", "BC1", "B2", "C1", "H"})
BUSY_SPACING = 0.6
#: The footpaths to the dormitory drop-off are painted most densely (delivery markers, signs).
DORM_NODES = frozenset({"DO"})
DORM_SPACING = 0.35


def _pick(rng: np.random.Generator, designs: Sequence[MarkingDesign]) -> MarkingDesign | None:
    weights = np.array([d.weight for d in designs], np.float64)
    if len(designs) == 0 or weights.sum() <= 0:
        return None
    return designs[int(rng.choice(len(designs), p=weights / weights.sum()))]


def place_markings(
    layout: CampusLayout,
    rng: np.random.Generator,
    available: Sequence[MarkingDesign],
    marking_spacing: float,
    custom_fraction: float,
) -> list[MarkingInstance]:
    """Markings along every path: standard ones repeating, custom ones unique, chevrons on bumps.

    ``marking_spacing`` is the mean distance (m) between regular sites along a path (less in the
    busy middle of the campus), ``custom_fraction`` the chance that such a site gets a custom design.
    """
    designs = list(available)
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
        spacing = marking_spacing * factor
        if length < 30.0:
            sites = [0.5 * length]
        else:
            sites = []
            s = rng.uniform(9.0, 9.0 + spacing * 0.6)
            while s < length - 9.0:
                sites.append(s)
                s += spacing * rng.uniform(0.6, 1.4)
        for s in sites:
            custom = rng.random() < custom_fraction or length < 30.0
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
