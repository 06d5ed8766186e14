"""The library of ground-marking designs: standard road markings and custom campus markings.

A design draws itself in metres on a :class:`Canvas` in the marking's local frame (x forward,
y left; the canvas is laid out like a BEV image: row 0 is the far end, column 0 the left side),
so that text and arrows read correctly for a robot driving along +x. Standard designs draw the
same shape every time (the same arrow repeats all over a campus: perceptual aliasing); custom
designs vary their content, size and colour per instance.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from sgf_pipeline.errors import ConfigError

RGB = tuple[int, int, int]
Point = tuple[float, float]

WHITE: RGB = (236, 236, 228)
YELLOW: RGB = (238, 188, 36)
BLUE: RGB = (34, 88, 172)
GREEN: RGB = (58, 142, 84)
RED: RGB = (186, 48, 44)
ORANGE: RGB = (232, 118, 34)
NAVY: RGB = (32, 46, 96)
MAROON: RGB = (120, 30, 48)
METAL: RGB = (74, 74, 76)
METAL_DARK: RGB = (42, 42, 44)
RUST: RGB = (120, 74, 48)
TACTILE: RGB = (232, 196, 40)

_SHIFT = 4
_ONE = 1 << _SHIFT


class Canvas:
    """A metric drawing surface for one marking: paint layers of coverage in [0, 1].

    Pixel ``(row, col)`` has its centre at local ``x = x_top - (row + 0.5) res`` and
    ``y = y_left - (col + 0.5) res``, with one spare pixel around the ``length x width`` box.
    Layers are drawn ``ss`` times finer without anti-aliasing and area-averaged, so a pixel's
    coverage is the exact fraction of it that is painted (shapes keep their true size).
    """

    def __init__(self, length: float, width: float, res: float, ss: int = 4) -> None:
        self.length = float(length)
        self.width = float(width)
        self.res = float(res)
        self.ss = ss
        self.sres = self.res / ss
        self.rows = math.ceil(self.length / res) + 2
        self.cols = math.ceil(self.width / res) + 2
        self.x_top = self.rows * res / 2.0
        self.y_left = self.cols * res / 2.0
        self.layers: list[tuple[RGB, np.ndarray]] = []

    # -- coordinates ---------------------------------------------------------------------

    def to_pixels(self, points: Iterable[Point]) -> np.ndarray:
        """Fixed-point pixel coordinates (col, row) of local metric points, for cv2 with ``shift``."""
        pts = np.asarray(list(points), dtype=np.float64).reshape(-1, 2)
        col = (self.y_left - pts[:, 1]) / self.sres - 0.5
        row = (self.x_top - pts[:, 0]) / self.sres - 0.5
        return np.round(np.stack([col, row], axis=1) * _ONE).astype(np.int32)

    def px(self, metres: float) -> float:
        """A length in (supersampled) drawing pixels."""
        return metres / self.sres

    def layer(self, colour: RGB) -> np.ndarray:
        """A new empty paint layer drawn over the previous ones."""
        cover = np.zeros((self.rows * self.ss, self.cols * self.ss), np.float32)
        self.layers.append((colour, cover))
        return cover

    # -- primitives (all in metres, local frame) ----------------------------------------

    def poly(self, layer: np.ndarray, points: Sequence[Point], value: float = 1.0) -> None:
        """Fill a polygon."""
        cv2.fillPoly(layer, [self.to_pixels(points)], value, cv2.LINE_8, _SHIFT)

    def polys(self, layer: np.ndarray, polygons: Sequence[Sequence[Point]], value: float = 1.0) -> None:
        """Fill several polygons at once (even-odd holes are not used: draw holes with value 0)."""
        cv2.fillPoly(layer, [self.to_pixels(p) for p in polygons], value, cv2.LINE_8, _SHIFT)

    def line(self, layer: np.ndarray, points: Sequence[Point], width: float, closed: bool = False) -> None:
        """A stroked polyline with round joints."""
        thickness = max(1, round(self.px(width)))
        cv2.polylines(layer, [self.to_pixels(points)], closed, 1.0, thickness, cv2.LINE_8, _SHIFT)

    def rect(self, layer: np.ndarray, x0: float, x1: float, y0: float, y1: float, value: float = 1.0) -> None:
        """Fill an axis-aligned rectangle ``x in [x0, x1], y in [y0, y1]``."""
        self.poly(layer, [(x0, y0), (x1, y0), (x1, y1), (x0, y1)], value)

    def disc(self, layer: np.ndarray, centre: Point, radius: float, value: float = 1.0) -> None:
        """Fill a circle."""
        self.poly(layer, circle_points(centre, radius), value)

    def ring(self, layer: np.ndarray, centre: Point, radius: float, width: float) -> None:
        """Stroke a circle."""
        self.line(layer, circle_points(centre, radius), width, closed=True)

    def text(
        self,
        layer: np.ndarray,
        text: str,
        box: tuple[float, float, float, float],
        font: int = cv2.FONT_HERSHEY_SIMPLEX,
        weight: float = 0.12,
    ) -> None:
        """Paint text stretched into ``box = (x0, x1, y0, y1)``, read by a robot driving along +x."""
        glyphs = _render_text(text, font, weight)
        self._paste(layer, glyphs, box)

    def strokes(
        self,
        layer: np.ndarray,
        strokes: Sequence[Sequence[Point]],
        box: tuple[float, float, float, float],
        weight: float,
    ) -> None:
        """Paint polylines given in a unit box (u right, v down, as seen by the robot) into ``box``."""
        x0, x1, y0, y1 = box
        for stroke in strokes:
            pts = [(x1 - v * (x1 - x0), y1 - u * (y1 - y0)) for u, v in stroke]
            self.line(layer, pts, weight * (x1 - x0))

    def _paste(self, layer: np.ndarray, glyphs: np.ndarray, box: tuple[float, float, float, float]) -> None:
        x0, x1, y0, y1 = box
        c0 = (self.y_left - y1) / self.sres - 0.5
        c1 = (self.y_left - y0) / self.sres - 0.5
        r0 = (self.x_top - x1) / self.sres - 0.5
        r1 = (self.x_top - x0) / self.sres - 0.5
        # Affine map from glyph pixels to canvas pixels (glyph top-left -> box far-left corner).
        gh, gw = glyphs.shape
        sx = (c1 - c0) / max(gw - 1, 1)
        sy = (r1 - r0) / max(gh - 1, 1)
        matrix = np.array([[sx, 0.0, c0], [0.0, sy, r0]])
        warped = cv2.warpAffine(glyphs, matrix, (self.cols * self.ss, self.rows * self.ss), flags=cv2.INTER_LINEAR)
        np.maximum(layer, warped, out=layer)

    # -- result --------------------------------------------------------------------------

    def compose(self) -> tuple[np.ndarray, np.ndarray]:
        """The painted colour (rows, cols, 3) float32 and total coverage (rows, cols) float32."""
        colour = np.zeros((self.rows, self.cols, 3), np.float32)
        alpha = np.zeros((self.rows, self.cols), np.float32)
        for rgb, cover in self.layers:
            if self.ss > 1:
                cover = cv2.resize(cover, (self.cols, self.rows), interpolation=cv2.INTER_AREA)
            a = np.clip(cover, 0.0, 1.0)
            colour = colour * (1.0 - a[:, :, None]) + np.asarray(rgb, np.float32) * a[:, :, None]
            alpha = alpha + a * (1.0 - alpha)
        safe = np.maximum(alpha, 1e-6)[:, :, None]
        # Colour is stored un-premultiplied so that it can be blended with a worn alpha later.
        colour = np.where(alpha[:, :, None] > 1e-6, colour / safe, 0.0)
        return colour.astype(np.float32), alpha


def circle_points(
    centre: Point, radius: float, n: int = 64, start: float = 0.0, stop: float = 2 * math.pi
) -> list[Point]:
    """Points on a circle (or an arc from ``start`` to ``stop`` rad, counter-clockwise seen from above)."""
    closed = abs(stop - start - 2 * math.pi) < 1e-9
    angles = np.linspace(start, stop, n, endpoint=not closed)
    return [(centre[0] + radius * math.cos(a), centre[1] + radius * math.sin(a)) for a in angles]


def _render_text(text: str, font: int, weight: float) -> np.ndarray:
    """Glyph coverage of ``text`` (float32, tight box) drawn large with a Hershey font."""
    scale = 4.0
    thickness = max(2, round(weight * 100))
    (w, h), base = cv2.getTextSize(text, font, scale, thickness)
    pad = thickness + 4
    img = np.zeros((h + base + 2 * pad, w + 2 * pad), np.uint8)
    cv2.putText(img, text, (pad, pad + h), font, scale, 255, thickness, cv2.LINE_AA)
    ys, xs = np.nonzero(img)
    if ys.size == 0:
        return np.zeros((2, 2), np.float32)
    crop = img[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
    return crop.astype(np.float32) / 255.0


# --- Hangul: a small stroke font (jamo composed into syllable blocks) ---------------------------

_JAMO: dict[str, list[list[Point]]] = {
    "ㄱ": [[(0.12, 0.15), (0.85, 0.15), (0.85, 0.9)]],
    "ㄴ": [[(0.15, 0.1), (0.15, 0.85), (0.9, 0.85)]],
    "ㄷ": [[(0.85, 0.15), (0.15, 0.15), (0.15, 0.85), (0.9, 0.85)]],
    "ㄹ": [[(0.12, 0.12), (0.85, 0.12), (0.85, 0.48), (0.15, 0.48), (0.15, 0.86), (0.9, 0.86)]],
    "ㅁ": [[(0.15, 0.15), (0.85, 0.15), (0.85, 0.85), (0.15, 0.85), (0.15, 0.15)]],
    "ㅂ": [[(0.15, 0.08), (0.15, 0.88), (0.85, 0.88), (0.85, 0.08)], [(0.15, 0.48), (0.85, 0.48)]],
    "ㅅ": [[(0.5, 0.1), (0.45, 0.42), (0.1, 0.9)], [(0.47, 0.45), (0.9, 0.9)]],
    "ㅇ": [[(0.5 + 0.36 * math.cos(a), 0.5 + 0.36 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 25)]],
    "ㅈ": [[(0.12, 0.15), (0.88, 0.15)], [(0.5, 0.15), (0.1, 0.9)], [(0.5, 0.45), (0.9, 0.9)]],
    "ㅊ": [
        [(0.42, 0.0), (0.6, 0.1)],
        [(0.12, 0.26), (0.88, 0.26)],
        [(0.5, 0.26), (0.1, 0.95)],
        [(0.5, 0.52), (0.9, 0.95)],
    ],
    "ㅎ": [
        [(0.36, 0.04), (0.64, 0.04)],
        [(0.12, 0.22), (0.88, 0.22)],
        [(0.5 + 0.24 * math.cos(a), 0.64 + 0.24 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 21)],
    ],
    "ㅏ": [[(0.4, 0.0), (0.4, 1.0)], [(0.4, 0.48), (0.85, 0.48)]],
    "ㅓ": [[(0.6, 0.0), (0.6, 1.0)], [(0.15, 0.48), (0.6, 0.48)]],
    "ㅣ": [[(0.5, 0.0), (0.5, 1.0)]],
    "ㅐ": [[(0.3, 0.0), (0.3, 1.0)], [(0.3, 0.48), (0.62, 0.48)], [(0.75, 0.0), (0.75, 1.0)]],
    "ㅗ": [[(0.5, 0.25), (0.5, 0.68)], [(0.0, 0.68), (1.0, 0.68)]],
    "ㅜ": [[(0.0, 0.3), (1.0, 0.3)], [(0.5, 0.3), (0.5, 0.78)]],
    "ㅡ": [[(0.0, 0.5), (1.0, 0.5)]],
}
_INITIALS = "ㄱㄲㄴㄷㄸㄹㅁㅂㅃㅅㅆㅇㅈㅉㅊㅋㅌㅍㅎ"
_MEDIALS = "ㅏㅐㅑㅒㅓㅔㅕㅖㅗㅘㅙㅚㅛㅜㅝㅞㅟㅠㅡㅢㅣ"
_FINALS = " ㄱㄲㄳㄴㄵㄶㄷㄹㄺㄻㄼㄽㄾㄿㅀㅁㅂㅄㅅㅆㅇㅈㅊㅋㅌㅍㅎ"
_HORIZONTAL_VOWELS = "ㅗㅜㅡ"


def hangul_strokes(word: str) -> list[list[Point]]:
    """Strokes of a Hangul word in a unit box per syllable laid side by side (u in [0, n])."""
    out: list[list[Point]] = []
    for i, ch in enumerate(word):
        code = ord(ch) - 0xAC00
        if not 0 <= code < 11172:
            raise ValueError(f"{ch!r} is not a Hangul syllable")
        initial, medial, final = _INITIALS[code // 588], _MEDIALS[(code % 588) // 28], _FINALS[code % 28].strip()
        horizontal = medial in _HORIZONTAL_VOWELS
        if horizontal:
            boxes = (
                [(0.2, 0.0, 0.8, 0.35), (0.0, 0.3, 1.0, 0.6), (0.15, 0.62, 0.85, 1.0)]
                if final
                else [
                    (0.15, 0.0, 0.85, 0.5),
                    (0.0, 0.45, 1.0, 0.9),
                ]
            )
        else:
            boxes = (
                [(0.0, 0.0, 0.6, 0.5), (0.55, 0.0, 1.0, 0.6), (0.1, 0.62, 0.9, 1.0)]
                if final
                else [
                    (0.0, 0.1, 0.6, 0.9),
                    (0.55, 0.0, 1.0, 1.0),
                ]
            )
        parts = [initial, medial] + ([final] if final else [])
        for jamo, (u0, v0, u1, v1) in zip(parts, boxes, strict=True):
            if jamo not in _JAMO:
                raise ValueError(f"the stroke font has no jamo {jamo!r} (in {word!r})")
            for stroke in _JAMO[jamo]:
                out.append([(i + 0.08 + 0.84 * (u0 + u * (u1 - u0)), v0 + v * (v1 - v0)) for u, v in stroke])
    return out


# --- the design table --------------------------------------------------------------------------

Category = Literal["standard", "custom"]
Placement = Literal["lane", "across", "along", "free", "edge", "bump"]
DrawFn = Callable[[Canvas, "np.random.Generator", RGB], None]


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


def _arrow_straight(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    h = c.length / 2
    c.poly(la, [(-h, 0.075), (0.2, 0.075), (0.2, 0.28), (h, 0.0), (0.2, -0.28), (0.2, -0.075), (-h, -0.075)])


def _arrow_turn(side: float) -> DrawFn:
    def draw(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
        la = c.layer(col)
        h = c.length / 2
        ys = -0.2 * side
        c.poly(la, [(-h, ys - 0.075), (0.42, ys - 0.075), (0.42, ys + 0.075), (-h, ys + 0.075)])
        c.poly(la, [(0.27, ys), (0.42, ys), (0.42, 0.12 * side), (0.27, 0.12 * side)])
        c.poly(la, [(0.08, 0.12 * side), (0.61, 0.12 * side), (0.345, 0.42 * side)])

    return draw


def _arrow_uturn(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    h = c.length / 2
    arc = circle_points((0.35, 0.0), 0.28, n=24, start=-math.pi / 2, stop=math.pi / 2)
    path = [(-h, -0.28), *arc, (-0.15, 0.28)]
    c.line(la, path, 0.15)
    c.poly(la, [(-0.15, 0.02), (-0.15, 0.54), (-h, 0.28)])


def _diamond(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    h, w = c.length / 2 - 0.05, c.width / 2 - 0.05
    c.line(la, [(h, 0), (0, w), (-h, 0), (0, -w)], 0.1, closed=True)


def _solid_line(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    c.rect(c.layer(col), -c.length / 2, c.length / 2, -c.width / 2, c.width / 2)


def _dashed_line(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    dash, gap = 0.6, 0.4
    x = -c.length / 2
    while x + dash <= c.length / 2 + 1e-9:
        c.rect(la, x, x + dash, -c.width / 2, c.width / 2)
        x += dash + gap


def _stop_line(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    c.rect(c.layer(col), -c.length / 2, c.length / 2, -c.width / 2, c.width / 2)


def _zebra(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    stripe = 0.3
    n = int((c.width + stripe) // (2 * stripe))
    span = n * 2 * stripe - stripe
    for i in range(n):
        y0 = -span / 2 + i * 2 * stripe
        c.rect(la, -c.length / 2, c.length / 2, y0, y0 + stripe)


def _give_way(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    tooth = 0.45
    n = int(c.width // (tooth + 0.15))
    span = n * (tooth + 0.15) - 0.15
    for i in range(n):
        y0 = -span / 2 + i * (tooth + 0.15)
        c.poly(la, [(c.length / 2, y0), (c.length / 2, y0 + tooth), (-c.length / 2, y0 + tooth / 2)])


def _chevrons(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    pitch = 0.6
    n = int(c.width // pitch)
    span = n * pitch
    for i in range(n):
        yc = -span / 2 + (i + 0.5) * pitch
        c.line(la, [(-0.16, yc - 0.22), (0.16, yc), (-0.16, yc + 0.22)], 0.09)


def _word(word: str, font: int = cv2.FONT_HERSHEY_DUPLEX, weight: float = 0.16) -> DrawFn:
    def draw(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
        c.text(c.layer(col), word, (-c.length / 2, c.length / 2, -c.width / 2, c.width / 2), font, weight)

    return draw


def _bicycle(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    r = 0.27
    c.ring(la, (-0.45, -0.12), r, 0.06)
    c.ring(la, (0.45, -0.12), r, 0.06)
    frame = [(-0.45, -0.12), (-0.05, -0.12), (0.28, 0.22), (-0.2, 0.22), (-0.45, -0.12)]
    c.line(la, frame, 0.06)
    c.line(la, [(-0.05, -0.12), (-0.25, 0.3)], 0.06)
    c.line(la, [(-0.34, 0.31), (-0.14, 0.31)], 0.07)
    c.line(la, [(0.45, -0.12), (0.3, 0.34), (0.42, 0.38)], 0.06)


def _icon(points: Sequence[Point]) -> list[Point]:
    """Icon coordinates (a right, b up as the robot sees the icon) to local (x forward, y left)."""
    return [(b, -a) for a, b in points]


def _wheelchair(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    h = c.length / 2
    c.rect(c.layer(BLUE), -h, h, -h, h)
    la = c.layer(WHITE)
    s = c.length / 1.0
    c.disc(la, _icon([(0.04 * s, 0.32 * s)])[0], 0.075 * s)
    c.line(la, _icon([(0.0, 0.2 * s), (-0.02 * s, -0.04 * s), (0.2 * s, -0.04 * s), (0.28 * s, -0.3 * s)]), 0.07 * s)
    c.line(la, _icon([(0.0, 0.1 * s), (0.18 * s, 0.1 * s)]), 0.06 * s)
    arc = circle_points((-0.06 * s, -0.12 * s), 0.22 * s, n=28, start=math.radians(-60), stop=math.radians(200))
    c.line(la, _icon(arc), 0.06 * s)


def _logo_shield(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    h, w = c.length / 2, c.width / 2
    outline = _icon(
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


def _logo_ring(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    r = c.length / 2 - 0.03
    la = c.layer(col)
    c.ring(la, (0.0, 0.0), r - 0.05, 0.09)
    c.ring(la, (0.0, 0.0), r - 0.2, 0.03)
    # a stylised flame or tree growing from a base line, and the founding year under it
    c.poly(
        la,
        _icon(
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


def _text_hangul(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    word = str(rng.choice(HANGUL_WORDS))
    n = len(word)
    h, w = c.length / 2, c.width / 2
    box_w = min(2 * w, n * 2 * h * 0.8)
    c.strokes(c.layer(col), _scale_strokes(hangul_strokes(word), n), (-h, h, -box_w / 2, box_w / 2), 0.11)


def _scale_strokes(strokes: list[list[Point]], n: int) -> list[list[Point]]:
    return [[(u / n, v) for u, v in s] for s in strokes]


def _text_font(words: Sequence[str], fonts: Sequence[int], weight: float) -> DrawFn:
    def draw(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
        word = str(rng.choice(list(words)))
        font = int(rng.choice(list(fonts)))
        if rng.random() < 0.3:
            font |= cv2.FONT_ITALIC
        c.text(c.layer(col), word, (-c.length / 2, c.length / 2, -c.width / 2, c.width / 2), font, weight)

    return draw


def _direction_sign(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


def _parking_number(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    h, w = c.length / 2, c.width / 2
    la = c.layer(col)
    c.line(la, [(h, w - 0.05), (-h + 0.05, w - 0.05), (-h + 0.05, -w + 0.05), (h, -w + 0.05)], 0.1)
    number = f"{int(rng.integers(1, 99)):02d}"
    c.text(la, number, (-h + 0.25, h - 0.15, -w + 0.22, w - 0.22), cv2.FONT_HERSHEY_SIMPLEX, 0.14)


def _coloured_zone(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


def _tactile_dots(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


def _tactile_bars(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    h, w = c.length / 2, c.width / 2
    c.rect(c.layer(col), -h, h, -w, w)
    bars = c.layer(tuple(int(v * 0.78) for v in col))  # type: ignore[arg-type]
    n = max(2, round(2 * w / 0.075))
    for j in range(n):
        y = -w + (j + 0.5) * 2 * w / n
        c.line(bars, [(-h + 0.04, y), (h - 0.04, y)], 0.025)


def _painted_star(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    c.poly(c.layer(col), _star_points((0.0, 0.0), c.length / 2 - 0.02, inner=0.42))


def _painted_heart(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    t = np.linspace(0, 2 * math.pi, 80, endpoint=False)
    a = 16 * np.sin(t) ** 3
    b = 13 * np.cos(t) - 5 * np.cos(2 * t) - 2 * np.cos(3 * t) - np.cos(4 * t)
    s = c.length / 2 / 17.0
    c.poly(c.layer(col), _icon(list(zip((a * s).tolist(), (b * s + 1.5 * s).tolist(), strict=True))))


def _footprint(cx: float, cy: float, mirror: float) -> list[list[Point]]:
    """A shoe print about 0.27 m long pointing along +x: the sole (ball and toes) and the heel."""
    a = np.linspace(0.0, 2 * math.pi, 28, endpoint=False)
    sole = [(cx + 0.045 + 0.085 * math.cos(t), cy + mirror * (0.012 + 0.045 * math.sin(t))) for t in a]
    heel = [(cx - 0.085 + 0.05 * math.cos(t), cy + 0.038 * math.sin(t)) for t in a]
    return [sole, heel]


def _painted_footprints(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    la = c.layer(col)
    h, w = c.length / 2, c.width / 2
    for k in range(4):
        x = -h + 0.15 + k * (2 * h - 0.3) / 3
        y = (w - 0.07) * (1 if k % 2 == 0 else -1)
        for p in _footprint(x, y, 1.0 if k % 2 == 0 else -1.0):
            c.poly(la, p)


def _delivery_pickup(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    r = c.length / 2 - 0.03
    la = c.layer(col)
    c.ring(la, (0.0, 0.0), r - 0.04, 0.07)
    # a parcel box with a tick, and the words under it
    c.rect(la, 0.05 * r, 0.55 * r, -0.3 * r, 0.3 * r)
    c.rect(c.layer((40, 40, 40)), 0.3 * r - 0.015, 0.3 * r + 0.015, -0.3 * r, 0.3 * r)
    c.text(c.layer(col), "PICK UP", (-0.6 * r, -0.1 * r, -0.65 * r, 0.65 * r), cv2.FONT_HERSHEY_SIMPLEX, 0.12)


def _delivery_dropoff(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


def _manhole(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


def _drain_grate(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


def _random_shape(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
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


#: Every design, standard (public road markings, identical wherever painted) and custom.
DESIGNS: dict[str, MarkingDesign] = {
    d.name: d
    for d in (
        MarkingDesign("solid_line", "line", "standard", True, (3.0, 0.15), _solid_line, "along", (WHITE, YELLOW)),
        MarkingDesign("dashed_line", "line", "standard", True, (2.6, 0.12), _dashed_line, "along", (WHITE, YELLOW)),
        MarkingDesign("stop_line", "line", "standard", True, (0.4, 2.6), _stop_line, "across", weight=0.8),
        MarkingDesign("zebra_crossing", "crossing", "standard", True, (2.0, 2.7), _zebra, "across", weight=1.2),
        MarkingDesign("give_way", "crossing", "standard", False, (0.55, 2.4), _give_way, "across", weight=0.6),
        MarkingDesign("arrow_straight", "arrow", "standard", False, (1.8, 0.6), _arrow_straight, "lane", weight=1.4),
        MarkingDesign("arrow_left", "arrow", "standard", False, (1.8, 0.9), _arrow_turn(1.0), "lane", weight=1.0),
        MarkingDesign("arrow_right", "arrow", "standard", False, (1.8, 0.9), _arrow_turn(-1.0), "lane", weight=1.0),
        MarkingDesign("arrow_uturn", "arrow", "standard", False, (1.6, 1.0), _arrow_uturn, "lane", weight=0.6),
        MarkingDesign("diamond", "diamond", "standard", True, (2.0, 0.8), _diamond, "lane", weight=0.8),
        MarkingDesign("number_30", "painted_text", "standard", False, (1.5, 0.9), _word("30"), "lane", (WHITE, YELLOW)),
        MarkingDesign(
            "word_slow", "painted_text", "standard", False, (1.4, 1.8), _word("SLOW"), "lane", (WHITE, YELLOW)
        ),
        MarkingDesign("word_stop", "painted_text", "standard", False, (1.4, 1.8), _word("STOP"), "lane", weight=0.7),
        MarkingDesign("bicycle", "symbol", "standard", False, (1.6, 0.9), _bicycle, "lane", weight=1.0),
        MarkingDesign("wheelchair", "symbol", "standard", False, (1.0, 1.0), _wheelchair, "lane", weight=0.6),
        MarkingDesign(
            "speed_bump_chevrons",
            "chevrons",
            "standard",
            False,
            (0.5, 2.4),
            _chevrons,
            "bump",
            (WHITE, YELLOW),
            weight=0.0,
        ),
        MarkingDesign(
            "campus_logo_shield", "logo", "custom", False, (1.2, 1.0), _logo_shield, "free", (NAVY, MAROON, GREEN), 0.25
        ),
        MarkingDesign(
            "campus_logo_ring", "logo", "custom", False, (1.3, 1.3), _logo_ring, "free", (NAVY, MAROON, WHITE), 0.25
        ),
        MarkingDesign(
            "text_hangul", "text_custom", "custom", False, (0.7, 1.9), _text_hangul, "free", (WHITE, YELLOW, GREEN), 0.2
        ),
        MarkingDesign(
            "text_script",
            "text_custom",
            "custom",
            False,
            (0.6, 2.0),
            _text_font(SCRIPT_WORDS, (cv2.FONT_HERSHEY_SCRIPT_SIMPLEX, cv2.FONT_HERSHEY_SCRIPT_COMPLEX), 0.1),
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
            _text_font(
                LATIN_WORDS, (cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_DUPLEX), 0.12
            ),
            "free",
            (WHITE, YELLOW, NAVY),
            0.2,
        ),
        MarkingDesign(
            "direction_sign", "sign", "custom", False, (0.7, 1.8), _direction_sign, "free", (WHITE, YELLOW, BLUE), 0.2
        ),
        MarkingDesign(
            "parking_number", "parking", "custom", False, (1.2, 1.0), _parking_number, "edge", (WHITE, YELLOW), 0.1
        ),
        MarkingDesign(
            "coloured_zone",
            "zone",
            "custom",
            False,
            (1.6, 1.3),
            _coloured_zone,
            "free",
            (GREEN, BLUE, RED, ORANGE),
            0.3,
        ),
        MarkingDesign(
            "tactile_dots", "tactile", "custom", True, (0.6, 0.6), _tactile_dots, "free", (TACTILE,), material="tile"
        ),
        MarkingDesign(
            "tactile_bars", "tactile", "custom", True, (0.6, 0.9), _tactile_bars, "across", (TACTILE,), material="tile"
        ),
        MarkingDesign(
            "painted_star",
            "painted_shape",
            "custom",
            True,
            (1.0, 1.0),
            _painted_star,
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
            _painted_heart,
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
            _painted_footprints,
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
            _delivery_pickup,
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
            _delivery_dropoff,
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
            _manhole,
            "free",
            (METAL, RUST),
            0.15,
            material="metal",
        ),
        MarkingDesign(
            "drain_grate", "utility", "custom", True, (0.8, 0.4), _drain_grate, "edge", (METAL,), 0.1, material="metal"
        ),
        # Never painted unless a world asks for it (``design_weights``): saliency training data.
        MarkingDesign(
            "random_shape",
            "procedural",
            "custom",
            False,
            (1.0, 1.0),
            _random_shape,
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


@dataclass(frozen=True)
class Raster:
    """A marking rasterised in its local frame: colour, worn paint alpha and the instance mask."""

    colour: np.ndarray
    alpha: np.ndarray
    mask: np.ndarray
    res: float
    x_top: float
    y_left: float

    def local_to_pixel_matrix(self) -> np.ndarray:
        """2x3 affine map from local ``(x, y, 1)`` to pixel ``(col, row)``."""
        r = self.res
        return np.array([[0.0, -1.0 / r, self.y_left / r - 0.5], [-1.0 / r, 0.0, self.x_top / r - 0.5]])


def rasterise(
    design: MarkingDesign,
    length: float,
    width: float,
    res: float,
    colour: RGB,
    content_seed: int,
    wear: float = 0.0,
    wear_seed: int = 0,
) -> Raster:
    """Draw a design at ``res`` m/pixel; ``wear`` in [0, 1] fades and chips the paint (not the mask).

    ``content_seed`` picks the instance's content (words, numbers) and must be the same at every
    resolution so that all levels of detail show the same marking.
    """
    canvas = Canvas(length, width, res)
    design.draw(canvas, np.random.default_rng(content_seed), colour)
    rgb, alpha = canvas.compose()
    mask = alpha > 0.5
    if wear > 0.0:
        from sgf_plugins.world.noise import lattice_noise

        # Chips and fading fixed in the marking's own frame, so every level of detail agrees.
        x0 = -canvas.y_left
        chips = lattice_noise(wear_seed, x0, canvas.x_top, canvas.cols, canvas.rows, res, 0.08)
        blotch = lattice_noise(wear_seed + 1, x0, canvas.x_top, canvas.cols, canvas.rows, res, 0.64)
        keep = np.clip(1.0 - wear * (0.45 + 0.35 * blotch) - np.where(chips > 1.0 - 0.9 * wear, 0.8, 0.0), 0.05, 1.0)
        if design.material != "paint":
            keep = np.clip(0.6 + 0.4 * keep, 0.0, 1.0)
        alpha = alpha * keep.astype(np.float32)
    return Raster(rgb, alpha.astype(np.float32), mask, res, canvas.x_top, canvas.y_left)


def contact_sheet(res: float = 0.01, seed: int = 0) -> np.ndarray:
    """Every design drawn once on asphalt grey, in a grid (for documentation and eyeballing)."""
    tiles = []
    for i, d in enumerate(DESIGNS.values()):
        r = rasterise(d, d.size[0], d.size[1], res, d.colours[0], seed + i)
        cell = np.full((int(3.2 / res), int(3.2 / res), 3), 90.0, np.float32)
        h, w = r.alpha.shape
        y0, x0 = (cell.shape[0] - h) // 2, (cell.shape[1] - w) // 2
        region = cell[y0 : y0 + h, x0 : x0 + w]
        a = r.alpha[:, :, None]
        cell[y0 : y0 + h, x0 : x0 + w] = region * (1 - a) + r.colour * a
        cv2.putText(cell, d.name, (6, cell.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
        tiles.append(cell)
    cols = 6
    while len(tiles) % cols:
        tiles.append(np.full_like(tiles[0], 60.0))
    rows = [np.hstack(tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    return np.clip(np.vstack(rows), 0, 255).astype(np.uint8)
