"""The metric canvas a marking design is drawn on, its paint colours and its drawing primitives.

A design draws itself in metres on a :class:`Canvas` in the marking's local frame (x forward,
y left; the canvas is laid out like a BEV image: row 0 is the far end, column 0 the left side),
so that text and arrows read correctly for a robot driving along +x.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import cv2
import numpy as np

#: An 8-bit colour (red, green, blue).
RGB = tuple[int, int, int]
#: A point in metres (or in a unit box) of a drawing.
Point = tuple[float, float]

#: The paint, metal and tile colours of the designs.
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


def icon_points(points: Sequence[Point]) -> list[Point]:
    """Icon coordinates (a right, b up as the robot sees the icon) to local (x forward, y left)."""
    return [(b, -a) for a, b in points]


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


#: A design's drawing: paints one instance on a canvas with the instance's random generator and colour.
DrawFn = Callable[[Canvas, np.random.Generator, RGB], None]
