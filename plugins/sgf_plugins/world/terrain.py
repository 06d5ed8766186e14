"""The ground's height field (hills, speed bumps, rough paving) and the robot's pose on its wheels."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sgf_plugins.world.layout import Hill, RoughPatch, SpatialIndex, SpeedBump

#: Wheel contact points of the robot (a 4-wheeled delivery robot): wheelbase and track (m).
WHEELBASE = 0.50
TRACK = 0.44


class Terrain:
    """Height ``z = H(x, y)`` of the campus ground and its gradient, for any array of points.

    Hills are anisotropic Gaussians, speed bumps cos^2 humps across a path, rough patches short
    waves under a raised-cosine window; all are evaluated analytically (exact heights and
    gradients), the small features only near the query points.
    """

    def __init__(
        self,
        hills: Sequence[Hill] = (),
        bumps: Sequence[SpeedBump] = (),
        rough: Sequence[RoughPatch] = (),
    ) -> None:
        self.hills = list(hills)
        # the hills' parameters as columns (one row per hill): all hills in one pass of numpy
        columns = [
            [
                h.centre[0],
                h.centre[1],
                math.cos(h.yaw),
                math.sin(h.yaw),
                h.amplitude,
                0.5 / h.sigma_along**2,
                0.5 / h.sigma_across**2,
            ]
            for h in self.hills
        ]
        self._hill_columns = np.asarray(columns, np.float64).reshape(-1, 7)[:, :, None]
        self._hill_columns32 = self._hill_columns.astype(np.float32)
        self.bumps = list(bumps)
        self.rough = list(rough)
        self._bump_index = SpatialIndex(16.0)
        for i, b in enumerate(self.bumps):
            r = max(b.half_length, b.half_width) + 0.5
            self._bump_index.add(i, b.centre[0] - r, b.centre[1] - r, b.centre[0] + r, b.centre[1] + r)
        self._rough_index = SpatialIndex(16.0)
        for i, p in enumerate(self.rough):
            self._rough_index.add(
                i, p.centre[0] - p.radius, p.centre[1] - p.radius, p.centre[0] + p.radius, p.centre[1] + p.radius
            )

    @property
    def flat(self) -> bool:
        """Whether the ground is the plane z = 0 everywhere."""
        return not (self.hills or self.bumps or self.rough)

    def height_and_gradient(
        self,
        x: np.ndarray,
        y: np.ndarray,
        near: tuple[float, float, float] | None = None,
        detail: bool = True,
        smooth: bool = True,
        rough: bool = True,
        gradient: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height ``H`` and its partial derivatives ``dH/dx``, ``dH/dy`` at points (any shape).

        ``near = (x, y, radius)`` limits the bumps and rough patches to those within ``radius`` of
        a point (the renderer skips sub-pixel features far from the camera); ``detail=False``
        leaves them out (the smooth hills only), ``smooth=False`` leaves the hills out, and
        ``gradient=False`` skips the derivatives (returned as zeros) where it saves work.
        """
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        shape = np.broadcast_shapes(x.shape, y.shape)
        x = np.broadcast_to(x, shape).ravel()
        y = np.broadcast_to(y, shape).ravel()
        if self.hills and smooth:
            h, gx, gy = self._smooth(x, y)
        else:
            h, gx, gy = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        if detail and (self.bumps or self.rough):
            if near is not None:
                lo_x, hi_x, lo_y, hi_y = near[0] - near[2], near[0] + near[2], near[1] - near[2], near[1] + near[2]
            else:
                lo_x, hi_x, lo_y, hi_y = float(x.min()), float(x.max()), float(y.min()), float(y.max())
            for i in self._bump_index.query(lo_x, lo_y, hi_x, hi_y):
                _add_bump(self.bumps[i], x, y, h, gx if gradient else None, gy if gradient else None)
            for i in self._rough_index.query(lo_x, lo_y, hi_x, hi_y) if rough else ():
                _add_rough(self.rough[i], x, y, h, gx, gy)
        return h.reshape(shape), gx.reshape(shape), gy.reshape(shape)

    def bumps_near(self, x: float, y: float, radius: float) -> list[SpeedBump]:
        """The speed bumps within ``radius`` of a point."""
        return [self.bumps[i] for i in self._bump_index.query(x - radius, y - radius, x + radius, y + radius)]

    def detail_boxes(self, x: float, y: float, radius: float, kind: str = "bumps") -> np.ndarray:
        """Bounding boxes (K, 4: x0, y0, x1, y1) of the ``bumps`` or ``rough`` patches within ``radius``."""
        boxes = []
        if kind == "bumps":
            for i in self._bump_index.query(x - radius, y - radius, x + radius, y + radius):
                b = self.bumps[i]
                r = max(b.half_length, b.half_width) + 0.2
                boxes.append((b.centre[0] - r, b.centre[1] - r, b.centre[0] + r, b.centre[1] + r))
        else:
            for i in self._rough_index.query(x - radius, y - radius, x + radius, y + radius):
                c, r = self.rough[i].centre, self.rough[i].radius
                boxes.append((c[0] - r, c[1] - r, c[0] + r, c[1] + r))
        return np.asarray(boxes, np.float64).reshape(-1, 4)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height (m) at points (any shape)."""
        return self.height_and_gradient(x, y)[0]

    def normal(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit ground normal (..., 3) at points."""
        _, gx, gy = self.height_and_gradient(x, y)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def hill_heights(
        self, x: np.ndarray, y: np.ndarray, single: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height and gradient of the smooth hills alone at points (1-D).

        ``single=True`` computes in float32, 2x faster and within a micrometre (the renderer's
        Newton steps, which stop at a millimetre, use it).
        """
        if not self.hills:
            return np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        if single:
            h, gx, gy = self._smooth(x.astype(np.float32), y.astype(np.float32), self._hill_columns32)
            return h.astype(np.float64), gx.astype(np.float64), gy.astype(np.float64)
        return self._smooth(x, y)

    def _smooth(
        self, x: np.ndarray, y: np.ndarray, columns: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The hills' height and gradient at points (1-D), all hills at once (rows) then summed."""
        table = self._hill_columns if columns is None else columns
        cx, cy, c, s, amplitude, ia, ic = (table[:, k] for k in range(7))
        dx, dy = x - cx, y - cy
        u = c * dx + s * dy  # along the hill's axis
        v = c * dy - s * dx  # across it
        e = amplitude * np.exp(-(u * u * ia + v * v * ic))
        du = u * e
        du *= -2 * ia
        dv = v * e
        dv *= -2 * ic
        h: np.ndarray = e.sum(axis=0)
        gx: np.ndarray = (c * du - s * dv).sum(axis=0)
        gy: np.ndarray = (s * du + c * dv).sum(axis=0)
        return h, gx, gy

    # -- the robot on its wheels ---------------------------------------------------------------

    def base_poses(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """Base poses (N, 4, 4) of the robot standing at ``(x, y)`` heading ``yaw`` on its four wheels.

        The wheel contacts (wheelbase x track) are lifted onto the ground; the base plane is their
        least-squares plane, its origin the plane's point under ``(x, y)``; x points along the
        heading within that plane. Roll and pitch therefore come from the wheel contacts.
        """
        x = np.atleast_1d(np.asarray(x, np.float64))
        y = np.atleast_1d(np.asarray(y, np.float64))
        yaw = np.atleast_1d(np.asarray(yaw, np.float64))
        c, s = np.cos(yaw), np.sin(yaw)
        half_l, half_t = WHEELBASE / 2, TRACK / 2
        offsets = [(half_l, half_t), (half_l, -half_t), (-half_l, half_t), (-half_l, -half_t)]
        wx = np.stack([x + c * a - s * b for a, b in offsets], axis=1)
        wy = np.stack([y + s * a + c * b for a, b in offsets], axis=1)
        z = self.height(wx, wy)
        z0 = z.mean(axis=1)
        slope_x = ((z[:, 0] + z[:, 1]) - (z[:, 2] + z[:, 3])) / (4 * half_l)
        slope_y = ((z[:, 0] + z[:, 2]) - (z[:, 1] + z[:, 3])) / (4 * half_t)
        n = len(x)
        xb = np.stack([np.ones(n), np.zeros(n), slope_x], axis=1)
        xb /= np.linalg.norm(xb, axis=1, keepdims=True)
        zb = np.stack([-slope_x, -slope_y, np.ones(n)], axis=1)
        zb /= np.linalg.norm(zb, axis=1, keepdims=True)
        yb = np.cross(zb, xb)
        local = np.stack([xb, yb, zb], axis=2)  # columns are the base axes in the heading frame
        rz = np.zeros((n, 3, 3))
        rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, :3] = rz @ local
        poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = x, y, z0
        return poses

    def base_pose(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Base pose (4, 4) of the robot standing at ``(x, y)`` heading ``yaw``."""
        return self.base_poses(np.array([x]), np.array([y]), np.array([yaw]))[0]

    def max_slope(self, points: np.ndarray) -> float:
        """Largest ground slope (rise over run) of the smooth hills at the given points (N, 2)."""
        if not self.hills:
            return 0.0
        _, gx, gy = self._smooth(points[:, 0], points[:, 1])
        return float(np.hypot(gx, gy).max())


def _add_bump(
    b: SpeedBump, x: np.ndarray, y: np.ndarray, h: np.ndarray, gx: np.ndarray | None, gy: np.ndarray | None
) -> None:
    """Add a cos^2 speed bump (tapered at its lateral ends over 0.15 m) in place (``gx is None``: height only)."""
    taper = 0.15
    d = b.direction
    dx, dy = x - b.centre[0], y - b.centre[1]
    s_all = dx * d[0] + dy * d[1]
    lat_all = dy * d[0] - dx * d[1]
    sel = np.flatnonzero((np.abs(s_all) < b.half_length) & (np.abs(lat_all) < b.half_width + taper))
    if sel.size == 0:
        return
    lat = lat_all[sel]
    ss, ll = s_all[sel], np.abs(lat)
    phase = math.pi * ss / (2 * b.half_length)
    cos_p = np.cos(phase)
    prof = cos_p * cos_p
    edge = np.clip((b.half_width + taper - ll) / taper, 0.0, 1.0)
    w = np.where(ll < b.half_width, 1.0, np.sin(0.5 * math.pi * edge) ** 2)
    h[sel] += b.height * prof * w
    if gx is None or gy is None:
        return
    dprof = -2 * cos_p * np.sin(phase) * math.pi / (2 * b.half_length)
    dw_dl = np.where(ll < b.half_width, 0.0, -np.sin(math.pi * edge) * 0.5 * math.pi / taper * np.sign(lat))
    # d/dx of s is d[0], of lat is -d[1]; d/dy of s is d[1], of lat is d[0].
    gs = b.height * dprof * w
    gl = b.height * prof * dw_dl
    gx[sel] += gs * d[0] - gl * d[1]
    gy[sel] += gs * d[1] + gl * d[0]


def _add_rough(p: RoughPatch, x: np.ndarray, y: np.ndarray, h: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> None:
    """Add a patch of uneven paving (short waves, raised-cosine window) in place."""
    box = np.flatnonzero((np.abs(x - p.centre[0]) < p.radius) & (np.abs(y - p.centre[1]) < p.radius))
    if box.size == 0:
        return
    dxb, dyb = x[box] - p.centre[0], y[box] - p.centre[1]
    rb = np.hypot(dxb, dyb)
    inside = rb < p.radius
    if not inside.any():
        return
    sel = box[inside]
    dx, dy = dxb[inside], dyb[inside]
    xs, ys, rs = x[sel], y[sel], rb[inside]
    w = 0.5 * (1.0 + np.cos(math.pi * rs / p.radius))
    dw = -0.5 * math.pi / p.radius * np.sin(math.pi * rs / p.radius)
    safe = np.maximum(rs, 1e-9)
    wave = np.zeros_like(xs)
    wx = np.zeros_like(xs)
    wy = np.zeros_like(xs)
    n = len(p.phases)
    for k in range(n):
        kx, ky = p.wavevectors[k]
        arg = kx * xs + ky * ys + p.phases[k]
        wave += np.sin(arg) / n
        cs = np.cos(arg) / n
        wx += kx * cs
        wy += ky * cs
    a = p.amplitude
    h[sel] += a * w * wave
    gx[sel] += a * (w * wx + dw * dx / safe * wave)
    gy[sel] += a * (w * wy + dw * dy / safe * wave)
