"""The custom campus markings: logos, words, signs, tactile tiles, painted shapes, utility covers.

Custom designs vary their content, size and colour per instance. Each function draws one design
on a :class:`~sgf_plugins.world.canvas.Canvas` (see :mod:`sgf_plugins.world.designs` for the
table); ``random_shape`` draws a new man-made shape for every instance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from sgf_plugins.world.canvas import METAL_DARK, RGB, WHITE, Canvas, DrawFn, Point, icon_points
from sgf_plugins.world.hangul_font import hangul_strokes


def logo_shield(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A campus shield in the instance's colour with two random initials and a star."""
    h, w = c.length / 2, c.width / 2
    outline = icon_points(
        [
            (-w, h),
            (-0.5 * w, 0.8 * h),
            (0.0, h),
            (0.5 * w, 0.8 * h),
            (w, h),
            (w, 0.25 * h),
            (0.55 * w, -0.5 * h),
            (0.0, -h),
            (-0.55 * w, -0.5 * h),
            (-w, 0.25 * h),
        ]
    )
    c.poly(c.layer(col), outline)
    la = c.layer(WHITE)
    c.line(la, outline, 0.05, closed=True)
    initials = "".join(rng.choice(list("ABDEHIKMNSTUW"), size=2))
    c.text(la, initials, (-0.35 * h, 0.45 * h, -0.6 * w, 0.6 * w), cv2.FONT_HERSHEY_TRIPLEX, 0.14)
    star = _star_points((0.72 * h, 0.0), 0.16 * min(h, w) * 2)
    c.poly(la, star)


def _star_points(centre: Point, radius: float, inner: float = 0.45, points: int = 5) -> list[Point]:
    pts: list[Point] = []
    for i in range(2 * points):
        r = radius if i % 2 == 0 else radius * inner
        a = i * math.pi / points
        pts.append((centre[0] + r * math.cos(a), centre[1] + r * math.sin(a)))
    return pts


def logo_ring(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A round campus seal: two rings, a stylised flame and a random founding year."""
    r = c.length / 2 - 0.03
    la = c.layer(col)
    c.ring(la, (0.0, 0.0), r - 0.05, 0.09)
    c.ring(la, (0.0, 0.0), r - 0.2, 0.03)
    # a stylised flame or tree growing from a base line, and the founding year under it
    c.poly(
        la,
        icon_points(
            [
                (0.0, 0.62 * r),
                (0.22 * r, 0.12 * r),
                (0.1 * r, 0.18 * r),
                (0.16 * r, -0.12 * r),
                (-0.16 * r, -0.12 * r),
                (-0.1 * r, 0.18 * r),
                (-0.22 * r, 0.12 * r),
            ]
        ),
    )
    year = str(int(rng.integers(1946, 1999)))
    c.text(la, year, (-0.6 * r, -0.25 * r, -0.45 * r, 0.45 * r), cv2.FONT_HERSHEY_SIMPLEX, 0.12)


HANGUL_WORDS = ("천천히", "서행", "정문", "배달", "학생")
LATIN_WORDS = ("LIBRARY", "HALL 3", "SCIENCE", "CAFE", "GATE 2", "DORM B", "ARTS", "GYM", "LAB 7", "MUSIC")
SCRIPT_WORDS = ("Welcome", "Hello", "Go Team", "Enjoy", "Campus")
SHORT_WORDS = ("CAFE", "GYM", "DORM", "LAB", "EXIT", "BUS")


def text_hangul(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A Hangul word of ``HANGUL_WORDS`` in the stroke font."""
    word = str(rng.choice(HANGUL_WORDS))
    n = len(word)
    h, w = c.length / 2, c.width / 2
    box_w = min(2 * w, n * 2 * h * 0.8)
    c.strokes(c.layer(col), _scale_strokes(hangul_strokes(word), n), (-h, h, -box_w / 2, box_w / 2), 0.11)


def _scale_strokes(strokes: list[list[Point]], n: int) -> list[list[Point]]:
    return [[(u / n, v) for u, v in s] for s in strokes]


def word_in_fonts(words: Sequence[str], fonts: Sequence[int], weight: float) -> DrawFn:
    """A drawing of a word of ``words`` in one of ``fonts`` (italic three times in ten)."""

    def draw(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
        word = str(rng.choice(list(words)))
        font = int(rng.choice(list(fonts)))
        if rng.random() < 0.3:
            font |= cv2.FONT_ITALIC
        c.text(c.layer(col), word, (-c.length / 2, c.length / 2, -c.width / 2, c.width / 2), font, weight)

    return draw


def direction_sign(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A framed sign: an arrow to the left or the right and a short word."""
    h, w = c.length / 2, c.width / 2
    la = c.layer(col)
    c.line(la, [(h - 0.04, w - 0.04), (h - 0.04, -w + 0.04), (-h + 0.04, -w + 0.04), (-h + 0.04, w - 0.04)], 0.06, True)
    left = bool(rng.random() < 0.5)
    s = 1.0 if left else -1.0
    ya, yb = s * (w - 0.12), s * (w - 0.12 - 0.5)
    c.line(la, [(0.0, yb), (0.0, ya - s * 0.12)], 0.1)
    c.poly(la, [(0.2, ya - s * 0.18), (-0.2, ya - s * 0.18), (0.0, ya)])
    word = str(rng.choice(SHORT_WORDS))
    y_text = (-w + 0.12, yb - 0.1) if left else (yb + 0.1, w - 0.12)
    c.text(la, word, (-h + 0.14, h - 0.14, min(y_text), max(y_text)), cv2.FONT_HERSHEY_DUPLEX, 0.14)


def parking_number(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A parking bay's open frame with a two-digit number."""
    h, w = c.length / 2, c.width / 2
    la = c.layer(col)
    c.line(la, [(h, w - 0.05), (-h + 0.05, w - 0.05), (-h + 0.05, -w + 0.05), (h, -w + 0.05)], 0.1)
    number = f"{int(rng.integers(1, 99)):02d}"
    c.text(la, number, (-h + 0.25, h - 0.15, -w + 0.22, w - 0.22), cv2.FONT_HERSHEY_SIMPLEX, 0.14)


def coloured_zone(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A coloured tag-shaped zone with a white inset outline and a letter."""
    h, w = c.length / 2, c.width / 2
    tag = [(-h, w), (0.4 * h, w), (h, 0.0), (0.4 * h, -w), (-h, -w)]
    c.poly(c.layer(col), tag)
    la = c.layer(WHITE)
    inset = [
        (-h + 0.06, w - 0.06),
        (0.4 * h - 0.03, w - 0.06),
        (h - 0.09, 0.0),
        (0.4 * h - 0.03, -w + 0.06),
        (-h + 0.06, -w + 0.06),
    ]
    c.line(la, inset, 0.06, closed=True)
    letter = str(rng.choice(list("ABCDEFGKPRZ")))
    c.text(la, letter, (-0.6 * h, 0.3 * h, -0.4 * w, 0.4 * w), cv2.FONT_HERSHEY_DUPLEX, 0.16)


def tactile_dots(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A tactile warning tile: a grid of raised dots with grout lines."""
    h, w = c.length / 2, c.width / 2
    c.rect(c.layer(col), -h, h, -w, w)
    dots = c.layer(tuple(int(v * 0.78) for v in col))  # type: ignore[arg-type]
    grout = c.layer((150, 140, 110))
    n = max(1, round(2 * h / 0.3))
    m = max(1, round(2 * w / 0.3))
    for i in range(n):
        for j in range(m):
            x0, y0 = -h + i * 2 * h / n, -w + j * 2 * w / m
            for a in range(4):
                for b in range(4):
                    c.disc(dots, (x0 + (a + 0.5) * 2 * h / n / 4, y0 + (b + 0.5) * 2 * w / m / 4), 0.022)
            c.line(grout, [(x0, y0), (x0 + 2 * h / n, y0), (x0 + 2 * h / n, y0 + 2 * w / m)], 0.008)


def tactile_bars(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A tactile guidance tile: raised bars along the direction of travel."""
    h, w = c.length / 2, c.width / 2
    c.rect(c.layer(col), -h, h, -w, w)
    bars = c.layer(tuple(int(v * 0.78) for v in col))  # type: ignore[arg-type]
    n = max(2, round(2 * w / 0.075))
    for j in range(n):
        y = -w + (j + 0.5) * 2 * w / n
        c.line(bars, [(-h + 0.04, y), (h - 0.04, y)], 0.025)


def painted_star(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A filled five-pointed star."""
    c.poly(c.layer(col), _star_points((0.0, 0.0), c.length / 2 - 0.02, inner=0.42))


def painted_heart(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A filled heart."""
    t = np.linspace(0, 2 * math.pi, 80, endpoint=False)
    a = 16 * np.sin(t) ** 3
    b = 13 * np.cos(t) - 5 * np.cos(2 * t) - 2 * np.cos(3 * t) - np.cos(4 * t)
    s = c.length / 2 / 17.0
    c.poly(c.layer(col), icon_points(list(zip((a * s).tolist(), (b * s + 1.5 * s).tolist(), strict=True))))


def _footprint(cx: float, cy: float, mirror: float) -> list[list[Point]]:
    """A shoe print about 0.27 m long pointing along +x: the sole (ball and toes) and the heel."""
    a = np.linspace(0.0, 2 * math.pi, 28, endpoint=False)
    sole = [(cx + 0.045 + 0.085 * math.cos(t), cy + mirror * (0.012 + 0.045 * math.sin(t))) for t in a]
    heel = [(cx - 0.085 + 0.05 * math.cos(t), cy + 0.038 * math.sin(t)) for t in a]
    return [sole, heel]


def painted_footprints(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """Four shoe prints, alternately left and right."""
    la = c.layer(col)
    h, w = c.length / 2, c.width / 2
    for k in range(4):
        x = -h + 0.15 + k * (2 * h - 0.3) / 3
        y = (w - 0.07) * (1 if k % 2 == 0 else -1)
        for p in _footprint(x, y, 1.0 if k % 2 == 0 else -1.0):
            c.poly(la, p)


def delivery_pickup(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A delivery pick-up point: a ring, a parcel and the words PICK UP."""
    r = c.length / 2 - 0.03
    la = c.layer(col)
    c.ring(la, (0.0, 0.0), r - 0.04, 0.07)
    # a parcel box with a tick, and the words under it
    c.rect(la, 0.05 * r, 0.55 * r, -0.3 * r, 0.3 * r)
    c.rect(c.layer((40, 40, 40)), 0.3 * r - 0.015, 0.3 * r + 0.015, -0.3 * r, 0.3 * r)
    c.text(c.layer(col), "PICK UP", (-0.6 * r, -0.1 * r, -0.65 * r, 0.65 * r), cv2.FONT_HERSHEY_SIMPLEX, 0.12)


def delivery_dropoff(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A delivery drop-off box: a frame, an arrow and the word DROP."""
    h, w = c.length / 2, c.width / 2
    la = c.layer(col)
    c.line(la, [(h - 0.05, w - 0.05), (h - 0.05, -w + 0.05), (-h + 0.05, -w + 0.05), (-h + 0.05, w - 0.05)], 0.08, True)
    c.poly(
        la,
        [
            (0.0, 0.18 * w),
            (0.0, 0.38 * w),
            (-0.15 * h, 0.0),
            (0.0, -0.38 * w),
            (0.0, -0.18 * w),
            (0.55 * h, -0.18 * w),
            (0.55 * h, 0.18 * w),
        ],
    )
    c.text(la, "DROP", (-0.8 * h, -0.3 * h, -0.7 * w, 0.7 * w), cv2.FONT_HERSHEY_DUPLEX, 0.13)


def manhole(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A round manhole cover with rings and spokes."""
    r = c.length / 2 - 0.01
    c.disc(c.layer(col), (0.0, 0.0), r)
    dark = c.layer(METAL_DARK)
    c.ring(dark, (0.0, 0.0), r - 0.03, 0.025)
    c.ring(dark, (0.0, 0.0), 0.62 * r, 0.02)
    c.ring(dark, (0.0, 0.0), 0.3 * r, 0.02)
    for k in range(12):
        a = k * math.pi / 6
        c.line(
            dark,
            [(0.3 * r * math.cos(a), 0.3 * r * math.sin(a)), (0.9 * r * math.cos(a), 0.9 * r * math.sin(a))],
            0.015,
        )


def drain_grate(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A drain grate: dark slots across a metal plate."""
    h, w = c.length / 2, c.width / 2
    c.rect(c.layer(col), -h, h, -w, w)
    dark = c.layer((18, 18, 20))
    n = max(3, round(2 * h / 0.06))
    for i in range(n):
        x = -h + (i + 0.5) * 2 * h / n
        c.rect(dark, x - 0.012, x + 0.012, -w + 0.04, w - 0.04)


# --- Procedural custom markings: a new shape per instance (saliency training data only) ----------

RANDOM_GLYPHS = "ABEFGHJKLMNQRTVWXYZ2345789"


def _blob_points(rng: np.random.Generator, rx: float, ry: float, lumpy: float) -> list[Point]:
    """A smooth closed curve: an ellipse whose radius wanders by a few low harmonics."""
    t = np.linspace(0.0, 2 * math.pi, 72, endpoint=False)
    r = np.ones_like(t)
    for k in range(2, 6):
        r += lumpy * rng.uniform(0.0, 1.0) / k * np.cos(k * t + rng.uniform(0, 2 * math.pi))
    r = np.clip(r, 0.35, None) / max(float(r.max()), 1e-6)
    return list(zip((rx * r * np.cos(t)).tolist(), (ry * r * np.sin(t)).tolist(), strict=True))


def _polygon_points(rng: np.random.Generator, rx: float, ry: float) -> list[Point]:
    """A random simple polygon (3 to 9 corners at sorted angles, any radius: often concave)."""
    n = int(rng.integers(3, 10))
    a = np.sort(rng.uniform(0.0, 2 * math.pi, n))
    r = rng.uniform(0.45, 1.0, n)
    return list(zip((rx * r * np.cos(a)).tolist(), (ry * r * np.sin(a)).tolist(), strict=True))


def _scribble(rng: np.random.Generator, h: float, w: float) -> list[Point]:
    """A smooth open stroke across the box (a random walk of the heading)."""
    n = int(rng.integers(12, 30))
    step = 2 * max(h, w) / n * rng.uniform(0.8, 1.4)
    heading = rng.uniform(0, 2 * math.pi)
    x, y = rng.uniform(-0.5 * h, 0.5 * h), rng.uniform(-0.5 * w, 0.5 * w)
    pts: list[Point] = [(x, y)]
    turn = rng.uniform(0.1, 0.5)
    for _ in range(n):
        heading += rng.normal(0.0, turn)
        x, y = x + step * math.cos(heading), y + step * math.sin(heading)
        if abs(x) > h or abs(y) > w:  # turn back inside the box
            heading += math.pi
            x, y = float(np.clip(x, -h, h)), float(np.clip(y, -w, w))
        pts.append((x, y))
    return pts


def random_shape(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """One of six kinds of man-made marking, drawn anew for every instance.

    Filled blobs and polygons (some with holes), outlines with a figure inside, painted strokes,
    random letters, and clusters of small parts: the variety of custom markings that no semantic
    class covers, so a network trained on them learns painted ground, not a list of designs.
    """
    h, w = c.length / 2 - 0.02, c.width / 2 - 0.02
    la = c.layer(col)
    kind = int(rng.integers(6))
    if kind == 0:  # filled blob, maybe with a hole
        c.poly(la, _blob_points(rng, h, w, rng.uniform(0.2, 0.9)))
        if rng.random() < 0.4:
            c.poly(la, _blob_points(rng, 0.35 * h, 0.35 * w, 0.3), 0.0)
    elif kind == 1:  # filled polygon, maybe with a hole
        c.poly(la, _polygon_points(rng, h, w))
        if rng.random() < 0.3:
            c.poly(la, _polygon_points(rng, 0.3 * h, 0.3 * w), 0.0)
    elif kind == 2:  # an outline with a small figure inside
        stroke = rng.uniform(0.04, 0.1)
        a, b = h - stroke, w - stroke
        outline = _blob_points(rng, a, b, 0.3) if rng.random() < 0.5 else [(a, b), (a, -b), (-a, -b), (-a, b)]
        c.line(la, outline, stroke, closed=True)
        c.poly(la, _polygon_points(rng, 0.45 * h, 0.45 * w))
    elif kind == 3:  # painted strokes
        for _ in range(int(rng.integers(1, 4))):
            c.line(la, _scribble(rng, h, w), rng.uniform(0.05, 0.14))
    elif kind == 4:  # letters that spell nothing
        n = int(rng.integers(1, 5))
        text = "".join(str(rng.choice(list(RANDOM_GLYPHS))) for _ in range(n))
        font = int(rng.choice([cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX]))
        c.text(la, text, (-h, h, -w, w), font, float(rng.uniform(0.1, 0.18)))
    else:  # a cluster of small parts
        for _ in range(int(rng.integers(2, 6))):
            cx, cy = rng.uniform(-0.6 * h, 0.6 * h), rng.uniform(-0.6 * w, 0.6 * w)
            part = _blob_points(rng, 0.3 * h, 0.3 * w, 0.5)
            c.poly(la, [(cx + x, cy + y) for x, y in part])
