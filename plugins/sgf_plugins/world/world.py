"""The synthetic campus world: layout, terrain, camera, the preset's drive and its exact ground truth."""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import cached_property
from typing import Any

import numpy as np
from pydantic import ValidationError

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.errors import ConfigError
from sgf_pipeline.truth import SequenceTruth
from sgf_pipeline.types import BevGrid, Frame
from sgf_plugins.world.conditions import RenderConditions
from sgf_plugins.world.designs import allowed_designs
from sgf_plugins.world.drive import DriveLog, OdometryModel, SensorLog, build_legs, drive, simulate_sensors
from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.layout_generator import LayoutOptions, build_layout
from sgf_plugins.world.noise import lattice_noise, rng_for
from sgf_plugins.world.params import WorldParams
from sgf_plugins.world.presets import PRESETS, Preset
from sgf_plugins.world.render import Renderer, RenderLayers
from sgf_plugins.world.sun import Sun
from sgf_plugins.world.terrain import Terrain
from sgf_plugins.world.texture import LEVELS
from sgf_plugins.world.truth import sequence_truth


class CampusWorld:
    """A synthetic campus with one preset's drive: render any pose, iterate the frames, read the truth."""

    def __init__(self, preset: Preset, params: WorldParams) -> None:
        self.preset = preset
        self.params = params
        designs = allowed_designs(params.exclude_designs, params.only_designs, params.design_weights)
        options = LayoutOptions(
            marking_spacing=params.marking_spacing,
            pedestrians_per_km=params.pedestrians_per_km,
            vehicles_per_km=params.vehicles_per_km,
            rough_paving_per_km=params.rough_paving_per_km,
            designs=tuple(designs),
        )
        self.layout: CampusLayout = build_layout(params.seed, params.scale, options)
        self.terrain = (
            Terrain() if params.flat_ground else Terrain(self.layout.hills, self.layout.bumps, self.layout.rough)
        )
        intr = Intrinsics(
            fx=params.fx,
            fy=params.fy,
            cx=params.cx if params.cx is not None else (params.width - 1) / 2.0,
            cy=params.cy if params.cy is not None else (params.height - 1) / 2.0,
            width=params.width,
            height=params.height,
        )
        self.calibration = Calibration.from_mounting(intr, params.camera_height, math.radians(params.camera_tilt_deg))
        rng = rng_for(params.seed, 501)
        self.sun = Sun(float(rng.uniform(-math.pi, math.pi)), math.radians(float(rng.uniform(38.0, 58.0))))
        self.renderer = Renderer(self.layout, self.terrain, self.calibration, self.sun, params.seed, params.clutter)
        self.grid = BevGrid(
            params.bev_resolution, params.bev_x_min, params.bev_x_max, params.bev_y_min, params.bev_y_max
        )

    @property
    def name(self) -> str:
        """The preset's name."""
        return self.preset.name

    @property
    def seed(self) -> int:
        """The world's seed."""
        return self.params.seed

    # -- the drive ---------------------------------------------------------------------------------

    @cached_property
    def drive(self) -> DriveLog:
        """The robot's ground-truth motion over the preset's route."""
        legs = build_legs(self.layout, self.preset.route)
        p = self.params
        return drive(self.layout, self.terrain, legs, p.seed, p.rate_hz, (p.speed_min, p.speed_max))

    @cached_property
    def sensors(self) -> SensorLog:
        """Wheel odometry and IMU roll/pitch along the drive."""
        p = self.params
        model = OdometryModel(
            scale_error=p.odometry_scale_error,
            yaw_bias_deg_per_m=p.odometry_yaw_bias_deg_per_m,
            yaw_random_walk_deg_per_m=p.odometry_yaw_random_walk_deg_per_m,
            distance_noise=p.odometry_distance_noise,
            yaw_noise_deg=p.odometry_yaw_noise_deg,
            imu_noise_deg=p.imu_noise_deg,
            imu_bias_deg=p.imu_bias_deg,
            seeded_sign=p.odometry_yaw_bias_seeded_sign,
        )
        return simulate_sensors(self.drive, model, p.seed if p.odometry_seed is None else p.odometry_seed)

    @cached_property
    def truth(self) -> SequenceTruth:
        """Marking table, passes and revisit pairs of the drive."""
        gap = round(self.params.pass_merge_gap_s * self.params.rate_hz)
        return sequence_truth(self.layout.markings, self.terrain, self.drive.poses, self.calibration, self.grid, gap)

    def __len__(self) -> int:
        return len(self.drive)

    @cached_property
    def exposures(self) -> np.ndarray:
        """Per-frame exposure of the camera's auto-exposure (a slow wander around 1)."""
        n = len(self.drive)
        wander = lattice_noise(self.params.seed + 511, 0.0, 1.0, n, 1, 1.0 / self.params.rate_hz, 6.4)[0]
        return np.exp(self.params.exposure_variation * wander.astype(np.float64))

    def frame_conditions(self, index: int) -> RenderConditions:
        """How frame ``index`` of the drive is rendered."""
        return RenderConditions(
            night=self.params.night,
            time=float(self.drive.timestamps[index]),
            exposure=float(self.exposures[index]),
            occluders=self.params.occluders,
            sensor_noise=self.params.sensor_noise,
            noise_seed=index,
        )

    def frame(self, index: int) -> Frame:
        """Frame ``index``: image and ids rendered lazily in one pass, poses, IMU attitude."""
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} out of range (the sequence has {len(self)} frames)")
        cache: dict[str, RenderLayers] = {}

        def layers() -> RenderLayers:
            if "layers" not in cache:
                cache["layers"] = self.render_layers(self.drive.poses[index], self.frame_conditions(index))
            return cache["layers"]

        imu = self.sensors.imu_roll_pitch[index]
        return Frame(
            index=index,
            timestamp=float(self.drive.timestamps[index]),
            image=lambda: layers().image,
            odometry=self.sensors.odometry[index].copy(),
            calibration=self.calibration,
            imu_roll_pitch=(float(imu[0]), float(imu[1])),
            ground_truth=self.drive.poses[index].copy(),
            instance_ids=lambda: layers().ids,
        )

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[Frame]:
        """The drive's frames in time order (every camera frame)."""
        for k in range(start, len(self) if stop is None else min(stop, len(self))):
            yield self.frame(k)

    # -- rendering any pose ------------------------------------------------------------------------

    def conditions(self, **kwargs: Any) -> RenderConditions:
        """Render conditions with this world's defaults (night, occluders, noise) and overrides."""
        base = {
            "night": self.params.night,
            "occluders": self.params.occluders,
            "sensor_noise": self.params.sensor_noise,
        }
        base.update(kwargs)
        return RenderConditions(**base)

    def render_layers(
        self, pose: np.ndarray, conditions: RenderConditions | None = None, **kwargs: Any
    ) -> RenderLayers:
        """Render a base pose (4x4, world frame) with all by-products (ids, depth, ground points)."""
        pose = np.asarray(pose, np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"a pose must be a finite 4x4 matrix, got shape {pose.shape}")
        cond = conditions if conditions is not None else self.conditions(**kwargs)
        return self.renderer.render(pose, cond)

    def render(
        self, pose: np.ndarray, conditions: RenderConditions | None = None, **kwargs: Any
    ) -> tuple[np.ndarray, np.ndarray]:
        """The camera image (uint8 RGB) and marking-id image (int32, 0 = none) of a base pose.

        ``kwargs`` are :class:`RenderConditions` fields, e.g. ``night=True, extra_occluders=2``.
        """
        layers = self.render_layers(pose, conditions, **kwargs)
        return layers.image, layers.ids

    def ground_pose(self, x: float, y: float, yaw: float) -> np.ndarray:
        """The base pose of the robot standing on its wheels at ``(x, y)`` heading ``yaw``."""
        return self.terrain.base_pose(x, y, yaw)

    def random_pose(self, rng: np.random.Generator, near_marking: bool = True) -> np.ndarray:
        """A plausible robot pose on a path (by default 1 to 5 m before a marking, facing it)."""
        lay = self.layout
        if near_marking and lay.markings:
            m = lay.markings[int(rng.integers(len(lay.markings)))]
            back = rng.uniform(1.5, 5.0)
            heading = float(rng.uniform(-math.pi, math.pi))
            side = rng.uniform(-0.8, 0.8)
            x = m.x - back * math.cos(heading) - side * math.sin(heading)
            y = m.y - back * math.sin(heading) + side * math.cos(heading)
            return self.ground_pose(x, y, heading + float(rng.normal(0.0, 0.2)))
        edge = lay.edges[int(rng.integers(len(lay.edges)))]
        s = float(rng.uniform(0.0, edge.length))
        p, t = edge.at(s)
        heading = math.atan2(t[1], t[0]) + (0.0 if rng.random() < 0.5 else math.pi)
        return self.ground_pose(float(p[0]), float(p[1]), heading + float(rng.normal(0.0, 0.15)))

    def marking_layout(self, pose: np.ndarray, grid: BevGrid | None = None) -> np.ndarray:
        """Ground-truth orthographic marking ids (int32) on a BEV grid in the heading frame of ``pose``.

        The grid's x points along the pose's heading projected on the horizontal plane, y to its
        left, and the markings are projected straight down; ids come from the same 1 cm id tiles
        the camera sees, so an exact IPM of the camera's id image agrees with this layout.
        """
        grid = grid or self.grid
        level = LEVELS[0]
        heading = math.atan2(pose[1, 0], pose[0, 0])
        c, s = math.cos(heading), math.sin(heading)
        v, u = np.mgrid[0 : grid.height, 0 : grid.width]
        gx, gy = grid.pixel_to_ground(u, v)
        wx = pose[0, 3] + c * gx - s * gy
        wy = pose[1, 3] + s * gx + c * gy
        tx = np.floor(wx / level.tile).astype(np.int64)
        ty = np.floor(wy / level.tile).astype(np.int64)
        out = np.zeros((grid.height, grid.width), np.int32)
        n = level.texels
        for a, b in {(int(p), int(q)) for p, q in zip(tx.ravel(), ty.ravel(), strict=True)}:
            sel = (tx == a) & (ty == b)
            _, ids = self.renderer.cache.get(level, a, b)
            col = np.clip(np.floor((wx[sel] - a * level.tile) / level.res).astype(np.int64), 0, n - 1)
            row = np.clip(np.floor(((b + 1) * level.tile - wy[sel]) / level.res).astype(np.int64), 0, n - 1)
            out[sel] = ids[row, col]
        return out


def world_params(**overrides: Any) -> WorldParams:
    """Validated world parameters; a bad value gives a clear error naming the parameter."""
    try:
        return WorldParams(**overrides)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"invalid world parameters: {problems}") from None


def build_world(preset: str = "campus_delivery", seed: int = 0, scale: float = 1.0, **overrides: Any) -> CampusWorld:
    """Build a preset's world; ``overrides`` are :class:`WorldParams` fields (camera, noise, designs...)."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown campus preset {preset!r}; presets: {', '.join(PRESETS)}")
    spec = PRESETS[preset]
    values: dict[str, Any] = {"night": spec.night}
    values.update(overrides)
    values.update(seed=seed, scale=scale)
    return CampusWorld(spec, world_params(**values))
