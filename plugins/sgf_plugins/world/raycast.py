"""The camera's rays on the terrain: a coarse grid of rays, their hits, and exact pixels on bumps.

Per frame the rays of a coarse grid (every 8th pixel) are intersected with the height field
(plane start, Newton steps on the hills, a march through the height band of nearby bumps).
Quantities at the samples are carried to every pixel by exact bilinear interpolation
(:meth:`RayCaster.upsample`); pixels that see a speed bump are ray cast one by one.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_plugins.world.terrain import Terrain
from sgf_plugins.world.texture import LEVELS

#: The ray grid: every STEP-th pixel; its samples sit at pixel coordinates STEP k - OFFSET.
STEP = 8
OFFSET = (STEP + 1) / 2
MAX_DISTANCE = 150.0
#: Speed bumps and rough patches farther than this from the camera are not ray cast (sub-pixel).
DETAIL_RADIUS = 45.0


class RayCaster:
    """The coarse ray grid of a camera and its intersection with the terrain."""

    def __init__(self, terrain: Terrain, calibration: Calibration) -> None:
        self.terrain = terrain
        self.calibration = calibration
        intr = calibration.intrinsics
        self.width, self.height = intr.width, intr.height
        # Coarse samples at u = STEP a - OFFSET (and v alike): resizing STEP times then cropping
        # STEP gives exact bilinear interpolation at every integer pixel (see upsample).
        self.nu = math.ceil(self.width / STEP) + 2
        self.nv = math.ceil(self.height / STEP) + 2
        us = STEP * np.arange(self.nu) - OFFSET
        vs = STEP * np.arange(self.nv) - OFFSET
        self.uu, self.vv = np.meshgrid(us, vs)
        uu, vv = self.uu, self.vv
        self.rays = np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], axis=-1)
        #: The smooth-ground solution of the last frame (t, slope, dH/dx, dH/dy per sample).
        self.smooth_hits = np.zeros((4, self.nv, self.nu))

    def intersect(
        self, centre: np.ndarray, dirs: np.ndarray, z_ref: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ray parameter (camera depth) of each sample's hit, whether it hits, dH/dx, dH/dy, near a bump.

        1. Newton steps on the smooth hills, from the horizontal plane under the robot (robust:
           slopes stay under 10 %). 2. Rays whose hit lies near a speed bump or rough patch are
           marched through the band of heights the feature spans, and the first crossing is
           refined by bisection, so that the near face of a bump is found, not the ground behind.
        """
        shape = dirs.shape[:2]
        d = dirs.reshape(-1, 3)
        n = len(d)
        t = np.full(n, 1e4)
        gx = np.zeros(n)
        gy = np.zeros(n)
        hit = np.zeros(n, bool)
        down = np.flatnonzero(d[:, 2] < -1e-9)
        if down.size == 0:
            return t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape), hit.reshape(shape)
        dd = d[down]
        t_max = MAX_DISTANCE / np.sqrt(dd[:, 0] ** 2 + dd[:, 1] ** 2 + 1e-18)
        td = np.minimum((z_ref - centre[2]) / dd[:, 2], t_max)
        gxd = np.zeros(len(down))
        gyd = np.zeros(len(down))
        if self.terrain.flat:
            t[down] = td
            hit[down] = td < t_max
            return t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape), np.zeros(shape, bool)
        residual = np.full(len(down), np.inf)
        slope = np.full(len(down), -1.0)
        active = np.arange(len(down))
        for _ in range(4):
            ta, da = td[active], dd[active]
            xa = centre[0] + ta * da[:, 0]
            ya = centre[1] + ta * da[:, 1]
            hgt, gxa, gya = self.terrain.hill_heights(xa, ya, single=True)
            f = centre[2] + ta * da[:, 2] - hgt
            fp = da[:, 2] - gxa * da[:, 0] - gya * da[:, 1]
            step = f / np.minimum(fp, -1e-6)
            gxd[active], gyd[active], residual[active], slope[active] = gxa, gya, np.abs(f), fp
            td[active] = np.clip(ta - step, 0.0, t_max[active])
            active = active[np.abs(step) > 1e-3 + 2e-4 * ta]
            if active.size == 0:
                break
        ok = (residual < 0.02) & (td > 0.0) & (td < t_max * 0.999)
        # the smooth solution, kept for the exact pixels around speed bumps
        smooth = np.zeros((4, n))
        smooth[0, down], smooth[1, down], smooth[2, down], smooth[3, down] = td, slope, gxd, gyd
        self.smooth_hits = smooth.reshape(4, *shape)
        near_feature = (float(centre[0]), float(centre[1]), DETAIL_RADIUS)
        x = centre[0] + td * dd[:, 0]
        y = centre[1] + td * dd[:, 1]
        # rough paving (low, gentle waves): two Newton steps on the full height field
        rough = self._near_boxes(centre, x, y, self.terrain.detail_boxes(*near_feature, kind="rough"), 0.5)
        idx = np.flatnonzero(rough & ok & (td < DETAIL_RADIUS))
        for _ in range(2 if idx.size else 0):
            ti, di = td[idx], dd[idx]
            hgt, gxi, gyi = self.terrain.height_and_gradient(
                centre[0] + ti * di[:, 0], centre[1] + ti * di[:, 1], near_feature
            )
            f = centre[2] + ti * di[:, 2] - hgt
            fp = np.minimum(di[:, 2] - gxi * di[:, 0] - gyi * di[:, 1], -1e-3)
            td[idx] = np.clip(ti - np.clip(f / fp, -0.5, 0.5), 0.0, t_max[idx])
            gxd[idx], gyd[idx] = gxi, gyi
        # speed bumps (tall, steep): march through their height band for the first crossing
        bumps = self._near_boxes(centre, x, y, self.terrain.detail_boxes(*near_feature, kind="bumps"), 2.0)
        idx = np.flatnonzero(bumps & ok & (td < DETAIL_RADIUS))
        bumpy = np.zeros(n, bool)
        if idx.size:
            before = td[idx]
            td[idx], gxd[idx], gyd[idx] = self._march(centre, dd[idx], before, slope[idx], gxd[idx], gyd[idx])
            # the samples whose ray meets a bump (on it, or cut short by it) need exact pixels around them
            xi, yi = centre[0] + td[idx] * dd[idx, 0], centre[1] + td[idx] * dd[idx, 1]
            on_bump, _, _ = self.terrain.height_and_gradient(xi, yi, near_feature, smooth=False, rough=False)
            bumpy[down[idx]] = (on_bump > 0.002) | (np.abs(td[idx] - before) > 0.01)
        t[down], hit[down], gx[down], gy[down] = td, ok, gxd, gyd
        return (t.reshape(shape), hit.reshape(shape), gx.reshape(shape), gy.reshape(shape), bumpy.reshape(shape))

    def refine_bumps(
        self,
        maps: np.ndarray,
        inverse_depth: np.ndarray,
        depth: np.ndarray,
        bumpy: np.ndarray,
        cam: np.ndarray,
        shift: tuple[int, int],
    ) -> None:
        """Ray cast exactly the pixels that see a speed bump (its faces are too sharp to interpolate).

        The maps hold every pixel's smooth-ground hit; the pixels whose hit lies within a bump's
        reach (its box grown by the 0.8 m a bump can hide behind it) are marched through its
        height band and their ground point and depth replaced.
        """
        rows = np.flatnonzero(cv2.dilate(bumpy.astype(np.uint8), np.ones((3, 3), np.uint8)).any(axis=1))
        r0 = max(0, STEP * int(rows[0]) - STEP)
        r1 = min(self.height, STEP * int(rows[-1]) + STEP)
        res = LEVELS[0].res
        x = (maps[r0:r1, :, 0] + np.float32(0.5 + shift[0])) * np.float32(res)
        y = -(maps[r0:r1, :, 1] + np.float32(0.5 + shift[1])) * np.float32(res)
        c = cam[:3, 3]
        reach = np.zeros(x.shape, bool)
        for b in self.terrain.bumps_near(float(c[0]), float(c[1]), DETAIL_RADIUS):
            rx, ry = x - np.float32(b.centre[0]), y - np.float32(b.centre[1])
            along = rx * np.float32(b.direction[0]) + ry * np.float32(b.direction[1])
            across = ry * np.float32(b.direction[0]) - rx * np.float32(b.direction[1])
            reach |= (np.abs(along) < b.half_length + 0.8) & (np.abs(across) < b.half_width + 0.4)
        vs, us = np.nonzero(reach)
        if vs.size == 0:
            return
        vs = vs + r0
        _, slope_s, gx_s, gy_s = self.smooth_hits
        coarse = np.stack([slope_s, gx_s, gy_s], axis=-1).astype(np.float32)
        up = self.upsample(coarse, rows=r1, start=r0)[vs - r0, us].astype(np.float64)
        intr = self.calibration.intrinsics
        d = np.stack([(us - intr.cx) / intr.fx, (vs - intr.cy) / intr.fy, np.ones(us.size)], axis=1) @ cam[:3, :3].T
        t = np.clip(1.0 / np.maximum(inverse_depth[vs, us].astype(np.float64), 1e-4), 0.05, 2 * DETAIL_RADIUS)
        t, _, _ = self._march(c, d, t, np.minimum(up[:, 0], -1e-3), up[:, 1], up[:, 2], rough=False)
        maps[vs, us, 0] = (c[0] + t * d[:, 0]) / res - 0.5 - shift[0]
        maps[vs, us, 1] = -(c[1] + t * d[:, 1]) / res - 0.5 - shift[1]
        depth[vs, us] = t

    def _near_boxes(
        self, centre: np.ndarray, x: np.ndarray, y: np.ndarray, boxes: np.ndarray, grow: float
    ) -> np.ndarray:
        """Whether points lie in any of the boxes grown by ``grow`` m (via 1 m cells around the camera)."""
        if len(boxes) == 0:
            return np.zeros(len(x), bool)
        half = int(DETAIL_RADIUS) + 4
        grid = np.zeros((2 * half, 2 * half), bool)
        for x0, y0, x1, y1 in boxes:
            c0 = max(0, int((x0 - grow - centre[0]) // 1.0) + half)
            c1 = min(2 * half, int((x1 + grow - centre[0]) // 1.0) + half + 1)
            r0 = max(0, int((y0 - grow - centre[1]) // 1.0) + half)
            r1 = min(2 * half, int((y1 + grow - centre[1]) // 1.0) + half + 1)
            grid[r0:r1, c0:c1] = True
        ci = np.clip(np.floor(x - centre[0]).astype(np.int64) + half, 0, 2 * half - 1)
        ri = np.clip(np.floor(y - centre[1]).astype(np.int64) + half, 0, 2 * half - 1)
        found: np.ndarray = grid[ri, ci]
        return found

    def _march(
        self,
        centre: np.ndarray,
        d: np.ndarray,
        t_smooth: np.ndarray,
        slope: np.ndarray,
        gx: np.ndarray,
        gy: np.ndarray,
        rough: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First crossing of rays with the full terrain within the height band of bumps and patches.

        Within the band the hills are linear (``f = slope (t - t_smooth)`` is the ray's height over
        them), so only the bumps and patches are evaluated along the ray.
        """
        near = (float(centre[0]), float(centre[1]), DETAIL_RADIUS)
        rate = np.maximum(-slope, 1e-3)  # metres of height lost per unit of t over the smooth ground
        lo = np.maximum(t_smooth - 0.16 / rate, 1e-3)
        hi = t_smooth + 0.04 / rate
        n = 8
        ts = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, n)[None, :]

        def clearance(t: np.ndarray) -> np.ndarray:
            """Height of the ray over the ground (hills linearised) at ray parameters ``t``."""
            x = centre[0] + t * d[:, 0:1] if t.ndim == 2 else centre[0] + t * d[:, 0]
            y = centre[1] + t * d[:, 1:2] if t.ndim == 2 else centre[1] + t * d[:, 1]
            bump, _, _ = self.terrain.height_and_gradient(x, y, near, smooth=False, rough=rough, gradient=False)
            base = slope[:, None] * (t - t_smooth[:, None]) if t.ndim == 2 else slope * (t - t_smooth)
            out: np.ndarray = base - bump
            return out

        f = clearance(ts)
        below = f <= 0.0
        first = np.where(below.any(axis=1), below.argmax(axis=1), n - 1)
        rows = np.arange(len(d))
        a, b = ts[rows, np.maximum(first - 1, 0)], ts[rows, first]
        fa, fb = f[rows, np.maximum(first - 1, 0)], f[rows, first]
        for _ in range(3):
            m = 0.5 * (a + b)
            fm = clearance(m)
            up = fm > 0.0
            a, fa = np.where(up, m, a), np.where(up, fm, fa)
            b, fb = np.where(up, b, m), np.where(up, fb, fm)
        # a last secant step inside the bracket
        t = np.where(fa - fb > 1e-12, a + (b - a) * fa / np.maximum(fa - fb, 1e-12), 0.5 * (a + b))
        _, dx, dy = self.terrain.height_and_gradient(
            centre[0] + t * d[:, 0], centre[1] + t * d[:, 1], near, smooth=False, rough=rough
        )
        return t, gx + dx, gy + dy

    def upsample_planes(self, planes: list[np.ndarray], rows: int | None = None) -> list[np.ndarray]:
        """``upsample`` of single-channel planes (each resized alone: several times faster than interleaved)."""
        return [self.upsample(np.ascontiguousarray(p, np.float32), rows) for p in planes]

    def upsample(self, coarse: np.ndarray, rows: int | None = None, start: int = 0) -> np.ndarray:
        """Exact bilinear interpolation of the coarse samples at every pixel of rows ``start .. rows - 1``.

        Coarse sample ``b`` sits at image row ``STEP b - OFFSET``; resizing a block of samples from
        ``b0`` STEP times puts image row ``v`` at block row ``v - STEP b0 + STEP``.
        """
        rows = self.height if rows is None else rows
        b0 = max(0, math.floor((start + OFFSET) / STEP) - 1)
        b1 = min(self.nv, math.ceil((rows - 1 + OFFSET) / STEP) + 2)
        big = cv2.resize(coarse[b0:b1], (self.nu * STEP, (b1 - b0) * STEP), interpolation=cv2.INTER_LINEAR)
        q0 = start - STEP * b0 + STEP
        return big[q0 : q0 + rows - start, STEP : STEP + self.width]
