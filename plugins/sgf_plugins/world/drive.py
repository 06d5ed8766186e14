"""The robot's drive: the route through the path network, its speed, and the drifting wheel odometry."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d, uniform_filter1d

from sgf_pipeline.geometry import rotation_rpy, rpy_from_rotation
from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.noise import lattice_noise, rng_for
from sgf_plugins.world.presets import RouteSpec
from sgf_plugins.world.terrain import Terrain


@dataclass
class Leg:
    """A stretch driven without stopping: a dense centre line (0.05 m spacing) and its headings."""

    xy: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    stop_after: float = 0.0

    @property
    def length(self) -> float:
        """Length (m)."""
        return float(np.linalg.norm(np.diff(self.xy, axis=0), axis=1).sum())


STEP = 0.05


def _fillet(points: np.ndarray, radius: float) -> np.ndarray:
    """A polyline with every corner replaced by a circular arc of (at most) ``radius`` m."""
    if len(points) < 3:
        return points
    out = [points[0]]
    for i in range(1, len(points) - 1):
        a, b, c = points[i - 1], points[i], points[i + 1]
        u = b - a
        v = c - b
        lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        if lu < 1e-9 or lv < 1e-9:
            continue
        u, v = u / lu, v / lv
        turn = math.atan2(u[0] * v[1] - u[1] * v[0], float(u @ v))
        if abs(turn) < 1e-4:
            out.append(b)
            continue
        tangent = min(radius * math.tan(abs(turn) / 2), 0.45 * lu, 0.45 * lv)
        r = tangent / math.tan(abs(turn) / 2)
        p0 = b - u * tangent
        normal = np.array([-u[1], u[0]]) * math.copysign(1.0, turn)
        centre = p0 + normal * r
        n = max(2, math.ceil(abs(turn) * r / 0.2) + 1)
        start = math.atan2(p0[1] - centre[1], p0[0] - centre[0])
        for k in range(n):
            ang = start + math.copysign(1.0, turn) * abs(turn) * k / (n - 1)
            out.append(centre + r * np.array([math.cos(ang), math.sin(ang)]))
    out.append(points[-1])
    return np.asarray(out)


def _head(points: np.ndarray, fraction: float) -> np.ndarray:
    """The first ``fraction`` of a polyline's length."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = fraction * cum[-1]
    i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    end = points[i] + (s - cum[i]) / max(seg[i], 1e-9) * (points[i + 1] - points[i])
    return np.concatenate([points[: i + 1], end[None]])


def _resample(points: np.ndarray, step: float = STEP) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    points = points[keep]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    s = np.arange(0.0, cum[-1], step)
    if cum[-1] - s[-1] > 1e-6:
        s = np.append(s, cum[-1])
    return np.stack([np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])], axis=1)


def build_legs(layout: CampusLayout, spec: RouteSpec, corner_radius: float = 4.0) -> list[Leg]:
    """The route's legs: node-to-node polylines joined with rounded corners, split at stops."""
    legs: list[Leg] = []
    current: list[np.ndarray] = []
    pairs = list(zip(spec.nodes, spec.nodes[1:], strict=False))
    for k, (a, b) in enumerate(pairs):
        edge, reverse = layout.edge_between(a, b)
        pts = edge.points[::-1] if reverse else edge.points
        if k == len(pairs) - 1 and spec.end_fraction < 1.0:
            pts = _head(pts, spec.end_fraction)
        current.append(pts if not current else pts[1:])
        stop = spec.stops.get(b, 0.0)
        if stop > 0.0 or b == spec.nodes[-1]:
            raw = np.concatenate(current)
            dense = _resample(_fillet(raw, corner_radius))
            d = np.gradient(dense, axis=0)
            heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
            # arcs are sampled every 0.2 m: smooth the curvature over 0.5 m
            curvature = uniform_filter1d(np.gradient(heading) / STEP, size=11, mode="nearest")
            legs.append(Leg(dense, heading, curvature, stop))
            current = [pts[-1:]]
    return legs


@dataclass
class DriveLog:
    """The robot's ground-truth motion sampled at the camera rate."""

    timestamps: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def length(self) -> float:
        """Distance driven (m)."""
        return float(np.linalg.norm(np.diff(self.poses[:, :3, 3], axis=0), axis=1).sum())


def drive(
    layout: CampusLayout,
    terrain: Terrain,
    legs: Sequence[Leg],
    seed: int,
    rate_hz: float = 10.0,
    speed_range: tuple[float, float] = (1.0, 1.5),
    lateral_wander: float = 0.25,
    max_lateral_accel: float = 0.35,
) -> DriveLog:
    """Drive the legs at a varying speed in ``speed_range`` (m/s), wandering a little sideways.

    The speed is the robot's own (off the centre line of a bend it covers less or more of it);
    it drops below the range only to start, to stop and in tight corners (lateral acceleration).
    """
    dt = 1.0 / rate_hz
    v_lo, v_hi = speed_range
    times: list[float] = []
    xs: list[float] = []
    ys: list[float] = []
    yaws: list[float] = []
    speeds: list[float] = []
    t = 0.0
    for k, leg in enumerate(legs):
        n = len(leg.xy)
        total = (n - 1) * STEP
        # Cruise speed: smooth noise along the route, capped on curves by the lateral acceleration.
        noise = lattice_noise(seed * 7 + k, 0.0, 1.0, n, 1, STEP, 25.6)[0].astype(np.float64)
        # a slow wander around 60 % of the range (1.3 m/s by default), whatever the seed
        cruise = v_lo + (v_hi - v_lo) * np.clip(0.6 + 0.7 * (noise - noise.mean()), 0.05, 0.95)
        kappa = np.abs(leg.curvature)
        # Look ahead 2 m for curvature so the robot slows before a corner, not in it.
        window = int(2.0 / STEP)
        ahead = maximum_filter1d(kappa, size=window, origin=-(window // 2), mode="nearest")
        cap = np.sqrt(max_lateral_accel / np.maximum(ahead, 1e-6))
        # cruise between v_lo and v_hi; only tight corners (radius under ~3 m) are taken slower
        profile = np.clip(np.minimum(cruise, cap), 0.5 * v_lo, v_hi)
        wander = lateral_wander * lattice_noise(seed * 13 + k, 0.0, 1.0, n, 1, STEP, 12.8)[0].astype(np.float64)
        wander = np.clip(wander, -lateral_wander, lateral_wander)
        # Fade the wander in and out at the ends of a leg (the robot starts and stops on the line).
        ramp = np.clip(np.minimum(np.arange(n), np.arange(n)[::-1]) * STEP / 4.0, 0.0, 1.0)
        wander = wander * ramp
        s = 0.0
        v = 0.0
        while True:
            i = min(int(s / STEP), n - 1)
            target = profile[i]
            # Accelerate from rest, brake to a stop at the end of the leg (1 m/s^2).
            v = min(target, v + 1.0 * dt, math.sqrt(max(2.0 * 1.0 * (total - s), 0.0)) + 0.05)
            heading = leg.heading[i]
            normal = np.array([-math.sin(heading), math.cos(heading)])
            lat = wander[i]
            dlat = (wander[min(i + 1, n - 1)] - wander[max(i - 1, 0)]) / (2 * STEP)
            p = leg.xy[i] + (s - i * STEP) * np.array([math.cos(heading), math.sin(heading)]) + normal * lat
            times.append(t)
            xs.append(float(p[0]))
            ys.append(float(p[1]))
            yaws.append(float(heading + math.atan(dlat)))
            speeds.append(v)
            t += dt
            if s >= total - 1e-6:
                break
            # the robot's own speed is v: off the centre line of a bend it covers less (or more) of it
            s = min(total, s + v * dt / max(0.5, 1.0 - lat * leg.curvature[i]))
        for _ in range(round(leg.stop_after * rate_hz)):
            times.append(t)
            xs.append(xs[-1])
            ys.append(ys[-1])
            yaws.append(yaws[-1])
            speeds.append(0.0)
            t += dt
    x = np.asarray(xs)
    y = np.asarray(ys)
    yaw = np.asarray(yaws)
    poses = terrain.base_poses(x, y, yaw)
    return DriveLog(np.asarray(times), np.stack([x, y], 1), yaw, np.asarray(speeds), poses)


@dataclass(frozen=True)
class OdometryModel:
    """Wheel odometry errors: scale, heading bias per metre and its random walk, and noise."""

    scale_error: float = 0.012
    yaw_bias_deg_per_m: float = 0.02
    yaw_random_walk_deg_per_m: float = 0.01
    distance_noise: float = 0.01
    yaw_noise_deg: float = 0.05
    imu_noise_deg: float = 0.15
    imu_bias_deg: float = 0.1
    seeded_sign: bool = True  # the seed picks the heading bias's sign; False: the sign of yaw_bias_deg_per_m


@dataclass
class SensorLog:
    """What the robot measures: odometry poses (N, 4, 4) and IMU roll/pitch (N, 2) in rad."""

    odometry: np.ndarray
    imu_roll_pitch: np.ndarray


def simulate_sensors(log: DriveLog, model: OdometryModel, seed: int) -> SensorLog:
    """Dead-reckon wheel odometry with the IMU's roll and pitch, starting at the true start pose.

    Per frame the wheels measure the distance driven with a scale error and noise; the heading
    change is measured with a bias (of either sign, by the seed, unless ``seeded_sign`` is off) and
    a random-walk drift proportional to the distance, and white noise; the IMU gives roll and pitch
    with a constant bias and white noise. The 3-D position integrates the measured distance along
    the measured attitude.
    """
    rng = rng_for(seed, 21)
    n = len(log)
    rpy = np.array([rpy_from_rotation(p[:3, :3]) for p in log.poses])
    bias = np.radians(model.imu_bias_deg) * rng.uniform(-1.0, 1.0, 2)
    imu = rpy[:, :2] + bias + rng.normal(0.0, np.radians(model.imu_noise_deg), (n, 2))
    pos = log.poses[:, :3, 3]
    ds_true = np.concatenate([[0.0], np.linalg.norm(np.diff(pos, axis=0), axis=1)])
    dyaw_true = np.concatenate([[0.0], np.diff(np.unwrap(rpy[:, 2]))])
    moving = (ds_true > 1e-6) | (np.abs(dyaw_true) > 1e-6)
    ds = ds_true * (1.0 + model.scale_error) + rng.normal(0.0, model.distance_noise, n) * np.sqrt(ds_true)
    walk = np.cumsum(rng.normal(0.0, np.radians(model.yaw_random_walk_deg_per_m), n) * np.sqrt(ds_true))
    flip = rng.random() < 0.5  # drawn either way: the rest of the noise stays that of the seed
    sign = (1.0 if flip else -1.0) if model.seeded_sign else 1.0
    drift = (sign * np.radians(model.yaw_bias_deg_per_m) + walk) * ds_true
    dyaw = dyaw_true + drift + rng.normal(0.0, np.radians(model.yaw_noise_deg), n) * moving
    odo = np.empty((n, 4, 4))
    odo[0] = log.poses[0]
    yaw = rpy[0, 2]
    p = pos[0].copy()
    for k in range(1, n):
        yaw_mid = yaw + 0.5 * dyaw[k]
        yaw += dyaw[k]
        rot_mid = rotation_rpy(imu[k, 0], imu[k, 1], yaw_mid)
        p = p + rot_mid[:, 0] * ds[k]
        odo[k] = np.eye(4)
        odo[k, :3, :3] = rotation_rpy(imu[k, 0], imu[k, 1], yaw)
        odo[k, :3, 3] = p
    return SensorLog(odo, imu)
