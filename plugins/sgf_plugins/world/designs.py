"""The library of ground-marking designs: standard road markings and custom campus markings.

Each design is a row of :data:`DESIGNS`: its name, family, size, where it is painted and how
often, and the function that draws it (:mod:`~sgf_plugins.world.road_markings`,
:mod:`~sgf_plugins.world.campus_markings`). A world paints the designs that
:func:`allowed_designs` leaves it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2

from sgf_pipeline.errors import ConfigError
from sgf_plugins.world.campus_markings import (
    LATIN_WORDS,
    SCRIPT_WORDS,
    coloured_zone,
    delivery_dropoff,
    delivery_pickup,
    direction_sign,
    drain_grate,
    logo_ring,
    logo_shield,
    manhole,
    painted_footprints,
    painted_heart,
    painted_star,
    parking_number,
    random_shape,
    tactile_bars,
    tactile_dots,
    text_hangul,
    word_in_fonts,
)
from sgf_plugins.world.canvas import (
    BLUE,
    GREEN,
    MAROON,
    METAL,
    NAVY,
    ORANGE,
    RED,
    RGB,
    RUST,
    TACTILE,
    WHITE,
    YELLOW,
    DrawFn,
)
from sgf_plugins.world.road_markings import (
    arrow_straight,
    arrow_turn,
    arrow_uturn,
    bicycle,
    chevrons,
    dashed_line,
    diamond,
    give_way,
    painted_word,
    solid_line,
    stop_line,
    wheelchair,
    zebra,
)

Category = Literal["standard", "custom"]
Placement = Literal["lane", "across", "along", "free", "edge", "bump"]


@dataclass(frozen=True)
class MarkingDesign:
    """One kind of ground marking: how it is drawn, how big it is, where it is painted."""

    name: str
    family: str
    category: Category
    symmetric: bool
    size: tuple[float, float]
    draw: DrawFn
    placement: Placement
    colours: tuple[RGB, ...] = (WHITE,)
    size_jitter: float = 0.0
    weight: float = 1.0
    material: Literal["paint", "metal", "tile"] = "paint"
    tags: tuple[str, ...] = field(default_factory=tuple)


#: Every design, standard (public road markings, identical wherever painted) and custom.
DESIGNS: dict[str, MarkingDesign] = {
    d.name: d
    for d in (
        MarkingDesign("solid_line", "line", "standard", True, (3.0, 0.15), solid_line, "along", (WHITE, YELLOW)),
        MarkingDesign("dashed_line", "line", "standard", True, (2.6, 0.12), dashed_line, "along", (WHITE, YELLOW)),
        MarkingDesign("stop_line", "line", "standard", True, (0.4, 2.6), stop_line, "across", weight=0.8),
        MarkingDesign("zebra_crossing", "crossing", "standard", True, (2.0, 2.7), zebra, "across", weight=1.2),
        MarkingDesign("give_way", "crossing", "standard", False, (0.55, 2.4), give_way, "across", weight=0.6),
        MarkingDesign("arrow_straight", "arrow", "standard", False, (1.8, 0.6), arrow_straight, "lane", weight=1.4),
        MarkingDesign("arrow_left", "arrow", "standard", False, (1.8, 0.9), arrow_turn(1.0), "lane", weight=1.0),
        MarkingDesign("arrow_right", "arrow", "standard", False, (1.8, 0.9), arrow_turn(-1.0), "lane", weight=1.0),
        MarkingDesign("arrow_uturn", "arrow", "standard", False, (1.6, 1.0), arrow_uturn, "lane", weight=0.6),
        MarkingDesign("diamond", "diamond", "standard", True, (2.0, 0.8), diamond, "lane", weight=0.8),
        MarkingDesign(
            "number_30", "painted_text", "standard", False, (1.5, 0.9), painted_word("30"), "lane", (WHITE, YELLOW)
        ),
        MarkingDesign(
            "word_slow", "painted_text", "standard", False, (1.4, 1.8), painted_word("SLOW"), "lane", (WHITE, YELLOW)
        ),
        MarkingDesign(
            "word_stop", "painted_text", "standard", False, (1.4, 1.8), painted_word("STOP"), "lane", weight=0.7
        ),
        MarkingDesign("bicycle", "symbol", "standard", False, (1.6, 0.9), bicycle, "lane", weight=1.0),
        MarkingDesign("wheelchair", "symbol", "standard", False, (1.0, 1.0), wheelchair, "lane", weight=0.6),
        MarkingDesign(
            "speed_bump_chevrons",
            "chevrons",
            "standard",
            False,
            (0.5, 2.4),
            chevrons,
            "bump",
            (WHITE, YELLOW),
            weight=0.0,
        ),
        MarkingDesign(
            "campus_logo_shield", "logo", "custom", False, (1.2, 1.0), logo_shield, "free", (NAVY, MAROON, GREEN), 0.25
        ),
        MarkingDesign(
            "campus_logo_ring", "logo", "custom", False, (1.3, 1.3), logo_ring, "free", (NAVY, MAROON, WHITE), 0.25
        ),
        MarkingDesign(
            "text_hangul", "text_custom", "custom", False, (0.7, 1.9), text_hangul, "free", (WHITE, YELLOW, GREEN), 0.2
        ),
        MarkingDesign(
            "text_script",
            "text_custom",
            "custom",
            False,
            (0.6, 2.0),
            word_in_fonts(SCRIPT_WORDS, (cv2.FONT_HERSHEY_SCRIPT_SIMPLEX, cv2.FONT_HERSHEY_SCRIPT_COMPLEX), 0.1),
            "free",
            (WHITE, YELLOW, BLUE, ORANGE),
            0.2,
        ),
        MarkingDesign(
            "text_serif",
            "text_custom",
            "custom",
            False,
            (0.55, 2.2),
            word_in_fonts(
                LATIN_WORDS, (cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_DUPLEX), 0.12
            ),
            "free",
            (WHITE, YELLOW, NAVY),
            0.2,
        ),
        MarkingDesign(
            "direction_sign", "sign", "custom", False, (0.7, 1.8), direction_sign, "free", (WHITE, YELLOW, BLUE), 0.2
        ),
        MarkingDesign(
            "parking_number", "parking", "custom", False, (1.2, 1.0), parking_number, "edge", (WHITE, YELLOW), 0.1
        ),
        MarkingDesign(
            "coloured_zone",
            "zone",
            "custom",
            False,
            (1.6, 1.3),
            coloured_zone,
            "free",
            (GREEN, BLUE, RED, ORANGE),
            0.3,
        ),
        MarkingDesign(
            "tactile_dots", "tactile", "custom", True, (0.6, 0.6), tactile_dots, "free", (TACTILE,), material="tile"
        ),
        MarkingDesign(
            "tactile_bars", "tactile", "custom", True, (0.6, 0.9), tactile_bars, "across", (TACTILE,), material="tile"
        ),
        MarkingDesign(
            "painted_star",
            "painted_shape",
            "custom",
            True,
            (1.0, 1.0),
            painted_star,
            "free",
            (YELLOW, RED, BLUE, WHITE),
            0.3,
        ),
        MarkingDesign(
            "painted_heart",
            "painted_shape",
            "custom",
            False,
            (0.9, 0.9),
            painted_heart,
            "free",
            (RED, ORANGE, WHITE),
            0.3,
        ),
        MarkingDesign(
            "painted_footprints",
            "painted_shape",
            "custom",
            False,
            (1.4, 0.5),
            painted_footprints,
            "free",
            (WHITE, YELLOW, GREEN),
            0.2,
        ),
        MarkingDesign(
            "delivery_pickup",
            "delivery",
            "custom",
            False,
            (1.2, 1.2),
            delivery_pickup,
            "free",
            (ORANGE, GREEN, WHITE),
            0.15,
        ),
        MarkingDesign(
            "delivery_dropoff",
            "delivery",
            "custom",
            False,
            (1.1, 1.1),
            delivery_dropoff,
            "free",
            (ORANGE, BLUE, WHITE),
            0.15,
        ),
        MarkingDesign(
            "manhole_round",
            "utility",
            "custom",
            True,
            (0.7, 0.7),
            manhole,
            "free",
            (METAL, RUST),
            0.15,
            material="metal",
        ),
        MarkingDesign(
            "drain_grate", "utility", "custom", True, (0.8, 0.4), drain_grate, "edge", (METAL,), 0.1, material="metal"
        ),
        # Never painted unless a world asks for it (``design_weights``): saliency training data.
        MarkingDesign(
            "random_shape",
            "procedural",
            "custom",
            False,
            (1.0, 1.0),
            random_shape,
            "free",
            (WHITE, YELLOW, BLUE, GREEN, RED, ORANGE, NAVY, MAROON),
            size_jitter=0.4,
            weight=0.0,
        ),
    )
}

#: Families a test split can hold out of training (``exclude_designs``) and use alone (``only_designs``).
HELD_OUT_FAMILIES: tuple[str, ...] = ("painted_shape", "delivery")


def families() -> dict[str, list[str]]:
    """Design names grouped by family."""
    out: dict[str, list[str]] = {}
    for d in DESIGNS.values():
        out.setdefault(d.family, []).append(d.name)
    return out


def resolve_designs(names: Iterable[str], what: str = "designs") -> set[str]:
    """Design names for a list of design or family names; unknown names are a clear error."""
    fam = families()
    out: set[str] = set()
    for n in names:
        if n in DESIGNS:
            out.add(n)
        elif n in fam:
            out.update(fam[n])
        else:
            raise ConfigError(
                f"{what}: unknown marking design or family {n!r}. Designs: {', '.join(sorted(DESIGNS))}. "
                f"Families: {', '.join(sorted(fam))}"
            )
    return out


def allowed_designs(
    exclude: Iterable[str] = (), only: Iterable[str] = (), weights: Mapping[str, float] | None = None
) -> list[MarkingDesign]:
    """The designs a world may paint: ``only`` (if given) minus ``exclude`` (names or families).

    ``weights`` replaces the named designs' weights (how often each is chosen; 0 = never).
    """
    weights = dict(weights or {})
    unknown = sorted(set(weights) - set(DESIGNS))
    if unknown:
        raise ConfigError(f"design_weights: unknown marking design(s) {unknown}. Designs: {', '.join(sorted(DESIGNS))}")
    only = list(only)
    chosen = resolve_designs(only, "only_designs") if only else set(DESIGNS)
    chosen -= resolve_designs(exclude, "exclude_designs")
    if not chosen:
        raise ConfigError("no marking design is left after only_designs/exclude_designs; allow at least one")
    return [replace(DESIGNS[n], weight=weights.get(n, DESIGNS[n].weight)) for n in DESIGNS if n in chosen]
