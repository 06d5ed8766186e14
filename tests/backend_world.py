"""A small synthetic world for the loop and back-end tests: a route, drifting odometry, ground markings.

The robot drives laps of a rounded rectangle; markings lie on its path. Each time a marking is
about 2.5 m ahead, an SGF is "selected": the marking's points in that frame's base frame, with
pixel-like noise. An oracle association groups the SGFs by design (as a descriptor would, so
look-alike markings of one design share a group) and hands the closest earlier member as
``matched`` with the yaw of the column shift (4 degree bins, as N_s = 90).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.geometry import invert, pose_from_xy_yaw, xy_yaw
from sgf_pipeline.truth import MarkingPass, MarkingTruth, RevisitPair, SequenceTruth
from sgf_pipeline.types import BevGrid, Frame, GroupAssignment, GroupAssignments, SalientGroundFeature, SgfDescriptor

CALIBRATION = Calibration.from_mounting(
    Intrinsics(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480), height=0.8, tilt=0.35
)
GRID = BevGrid(resolution=0.02, x_min=1.0, x_max=6.0, y_min=-2.5, y_max=2.5)


def _fill(mask_fn, extent: float = 0.7, spacing: float = 0.03) -> np.ndarray:
    xs = np.arange(-extent, extent + 1e-9, spacing)
    gx, gy = np.meshgrid(xs, xs)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    return pts[mask_fn(pts[:, 0], pts[:, 1])]


def arrow_points(spacing: float = 0.03, head: float = 0.35) -> np.ndarray:
    """A straight-ahead arrow: a shaft and a triangular head ``head`` m wide at its base (about 1.2 m long)."""
    return _fill(
        lambda x, y: (
            ((x <= 0.1) & (x >= -0.6) & (np.abs(y) <= 0.08))
            | ((x > 0.1) & (x <= 0.6) & (np.abs(y) <= head * (0.6 - x) / 0.5))
        ),
        spacing=spacing,
    )


def ell_points(spacing: float = 0.03) -> np.ndarray:
    """A custom L-shaped marking."""
    return _fill(
        lambda x, y: ((np.abs(x) <= 0.6) & (y >= -0.5) & (y <= -0.3)) | ((x <= -0.4) & (np.abs(y) <= 0.5)),
        spacing=spacing,
    )


def tee_points(spacing: float = 0.03) -> np.ndarray:
    """A custom T-shaped marking."""
    return _fill(
        lambda x, y: ((x >= 0.4) & (x <= 0.6) & (np.abs(y) <= 0.6)) | ((np.abs(y) <= 0.1) & (x >= -0.6) & (x <= 0.6)),
        spacing=spacing,
    )


def disc_points(spacing: float = 0.03) -> np.ndarray:
    """A round manhole cover (symmetric)."""
    return _fill(lambda x, y: x**2 + y**2 <= 0.5**2, spacing=spacing)


SHAPES = {"arrow": arrow_points, "ell": ell_points, "tee": tee_points, "disc": disc_points}


def rounded_rectangle(length: float, width: float, step: float) -> np.ndarray:
    """(N, 3) x, y, yaw every ``step`` metres around a rectangle with round corners (counter-clockwise)."""
    r = 5.0
    pts: list[tuple[float, float, float]] = []
    straight = [
        (length - 2 * r, 0.0),
        (width - 2 * r, math.pi / 2),
        (length - 2 * r, math.pi),
        (width - 2 * r, -math.pi / 2),
    ]
    x, y = r, 0.0
    for seg_len, heading in straight:
        n = round(seg_len / step)
        for k in range(n):
            pts.append((x + math.cos(heading) * k * step, y + math.sin(heading) * k * step, heading))
        x += math.cos(heading) * seg_len
        y += math.sin(heading) * seg_len
        # quarter circle to the left
        cx, cy = x - math.sin(heading) * r, y + math.cos(heading) * r
        n_arc = round(0.5 * math.pi * r / step)
        for k in range(n_arc):
            a = heading + 0.5 * math.pi * k / n_arc
            pts.append((cx + math.sin(a) * r, cy - math.cos(a) * r, a))
        x, y = cx + math.sin(heading + math.pi / 2) * r, cy - math.cos(heading + math.pi / 2) * r
    return np.array(pts)


@dataclass
class Marking:
    """A marking placed in the world."""

    instance_id: int
    design: str
    pose: tuple[float, float, float]
    symmetric: bool = False

    def world_points(self) -> np.ndarray:
        x, y, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        pts = SHAPES[self.design]()
        return pts @ np.array([[c, -s], [s, c]]).T + [x, y]


@dataclass
class World:
    """Ground truth, odometry, frames and the SGFs seen on them."""

    gt: np.ndarray
    odometry: np.ndarray
    markings: list[Marking]
    frames: list[Frame] = field(default_factory=list)
    sgfs: dict[int, list[tuple[Marking, np.ndarray]]] = field(default_factory=dict)
    truth: SequenceTruth = field(default_factory=SequenceTruth)


def drifting_odometry(
    gt: np.ndarray,
    rng: np.random.Generator,
    sigma_xy: float,
    sigma_yaw: float,
    scale: float,
    yaw_bias: float,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """Odometry that composes noisy, biased increments of the ground truth (a random walk with drift)."""
    odo = [gt[0] if start is None else start]
    for a, b in itertools.pairwise(gt):
        x, y, yaw = xy_yaw(invert(a) @ b)
        d = math.hypot(x, y)
        noisy = pose_from_xy_yaw(
            x * (1 + scale) + rng.normal(0, sigma_xy * math.sqrt(d)),
            y + rng.normal(0, sigma_xy * math.sqrt(d)),
            yaw + yaw_bias * d + rng.normal(0, sigma_yaw * math.sqrt(d)),
        )
        odo.append(odo[-1] @ noisy)
    return np.stack(odo)


def make_world(
    seed: int = 0,
    laps: float = 2.0,
    reverse_lap: bool = True,
    markings: list[Marking] | None = None,
    step: float = 1.0,
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    odometry_noise: tuple[float, float, float, float] = (0.01, math.radians(0.3), 0.01, math.radians(0.03)),
    point_noise: float = 0.01,
    length: float = 60.0,
    width: float = 40.0,
    odometry_start: tuple[float, float, float] | None = None,
) -> World:
    """A route of ``laps`` counter-clockwise laps (then one clockwise lap) with SGFs on its markings."""
    rng = np.random.default_rng(seed)
    lap = rounded_rectangle(length, width, step)
    n = round(laps * len(lap))
    rows = [lap[k % len(lap)] for k in range(n)]
    if reverse_lap:
        rows += [(x, y, yaw + math.pi) for x, y, yaw in lap[::-1]]
    ox, oy, oyaw = start_offset
    shift = pose_from_xy_yaw(ox, oy, oyaw)
    gt = np.stack([shift @ pose_from_xy_yaw(*r) for r in rows])
    start = None if odometry_start is None else pose_from_xy_yaw(*odometry_start)
    odometry = drifting_odometry(gt, rng, *odometry_noise, start=start)
    if markings is None:
        markings = [
            Marking(1, "arrow", (30.0, 0.0, 0.0)),
            Marking(2, "ell", (60.0, 20.0, math.pi / 2)),
            Marking(3, "tee", (30.0, 40.0, math.pi)),
            Marking(4, "disc", (0.0, 20.0, 0.0), symmetric=True),
            Marking(5, "arrow", (45.0, 40.0, math.pi)),
        ]
        markings = [Marking(m.instance_id, m.design, _on(shift, m.pose), m.symmetric) for m in markings]
    world = World(gt, odometry, markings)
    for k, (g, o) in enumerate(zip(gt, odometry, strict=True)):
        roll, pitch = float(rng.normal(0, 0.002)), float(rng.normal(0, 0.002))
        world.frames.append(
            Frame(k, 0.5 * k, np.zeros((2, 2), np.uint8), o, CALIBRATION, imu_roll_pitch=(roll, pitch), ground_truth=g)
        )
    _place_sgfs(world, rng, point_noise)
    return world


def _on(shift: np.ndarray, pose: tuple[float, float, float]) -> tuple[float, float, float]:
    return xy_yaw(shift @ pose_from_xy_yaw(*pose))


def _place_sgfs(world: World, rng: np.random.Generator, point_noise: float) -> None:
    """Select an SGF on the first frame of each pass at which a marking is 2 to 3.2 m straight ahead."""
    passes: dict[int, list[MarkingPass]] = {}
    for m in world.markings:
        pts_world = m.world_points()
        last_seen = -10
        for k, g in enumerate(world.gt):
            local = invert(g) @ np.array([m.pose[0], m.pose[1], 0.0, 1.0])
            ahead = 2.0 <= local[0] <= 3.2 and abs(local[1]) <= 1.0
            if not ahead:
                continue
            if k - last_seen > 3:
                inv = invert(g)
                base = pts_world @ inv[:2, :2].T + inv[:2, 3]
                keep = rng.random(len(base)) < 0.85
                base = base[keep] + rng.normal(0, point_noise, (int(keep.sum()), 2))
                world.sgfs.setdefault(k, []).append((m, base))
                heading = xy_yaw(g)[2]
                number = len(passes.get(m.instance_id, []))
                passes.setdefault(m.instance_id, []).append(MarkingPass(m.instance_id, number, k - 2, k + 2, heading))
            last_seen = k
    truth = SequenceTruth()
    for m in world.markings:
        truth.markings[m.instance_id] = MarkingTruth(m.instance_id, m.design, "custom", m.symmetric, m.pose, (1.2, 1.0))
        ps = passes.get(m.instance_id, [])
        truth.passes.extend(ps)
        for a, b in itertools.pairwise(ps):
            reverse = abs(math.remainder(b.heading - a.heading, 2 * math.pi)) > math.pi / 2
            truth.revisits.append(RevisitPair(m.instance_id, a, b, reverse))
    world.truth = truth


def descriptor(frame: Frame, marking: Marking, points: np.ndarray) -> SgfDescriptor:
    """An SGF descriptor of points seen on a frame (a density polar context, 10 x 90)."""
    centroid = points.mean(axis=0)
    rel = points - centroid
    r = np.hypot(rel[:, 0], rel[:, 1])
    a = np.mod(np.arctan2(rel[:, 1], rel[:, 0]), 2 * math.pi)
    ring = np.minimum((r / 0.2).astype(int), 9)
    sector = np.minimum((a / (2 * math.pi / 90)).astype(int), 89)
    matrix = np.zeros((10, 90))
    np.add.at(matrix, (ring, sector), 1.0)
    sgf = SalientGroundFeature(
        track_id=marking.instance_id * 1000 + frame.index,
        frame_index=frame.index,
        timestamp=frame.timestamp,
        odometry=frame.odometry,
        pixels=np.zeros((0, 2), np.int64),
        grid=GRID,
        saliency=0.9,
        hu=np.zeros(7),
        views=5,
        instance_id=marking.instance_id,
    )
    return SgfDescriptor(sgf, points, centroid, matrix, matrix.sum(axis=1))


class OracleAssociation:
    """Groups SGFs by design (look-alikes share a group) and matches the closest earlier member."""

    def __init__(
        self, world: World, yaw_sign: float = 1.0, prior: list[SgfDescriptor] | None = None, by: str = "design"
    ) -> None:
        self.world = world
        self.yaw_sign = yaw_sign
        self.by = by
        self.groups: dict[str, list[SgfDescriptor]] = {}
        self.design_of: dict[int, str] = {m.instance_id: m.design for m in world.markings}
        for d in prior or []:
            assert d.sgf.instance_id is not None
            self.groups.setdefault(self._key(d.sgf.instance_id), []).append(d)

    def _key(self, instance_id: int) -> str:
        return self.design_of[instance_id] if self.by == "design" else str(instance_id)

    def assign(self, frame: Frame) -> GroupAssignments | None:
        """The assignments of the SGFs selected on ``frame`` (None when there are none)."""
        seen = self.world.sgfs.get(frame.index)
        if not seen:
            return None
        items = []
        for marking, points in seen:
            d = descriptor(frame, marking, points)
            key = self._key(marking.instance_id)
            group = self.groups.setdefault(key, [])
            gid = list(self.groups).index(key)
            matched = group[-1] if group else None
            yaw = 0.0
            if matched is not None:
                # the column shift between the two views, quantized to N_s = 90 bins
                rel = self._relative_yaw(matched, d)
                yaw = self.yaw_sign * round(rel / (2 * math.pi / 90)) * (2 * math.pi / 90)
            items.append(GroupAssignment(d, gid, matched is None, 0.1, 0, yaw, matched, marking.symmetric))
            group.append(d)
        return GroupAssignments(tuple(items))

    def _relative_yaw(self, a: SgfDescriptor, b: SgfDescriptor) -> float:
        """Rotation taking ``b``'s view of its marking onto ``a``'s view of its own (what the column shift measures)."""
        ga = getattr(a, "ground_truth", None)
        if ga is None:
            ga = self.world.gt[a.sgf.frame_index]
        gb = self.world.gt[b.sgf.frame_index]
        marking = {m.instance_id: m for m in self.world.markings}
        assert a.sgf.instance_id is not None and b.sgf.instance_id is not None
        seen_a = marking[a.sgf.instance_id].pose[2] - xy_yaw(ga)[2]
        seen_b = marking[b.sgf.instance_id].pose[2] - xy_yaw(gb)[2]
        return math.remainder(seen_a - seen_b, 2 * math.pi)


def ate(estimate: np.ndarray, gt: np.ndarray) -> float:
    """RMS position error after a rigid 2-D alignment (Umeyama, as evo's -a)."""
    p, q = estimate[:, :2, 3], gt[:, :2, 3]
    mp, mq = p.mean(0), q.mean(0)
    h = (p - mp).T @ (q - mq)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, d]) @ u.T
    aligned = (p - mp) @ rot.T + mq
    return float(np.sqrt(np.mean(np.sum((aligned - q) ** 2, axis=1))))


def rmse(estimate: np.ndarray, gt: np.ndarray) -> float:
    """RMS position error without alignment (both in one frame)."""
    return float(np.sqrt(np.mean(np.sum((estimate[:, :2, 3] - gt[:, :2, 3]) ** 2, axis=1))))


@dataclass
class Run:
    """What a run of the loop stage (and a back-end) over a world produced."""

    context: object
    loops: list
    estimates: list
    settlement: object = None


def run_stages(world: World, loop=None, backend=None, association=None, run_dir=None, frames=None, settle=True) -> Run:  # type: ignore[no-untyped-def]
    """Stream a world's frames through an association, the loop stage and a back-end, as the runner would.

    ``settle=False`` ends the run with ``conclude`` and ``finalize`` alone, as a caller that does not know
    ``settle`` would.
    """
    from sgf_pipeline.context import RunContext
    from sgf_pipeline.stage import Settlement

    context = RunContext(run_dir=run_dir, sequence="toy", calibration=CALIBRATION, truth=world.truth)
    association = association or OracleAssociation(world)
    for stage in (loop, backend):
        if stage is not None:
            stage.begin(context)
    loops, estimates = [], []
    estimate = None
    for frame in frames if frames is not None else world.frames:
        assignments = association.assign(frame)
        found = loop.process(frame=frame, assignments=assignments, estimate=estimate) if loop is not None else None
        if found is not None:
            loops.extend(found.items)
        if backend is not None:
            estimate = backend.process(frame=frame, loops=found)
            estimates.append(estimate)
    stages = [s for s in (loop, backend) if s is not None]
    settlement = Settlement()
    for stage in stages if settle else []:  # as the runner ends a run: every stage settles, then each concludes
        settlement = stage.settle(context, settlement)
    for stage in stages:
        settlement = stage.conclude(context, settlement)
        stage.finalize(context)
    return Run(context, loops, estimates, settlement)
