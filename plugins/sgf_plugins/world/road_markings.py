"""The standard road markings: public designs that draw the same shape wherever they are painted.

The same arrow repeats all over a campus (perceptual aliasing). Each function draws one design on
a :class:`~sgf_plugins.world.canvas.Canvas` (see :mod:`sgf_plugins.world.designs` for the table).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.canvas import BLUE, RGB, WHITE, Canvas, DrawFn, circle_points, icon_points


def arrow_straight(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A straight-ahead arrow."""
    la = c.layer(col)
    h = c.length / 2
    c.poly(la, [(-h, 0.075), (0.2, 0.075), (0.2, 0.28), (h, 0.0), (0.2, -0.28), (0.2, -0.075), (-h, -0.075)])


def arrow_turn(side: float) -> DrawFn:
    """A turn arrow: to the left for ``side`` 1, to the right for -1."""

    def draw(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
        la = c.layer(col)
        h = c.length / 2
        ys = -0.2 * side
        c.poly(la, [(-h, ys - 0.075), (0.42, ys - 0.075), (0.42, ys + 0.075), (-h, ys + 0.075)])
        c.poly(la, [(0.27, ys), (0.42, ys), (0.42, 0.12 * side), (0.27, 0.12 * side)])
        c.poly(la, [(0.08, 0.12 * side), (0.61, 0.12 * side), (0.345, 0.42 * side)])

    return draw


def arrow_uturn(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A U-turn arrow."""
    la = c.layer(col)
    h = c.length / 2
    arc = circle_points((0.35, 0.0), 0.28, n=24, start=-math.pi / 2, stop=math.pi / 2)
    path = [(-h, -0.28), *arc, (-0.15, 0.28)]
    c.line(la, path, 0.15)
    c.poly(la, [(-0.15, 0.02), (-0.15, 0.54), (-h, 0.28)])


def diamond(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A diamond outline."""
    la = c.layer(col)
    h, w = c.length / 2 - 0.05, c.width / 2 - 0.05
    c.line(la, [(h, 0), (0, w), (-h, 0), (0, -w)], 0.1, closed=True)


def solid_line(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A solid line filling the box."""
    c.rect(c.layer(col), -c.length / 2, c.length / 2, -c.width / 2, c.width / 2)


def dashed_line(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A dashed line: 0.6 m dashes, 0.4 m gaps."""
    la = c.layer(col)
    dash, gap = 0.6, 0.4
    x = -c.length / 2
    while x + dash <= c.length / 2 + 1e-9:
        c.rect(la, x, x + dash, -c.width / 2, c.width / 2)
        x += dash + gap


def stop_line(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A stop line filling the box."""
    c.rect(c.layer(col), -c.length / 2, c.length / 2, -c.width / 2, c.width / 2)


def zebra(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A zebra crossing: 0.3 m stripes along the direction of travel, 0.3 m apart."""
    la = c.layer(col)
    stripe = 0.3
    n = int((c.width + stripe) // (2 * stripe))
    span = n * 2 * stripe - stripe
    for i in range(n):
        y0 = -span / 2 + i * 2 * stripe
        c.rect(la, -c.length / 2, c.length / 2, y0, y0 + stripe)


def give_way(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A give-way line: a row of triangles pointing back."""
    la = c.layer(col)
    tooth = 0.45
    n = int(c.width // (tooth + 0.15))
    span = n * (tooth + 0.15) - 0.15
    for i in range(n):
        y0 = -span / 2 + i * (tooth + 0.15)
        c.poly(la, [(c.length / 2, y0), (c.length / 2, y0 + tooth), (-c.length / 2, y0 + tooth / 2)])


def chevrons(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A row of chevrons pointing forward (painted on speed bumps)."""
    la = c.layer(col)
    pitch = 0.6
    n = int(c.width // pitch)
    span = n * pitch
    for i in range(n):
        yc = -span / 2 + (i + 0.5) * pitch
        c.line(la, [(-0.16, yc - 0.22), (0.16, yc), (-0.16, yc + 0.22)], 0.09)


def painted_word(word: str, font: int = cv2.FONT_HERSHEY_DUPLEX, weight: float = 0.16) -> DrawFn:
    """A drawing of ``word`` in a Hershey font stretched over the box."""

    def draw(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
        c.text(c.layer(col), word, (-c.length / 2, c.length / 2, -c.width / 2, c.width / 2), font, weight)

    return draw


def bicycle(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A bicycle symbol."""
    la = c.layer(col)
    r = 0.27
    c.ring(la, (-0.45, -0.12), r, 0.06)
    c.ring(la, (0.45, -0.12), r, 0.06)
    frame = [(-0.45, -0.12), (-0.05, -0.12), (0.28, 0.22), (-0.2, 0.22), (-0.45, -0.12)]
    c.line(la, frame, 0.06)
    c.line(la, [(-0.05, -0.12), (-0.25, 0.3)], 0.06)
    c.line(la, [(-0.34, 0.31), (-0.14, 0.31)], 0.07)
    c.line(la, [(0.45, -0.12), (0.3, 0.34), (0.42, 0.38)], 0.06)


def wheelchair(c: Canvas, rng: np.random.Generator, col: RGB) -> None:
    """A white wheelchair symbol on a blue square."""
    h = c.length / 2
    c.rect(c.layer(BLUE), -h, h, -h, h)
    la = c.layer(WHITE)
    s = c.length / 1.0
    c.disc(la, icon_points([(0.04 * s, 0.32 * s)])[0], 0.075 * s)
    c.line(
        la, icon_points([(0.0, 0.2 * s), (-0.02 * s, -0.04 * s), (0.2 * s, -0.04 * s), (0.28 * s, -0.3 * s)]), 0.07 * s
    )
    c.line(la, icon_points([(0.0, 0.1 * s), (0.18 * s, 0.1 * s)]), 0.06 * s)
    arc = circle_points((-0.06 * s, -0.12 * s), 0.22 * s, n=28, start=math.radians(-60), stop=math.radians(200))
    c.line(la, icon_points(arc), 0.06 * s)
