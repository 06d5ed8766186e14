"""The four sequences of the paper's campus (Sec. IV-A), as routes through the synthetic campus."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class RouteSpec:
    """A route as the network nodes it passes, with stops (seconds of standing still) at some nodes.

    ``end_fraction`` of the last edge is driven (the route may end part-way along a path).
    """

    nodes: tuple[str, ...]
    stops: dict[str, float] = field(default_factory=dict)
    end_fraction: float = 1.0


@dataclass(frozen=True)
class Preset:
    """A named sequence: its route, whether it is driven at night, and what it mirrors in the paper."""

    name: str
    route: RouteSpec
    night: bool
    description: str
    paper: dict[str, float] = field(default_factory=dict)


#: Around the campus (rows 0 and 2), around the east half again (forward revisits), back west through
#: the middle, and a short stretch driven against the first lap (the reverse revisits).
LARGE_LOOP = RouteSpec(
    (
        "A1",
        "A0",
        "B0",
        "C0",
        "D0",
        "E0",
        "E1",
        "E2",
        "D2",
        "C2",
        "B2",
        "A2",
        "A1",
        "A0",
        "B0",
        "C0",
        "D0",
        "E0",
        "E1",
        "D1",
        "C1",
        "BC1",
        "B1",
        "A1",
        "A2",
    ),
    end_fraction=0.5,
)

PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        Preset(
            "campus_large_loop",
            LARGE_LOOP,
            False,
            "Seq. Large loop: about 2.7 km around the campus with forward revisits and a short reverse stretch",
            {"markings": 94, "pairs": 34, "pairs_reverse": 3, "ate_odometry_m": 292.966},
        ),
        Preset(
            "campus_reverse_slope",
            RouteSpec(("A2", "B2", "C2", "D2", "D3", "E3", "E2", "D2", "C2", "B2", "A2")),
            False,
            "Seq. Reverse+Slope: out over the hills, a loop, and back the same way (reverse revisits only)",
            {"markings": 46, "pairs": 16, "pairs_reverse": 16, "ate_odometry_m": 140.532},
        ),
        Preset(
            "campus_delivery",
            RouteSpec(("H", "B1", "BC1", "DO", "B1", "H"), stops={"DO": 6.0}),
            False,
            "Seq. Delivery: from the robot's home out to a drop-off, a stop, and back home",
            {"markings": 23, "pairs": 1, "pairs_reverse": 1, "ate_odometry_m": 71.147},
        ),
        Preset(
            "campus_large_loop_night",
            LARGE_LOOP,
            True,
            "Seq. Large loop (Night): the large loop after dark, lit by the robot's LED and street lamps",
            {"ate_odometry_m": 295.106},
        ),
    )
}
