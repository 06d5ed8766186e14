"""Flat ground shapes rendered into BEV saliency maps: streams with exact truth for SGF tests and benches."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.geometry import invert, pose_from_xy_yaw
from sgf_pipeline.truth import MarkingPass, MarkingTruth, RevisitPair, SequenceTruth
from sgf_pipeline.types import Bev, BevGrid, Frame, SaliencyMap

#: The project's default BEV grid: 256 x 256 pixels of 2 cm, 0.5..5.62 m ahead, 2.56 m either side.
DEFAULT_GRID = BevGrid(resolution=0.02, x_min=0.5, x_max=5.62, y_min=-2.56, y_max=2.56)


@dataclass(frozen=True)
class ConvexPart:
    """A convex polygon (K, 2) in the shape's frame (metres, counter-clockwise or clockwise)."""

    vertices: np.ndarray

    @property
    def radius(self) -> float:
        """Distance from the shape's origin to the farthest vertex."""
        return float(np.max(np.hypot(self.vertices[:, 0], self.vertices[:, 1])))

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether each point lies inside the polygon."""
        v = np.asarray(self.vertices, dtype=np.float64)
        nxt = np.roll(v, -1, axis=0)
        cross = [(b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) for a, b in zip(v, nxt, strict=True)]
        stack = np.stack(cross)
        return np.all(stack >= 0.0, axis=0) | np.all(stack <= 0.0, axis=0)


@dataclass(frozen=True)
class Annulus:
    """A disc (``inner`` = 0) or a ring centred at ``centre`` in the shape's frame."""

    outer: float
    inner: float = 0.0
    centre: tuple[float, float] = (0.0, 0.0)

    @property
    def radius(self) -> float:
        """Distance from the shape's origin to the farthest point."""
        return float(math.hypot(*self.centre) + self.outer)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether each point lies inside the annulus."""
        r2 = (x - self.centre[0]) ** 2 + (y - self.centre[1]) ** 2
        return (r2 <= self.outer**2) & (r2 >= self.inner**2)


@dataclass(frozen=True)
class GroundShape:
    """A flat marking: a union of convex parts and annuli, placed at world ``pose`` = (x, y, yaw)."""

    parts: tuple[ConvexPart | Annulus, ...]
    pose: tuple[float, float, float]
    instance_id: int = 1

    @property
    def radius(self) -> float:
        """Radius (m) of a circle around the pose that holds the whole marking."""
        return max(part.radius for part in self.parts)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether world points lie on the marking."""
        px, py, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = x - px, y - py
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        inside = np.zeros(np.shape(x), dtype=bool)
        for part in self.parts:
            inside |= part.contains(lx, ly)
        return inside

    def placed(self, x: float, y: float, yaw: float, instance_id: int | None = None) -> GroundShape:
        """The same marking at another world pose."""
        return GroundShape(self.parts, (x, y, yaw), self.instance_id if instance_id is None else instance_id)


def rectangle(length: float, width: float) -> ConvexPart:
    """A rectangle centred on the origin, ``length`` along x."""
    a, b = length / 2.0, width / 2.0
    return ConvexPart(np.array([[-a, -b], [a, -b], [a, b], [-a, b]]))


def arrow_shape(length: float = 1.6, width: float = 0.6, shaft: float = 0.18) -> tuple[ConvexPart, ...]:
    """A straight-ahead arrow along +x: a shaft and a triangular head (an asymmetric standard marking)."""
    head = 0.4 * length
    x0, x1 = -length / 2.0, length / 2.0 - head
    shaft_part = ConvexPart(np.array([[x0, -shaft / 2], [x1, -shaft / 2], [x1, shaft / 2], [x0, shaft / 2]]))
    head_part = ConvexPart(np.array([[x1, -width / 2], [length / 2.0, 0.0], [x1, width / 2]]))
    return shaft_part, head_part


def ell_shape(length: float = 1.2, width: float = 0.8, bar: float = 0.2) -> tuple[ConvexPart, ...]:
    """An L: two bars meeting at a corner (a custom, chiral marking)."""
    a = ConvexPart(np.array([[0.0, 0.0], [length, 0.0], [length, bar], [0.0, bar]]))
    b = ConvexPart(np.array([[0.0, 0.0], [bar, 0.0], [bar, width], [0.0, width]]))
    off = np.array([length / 3.0, width / 3.0])
    return ConvexPart(a.vertices - off), ConvexPart(b.vertices - off)


def tee_shape(length: float = 1.2, width: float = 1.0, bar: float = 0.2) -> tuple[ConvexPart, ...]:
    """A T: a stem along x capped by a cross bar (mirror-symmetric, no rotational symmetry)."""
    stem = ConvexPart(
        np.array([[-length / 2, -bar / 2], [length / 2, -bar / 2], [length / 2, bar / 2], [-length / 2, bar / 2]])
    )
    top = ConvexPart(
        np.array(
            [
                [length / 2 - bar, -width / 2],
                [length / 2, -width / 2],
                [length / 2, width / 2],
                [length / 2 - bar, width / 2],
            ]
        )
    )
    return stem, top


def plus_shape(size: float = 1.0, bar: float = 0.2) -> tuple[ConvexPart, ...]:
    """A plus sign (4-fold rotational symmetry)."""
    return rectangle(size, bar), rectangle(bar, size)


def triangle_shape(side: float = 1.2) -> tuple[ConvexPart, ...]:
    """An equilateral triangle (3-fold rotational symmetry), like a give-way marking."""
    r = side / math.sqrt(3.0)
    angles = np.radians([90.0, 210.0, 330.0])
    return (ConvexPart(np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)),)


def chevron_shape(size: float = 1.0, bar: float = 0.2) -> tuple[ConvexPart, ...]:
    """A chevron (two bars meeting at 90 degrees), pointing along +x."""
    h = size / 2.0
    a = ConvexPart(np.array([[0.0, 0.0], [-h, h], [-h - bar, h - bar], [-bar, 0.0]]) + np.array([h / 2, 0.0]))
    b = ConvexPart(np.array([[0.0, 0.0], [-bar, 0.0], [-h - bar, -h + bar], [-h, -h]]) + np.array([h / 2, 0.0]))
    return a, b


def fov_valid_mask(grid: BevGrid, half_angle: float = math.radians(40.0)) -> np.ndarray:
    """The camera's field of view inside the BEV: ground points with ``|y| <= x tan(half_angle)``."""
    v, u = np.mgrid[0 : grid.height, 0 : grid.width]
    x, y = grid.pixel_to_ground(u, v)
    return np.abs(y) <= x * math.tan(half_angle)


def render_saliency(
    shapes: Sequence[GroundShape],
    pose: np.ndarray,
    grid: BevGrid = DEFAULT_GRID,
    valid: np.ndarray | None = None,
    supersample: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Saliency (fraction of each pixel covered by a marking) and instance ids seen from a 4x4 base pose."""
    h, w = grid.height, grid.width
    n = supersample
    offsets = (np.arange(n) + 0.5) / n - 0.5
    cover = np.zeros((h, w))
    ids = np.zeros((h, w), dtype=np.int32)
    rot, t = pose[:2, :2], pose[:2, 3]
    to_base = invert(pose)
    for shape in shapes:
        # Only the pixels of a window around the marking can be covered by it.
        bx, by = to_base[:2, :2] @ np.asarray(shape.pose[:2]) + to_base[:2, 3]
        cu, cv = grid.ground_to_pixel(bx, by)
        reach = shape.radius / grid.resolution + 2.0
        u0, u1 = max(0, math.floor(cu - reach)), min(w, math.ceil(cu + reach) + 1)
        v0, v1 = max(0, math.floor(cv - reach)), min(h, math.ceil(cv + reach) + 1)
        if u0 >= u1 or v0 >= v1:
            continue
        v, u = np.mgrid[v0:v1, u0:u1].astype(np.float64)
        window = np.zeros(u.shape)
        for du in offsets:
            for dv in offsets:
                gx, gy = grid.pixel_to_ground(u + du, v + dv)
                inside = shape.contains(rot[0, 0] * gx + rot[0, 1] * gy + t[0], rot[1, 0] * gx + rot[1, 1] * gy + t[1])
                window += inside
        cover[v0:v1, u0:u1] += window
        ids[v0:v1, u0:u1][window > 0] = shape.instance_id
    probability = np.clip(cover / (n * n), 0.0, 1.0).astype(np.float32)
    if valid is not None:
        probability[~valid] = 0.0
        ids[~valid] = 0
    return probability, ids


def straight_path(start: tuple[float, float, float], step: float, count: int) -> list[np.ndarray]:
    """Base poses along a straight line: ``count`` poses ``step`` metres apart, heading ``start[2]``."""
    x, y, yaw = start
    return [pose_from_xy_yaw(x + i * step * math.cos(yaw), y + i * step * math.sin(yaw), yaw) for i in range(count)]


def toy_calibration() -> Calibration:
    """A forward camera 0.5 m high, tilted 30 degrees down (the calibration that synthetic frames carry)."""
    intrinsics = Intrinsics(fx=300.0, fy=300.0, cx=160.0, cy=120.0, width=320, height=240)
    return Calibration.from_mounting(intrinsics, height=0.5, tilt=math.radians(30.0))


@dataclass
class SaliencyStream:
    """Frames, BEVs and saliency maps of a robot driving past flat shapes (odometry = truth unless given).

    ``gain`` scales each frame's saliency above 0.5 (a detector's confidence, leaving the binary
    mask at 0.5 unchanged); after a full iteration,
    :meth:`truth` gives the passes (frames where a shape is wholly in view, off the border band)
    and the revisit pairs, as a synthetic world's dataset reports them.
    """

    shapes: Sequence[GroundShape]
    poses: Sequence[np.ndarray]
    odometry: Sequence[np.ndarray] | None = None
    grid: BevGrid = DEFAULT_GRID
    valid: np.ndarray | None = None
    gain: Sequence[float] | None = None
    dt: float = 0.1
    supersample: int = 3
    calibration: Calibration = field(default_factory=toy_calibration)
    _in_view: dict[int, list[int]] = field(default_factory=dict, init=False, repr=False)

    def __iter__(self) -> Iterator[tuple[Frame, Bev, SaliencyMap]]:
        valid = self.valid if self.valid is not None else fov_valid_mask(self.grid)
        odometry = self.odometry if self.odometry is not None else self.poses
        origin = invert(np.asarray(odometry[0]))
        band = _band(valid)
        self._in_view = {}
        for i, (pose, odom) in enumerate(zip(self.poses, odometry, strict=True)):
            probability, full_ids = render_saliency(self.shapes, pose, self.grid, None, self.supersample)
            for instance in np.unique(full_ids[full_ids > 0]):
                if not band[full_ids == instance].any():
                    self._in_view.setdefault(int(instance), []).append(i)
            ids = np.where(valid, full_ids, 0)
            probability[~valid] = 0.0
            if self.gain is not None:
                above = probability >= 0.5
                probability[above] = 0.5 + float(self.gain[i]) * (probability[above] - 0.5)
            image = (probability * 255).astype(np.uint8)
            bev = Bev(image, valid, self.grid, i, i * self.dt, instance_ids=ids)
            odom_local = origin @ np.asarray(odom)
            frame = Frame(i, i * self.dt, image, odom_local, self.calibration, ground_truth=np.asarray(pose))
            yield frame, bev, SaliencyMap(probability, bev)

    def truth(self) -> SequenceTruth:
        """Passes and revisit pairs of the shapes over the frames iterated so far."""
        shapes = {s.instance_id: s for s in self.shapes}
        passes: list[MarkingPass] = []
        revisits: list[RevisitPair] = []
        for instance, frames in sorted(self._in_view.items()):
            runs: list[list[int]] = []
            for f in frames:
                if runs and f == runs[-1][-1] + 1:
                    runs[-1].append(f)
                else:
                    runs.append([f])
            mine = []
            for number, run in enumerate(runs):
                heading = math.atan2(self.poses[run[0]][1, 0], self.poses[run[0]][0, 0])
                mine.append(MarkingPass(instance, number, run[0], run[-1], heading))
            passes.extend(mine)
            for a, b in itertools.pairwise(mine):
                turn = abs((b.heading - a.heading + math.pi) % (2.0 * math.pi) - math.pi)
                revisits.append(RevisitPair(instance, a, b, turn > math.pi / 2.0))
        markings = {
            i: MarkingTruth(i, "synthetic", "custom", False, s.pose, (2.0 * s.radius, 2.0 * s.radius))
            for i, s in shapes.items()
        }
        return SequenceTruth(markings=markings, passes=passes, revisits=revisits)


def _band(valid: np.ndarray) -> np.ndarray:
    """Pixels on the image border or within one pixel of the invalid area (a marking there is not wholly in view)."""
    outside = np.pad(~valid, 1, constant_values=True).astype(np.uint8)
    return cv2.dilate(outside, np.ones((3, 3), np.uint8))[1:-1, 1:-1] > 0
