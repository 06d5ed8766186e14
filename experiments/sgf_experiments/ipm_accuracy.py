"""How metric the BEV of each IPM variant is on the synthetic world, by kind of ground (Table 4).

For a frame, every BEV sample point ``(x, y)`` claims that the ground ``x`` metres ahead and ``y``
to the left of the robot (on the horizontal, in its heading frame, as the ground-truth marking
layout ``CampusWorld.marking_layout`` is drawn) appears at the image pixel the IPM's homography
maps it to. The world's renderer knows which ground point that pixel really sees (its ray cast
onto the terrain, bumps included); the distance between the two is the BEV's position error
there: what a marking corner drawn at that BEV pixel would be off by. A frame's error is the
mean over the visible BEV samples.

Frames are sorted by the ground under and ahead of the robot (from the world's exact terrain):
``bump`` (a speed bump or rough paving tilts the robot against the smooth ground under it),
``transition`` (the smooth ground's grade changes within the BEV's reach), ``slope`` (a steady
grade) and ``flat``.

``python -m sgf_experiments.ipm_accuracy --preset campus_reverse_slope --scale 0.3 --out DIR`` writes
the table (``ipm_accuracy.md``, ``ipm_accuracy.csv``) and a plot of the error along the route.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml
from sgf_plugins.ipm.stages import (
    AHEAD_MC,
    HindsightMotionCompensatedIPM,
    HindsightMotionCompensatedIpmParams,
    InversePerspectiveMapping,
    IpmParams,
    MotionCompensatedIPM,
    MotionCompensatedIpmParams,
    PlaneMotionCompensatedIPM,
    PlaneMotionCompensatedIpmParams,
)

from sgf_pipeline import RunContext, SgfError
from sgf_pipeline.geometry import rpy_from_rotation
from sgf_pipeline.io import atomic_write_bytes, atomic_write_text
from sgf_pipeline.types import BevGrid, PathAhead

GroundKind = Literal["flat", "slope", "transition", "bump"]
KINDS: tuple[GroundKind, ...] = ("flat", "slope", "transition", "bump")

#: Robot pitch against the smooth ground under it (rad) beyond which a bump or rough paving tilts it.
BUMP_PITCH = 0.006
#: Change of the smooth ground's grade (rise over run) within the BEV's reach that makes a transition.
TRANSITION_GRADE = 0.015
#: Grade of a steady slope.
SLOPE_GRADE = 0.03
#: Distances ahead (m) at which the ground's grade is compared with the grade under the robot.
AHEAD = (1.5, 3.0, 4.5)


def ground_kind(world: Any, pose: np.ndarray) -> GroundKind:
    """The kind of ground the robot at ``pose`` stands on and looks at (from the world's exact terrain)."""
    heading = math.atan2(pose[1, 0], pose[0, 0])
    c, s = math.cos(heading), math.sin(heading)
    d = np.array((0.0, *AHEAD))
    _, gx, gy = world.terrain.height_and_gradient(pose[0, 3] + d * c, pose[1, 3] + d * s, detail=False)
    grade = gx * c + gy * s
    _, pitch, _ = rpy_from_rotation(pose[:3, :3])
    if abs(pitch + math.atan(grade[0])) > BUMP_PITCH:  # pitch is nose-down positive, grade uphill positive
        return "bump"
    if np.abs(grade - grade[0]).max() > TRANSITION_GRADE:
        return "transition"
    return "slope" if abs(grade[0]) > SLOPE_GRADE else "flat"


class BevSamples:
    """Sample points of a BEV grid (every ``step`` pixels) and their ground coordinates."""

    def __init__(self, grid: BevGrid, step: int = 4) -> None:
        if step < 1:
            raise ValueError(f"the sample step must be at least one BEV pixel, got {step}")
        v, u = np.mgrid[step // 2 : grid.height : step, step // 2 : grid.width : step]
        x, y = grid.pixel_to_ground(u.ravel().astype(np.float64), v.ravel().astype(np.float64))
        self.grid = grid
        self.pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)]).astype(np.float64)
        self.ground = np.stack([x, y], axis=1)


def bev_position_error(ground_xy: np.ndarray, pose: np.ndarray, homography: np.ndarray, samples: BevSamples) -> float:
    """Mean distance (m) between where the BEV puts its sample points and the ground the camera sees there.

    ``ground_xy`` (H, W, 2): world ``(x, y)`` of the ground each image pixel sees (NaN for sky);
    ``homography``: BEV pixel -> image pixel, as the IPM stage warps with. NaN when no sample is visible.
    """
    return _position_error(_relative_ground(ground_xy, pose), pose, homography, samples)


def _relative_ground(ground_xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``ground_xy`` relative to the robot, in float32 (small numbers: float32 keeps 0.1 mm): one per frame."""
    return (ground_xy - pose[:2, 3]).astype(np.float32)


def _position_error(relative: np.ndarray, pose: np.ndarray, homography: np.ndarray, samples: BevSamples) -> float:
    """:func:`bev_position_error` on the frame's ground points already made relative to the robot."""
    height, width = relative.shape[:2]
    q = homography @ samples.pixels
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = q[0] / q[2], q[1] / q[2]
    seen = (q[2] > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    if not seen.any():
        return math.nan
    seen_xy = cv2.remap(
        relative,
        u[seen].astype(np.float32)[None],
        v[seen].astype(np.float32)[None],
        cv2.INTER_LINEAR,
    )[0]
    heading = math.atan2(pose[1, 0], pose[0, 0])
    c, s = math.cos(heading), math.sin(heading)
    x, y = samples.ground[seen, 0], samples.ground[seen, 1]
    error = np.hypot(seen_xy[:, 0] - (c * x - s * y), seen_xy[:, 1] - (s * x + c * y))
    error = error[np.isfinite(error)]
    return float(error.mean()) if error.size else math.nan


@dataclass
class IpmAccuracy:
    """Per-frame BEV position errors (m) of each variant, and each frame's kind of ground."""

    frames: list[int] = field(default_factory=list)
    kinds: list[GroundKind] = field(default_factory=list)
    errors: dict[str, list[float]] = field(default_factory=dict)

    def mean(self, variant: str, kind: GroundKind | None = None) -> float:
        """Mean error (m) of a variant over the frames of one kind (all frames when ``kind`` is None)."""
        values = [e for e, k in zip(self.errors[variant], self.kinds, strict=True) if kind is None or k == kind]
        finite = [e for e in values if math.isfinite(e)]
        return float(np.mean(finite)) if finite else math.nan

    def count(self, kind: GroundKind) -> int:
        """How many frames are of this kind."""
        return sum(1 for k in self.kinds if k == kind)

    def table(self) -> str:
        """The mean error per kind of ground and variant as a markdown table (cm)."""
        variants = list(self.errors)
        lines = [
            "| ground | frames | " + " | ".join(f"{v} (cm)" for v in variants) + " |",
            "|---|---:|" + "---:|" * len(variants),
        ]
        for kind in (*KINDS, None):
            n = len(self.frames) if kind is None else self.count(kind)
            if n == 0:
                continue
            cells = " | ".join(f"{100 * self.mean(v, kind):.1f}" for v in variants)
            lines.append(f"| {kind or 'all'} | {n} | {cells} |")
        return "\n".join(lines) + "\n"

    def csv(self) -> str:
        """One row per frame: index, kind of ground, each variant's error in metres."""
        out = io.StringIO()
        writer = csv.writer(out)
        writer.writerow(["frame", "ground", *self.errors])
        for i, (frame, kind) in enumerate(zip(self.frames, self.kinds, strict=True)):
            writer.writerow([frame, kind, *(f"{self.errors[v][i]:.5f}" for v in self.errors)])
        return out.getvalue()


def default_variants() -> dict[str, InversePerspectiveMapping]:
    """Plain IPM, the paper's MC-IPM (``ipm=mc``), and ``ipm=mc_ahead``, ``mc_plane`` and ``mc_hindsight``."""
    return {
        "plain": InversePerspectiveMapping(IpmParams()),
        "mc": MotionCompensatedIPM(MotionCompensatedIpmParams()),
        "mc_ahead": MotionCompensatedIPM(MotionCompensatedIpmParams(**AHEAD_MC)),
        "mc_plane": PlaneMotionCompensatedIPM(PlaneMotionCompensatedIpmParams(**AHEAD_MC)),
        "mc_hindsight": HindsightMotionCompensatedIPM(HindsightMotionCompensatedIpmParams()),
    }


def route_distances(world: Any) -> np.ndarray:
    """Metres the world's odometry has driven at each frame."""
    positions = world.sensors.odometry[:, :3, 3]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def path_ahead(world: Any, index: int, distance: float, driven: np.ndarray | None = None) -> PathAhead:
    """The odometry and IMU of the world's frames after ``index``, until the odometry has moved ``distance`` metres.

    What the runner's read-ahead (``Pipeline.frames``) gives a frame when every frame is a keyframe.
    ``driven``: :func:`route_distances` of the world, when the caller has it already.
    """
    sensors = world.sensors
    odometry, imu = sensors.odometry, sensors.imu_roll_pitch
    driven = route_distances(world) if driven is None else driven
    end = int(np.searchsorted(driven, driven[index] + distance, side="left"))
    complete = end < len(driven)
    end = min(end, len(driven) - 1)
    return PathAhead(odometry[index + 1 : end + 1].copy(), imu[index + 1 : end + 1].copy(), distance, complete)


def evaluate(
    world: Any,
    variants: Mapping[str, InversePerspectiveMapping],
    frames: Iterable[int] | None = None,
    step: int = 4,
    progress: bool = False,
) -> IpmAccuracy:
    """Run every variant over the world's frames (in order: MC-IPM's queue needs them all) and measure its BEVs."""
    stages = dict(variants)
    if not stages:
        raise ValueError("evaluate needs at least one IPM variant")
    grids = {s.grid for s in stages.values()}
    samples = {grid: BevSamples(grid, step) for grid in grids}
    for stage in stages.values():
        stage.begin(RunContext(run_dir=None))
    indices = list(range(len(world)) if frames is None else frames)
    result = IpmAccuracy(errors={name: [] for name in stages})
    driven = route_distances(world) if any(s.read_ahead > 0.0 for s in stages.values()) else None
    iterator: Iterable[int] = indices
    if progress:
        from tqdm import tqdm

        iterator = tqdm(indices, desc="ipm accuracy", unit="frame")
    for k in iterator:
        frame = world.frame(k)
        pose = frame.ground_truth
        layers = world.render_layers(pose, world.frame_conditions(k))
        relative = _relative_ground(layers.ground_xy(), pose)  # once per frame, for every variant
        result.frames.append(k)
        result.kinds.append(ground_kind(world, pose))
        for name, stage in stages.items():
            frame.path_ahead = path_ahead(world, k, stage.read_ahead, driven) if stage.read_ahead > 0.0 else None
            psi, theta = stage.compensation(frame, layers.image)
            h = stage.homography(frame.calibration, psi, theta)
            result.errors[name].append(_position_error(relative, pose, h, samples[stage.grid]))
    return result


def plot(result: IpmAccuracy, title: str) -> bytes:
    """PNG bytes: each variant's error along the route, the kind of ground shaded behind."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"flat": "#ffffff", "slope": "#dbe9f6", "transition": "#fde0c5", "bump": "#f4b6b6"}
    fig, ax = plt.subplots(figsize=(11, 4), dpi=110)
    frames = np.asarray(result.frames)
    for kind in ("slope", "transition", "bump"):
        mask = np.asarray([k == kind for k in result.kinds])
        if mask.any():
            ax.fill_between(frames, 0, 1, where=mask, color=colours[kind], transform=ax.get_xaxis_transform(), lw=0)
    for name, values in result.errors.items():
        ax.plot(frames, 100 * np.asarray(values), lw=0.8, label=f"{name} (mean {100 * result.mean(name):.1f} cm)")
    handles, _ = ax.get_legend_handles_labels()
    from matplotlib.patches import Patch

    handles += [Patch(color=colours[k], label=k) for k in ("slope", "transition", "bump")]
    ax.legend(handles=handles, loc="upper right", fontsize=8, ncol=2)
    ax.set_yscale("symlog", linthresh=10)
    ax.set_xlabel("frame")
    ax.set_ylabel("BEV position error (cm)")
    ax.set_title(title)
    fig.tight_layout()
    out = io.BytesIO()
    fig.savefig(out, format="png")
    plt.close(fig)
    return out.getvalue()


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: measure plain IPM and MC-IPM on a world preset and write the table, CSV and plot."""
    parser = argparse.ArgumentParser(prog="python -m sgf_experiments.ipm_accuracy", description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="campus_reverse_slope", help="world preset (default: the hilly one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scale", type=float, default=0.3, help="route length scale")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--out", type=Path, default=Path("ipm_accuracy"), help="folder to write into")
    parser.add_argument(
        "--variants", default=None, help="comma-separated IPM variants to measure (default: all of them)"
    )
    parser.add_argument(
        "--world",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a world parameter (dataset.KEY of the campus presets), e.g. rough_paving_per_km=50; repeatable",
    )
    args = parser.parse_args(argv)
    overrides: dict[str, Any] = {}
    for item in args.world:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            print(f"error: --world takes KEY=VALUE, got {item!r}", file=sys.stderr)
            return 1
        overrides[key.strip()] = yaml.safe_load(value)
    variants = default_variants()
    if args.variants is not None:
        chosen = [v.strip() for v in args.variants.split(",") if v.strip()]
        unknown = [v for v in chosen if v not in variants]
        if unknown or not chosen:
            print(
                f"error: unknown IPM variant(s) {unknown or args.variants!r}; choose from {', '.join(variants)}",
                file=sys.stderr,
            )
            return 1
        variants = {v: variants[v] for v in chosen}
    from sgf_plugins.world import build_world

    try:
        # occluders and sensor noise change the image, not the geometry: left out, the frames render faster
        world = build_world(
            args.preset, seed=args.seed, scale=args.scale, **{"occluders": False, "sensor_noise": False, **overrides}
        )
        frames = range(len(world) if args.frames is None else min(args.frames, len(world)))
        result = evaluate(world, variants, frames, progress=True)
    except (SgfError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    world_text = "".join(f", {k}={v}" for k, v in overrides.items())
    title = f"{args.preset} seed {args.seed} scale {args.scale}{world_text}: BEV position error per frame"
    args.out.mkdir(parents=True, exist_ok=True)
    table = result.table()
    atomic_write_text(args.out / "ipm_accuracy.md", f"# {title}\n\n{table}")
    atomic_write_text(args.out / "ipm_accuracy.csv", result.csv())
    atomic_write_bytes(args.out / "ipm_accuracy.png", plot(result, title))
    print(table)
    print(f"wrote {args.out / 'ipm_accuracy.md'}, .csv and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
