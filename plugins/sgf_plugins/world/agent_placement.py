"""Placing the people and vehicles of a campus layout on its paths."""

from __future__ import annotations

import numpy as np

from sgf_plugins.world.layout import Agent, CampusLayout


def place_agents(
    layout: CampusLayout, rng: np.random.Generator, pedestrians_per_km: float, vehicles_per_km: float
) -> list[Agent]:
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
        n_ped = rng.poisson(length / 1000.0 * pedestrians_per_km)
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
            n_car = rng.poisson(length / 1000.0 * vehicles_per_km)
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
