"""What loop closing can reach on a campus route: ATE when revisit pairs close at their true relative pose.

    .venv/bin/python bench/bench_loop_oracle.py campus_large_loop --seeds 0 1 2 --scale 0.3
    .venv/bin/python bench/bench_loop_oracle.py campus_large_loop --scale 1.0 --loops RUN/loops.csv

The shipped back-end (``backend=isam2``, its defaults) gets the route's keyframes (every 0.25 m of
odometry, as ``sgf-run``) and a loop constraint per chosen revisit pair, measured from the ground
truth between the middles of the two passes (5 cm and 1 degree of noise in the covariance only),
delivered when the second pass is driven. The pairs: every revisit pair, the pairs of asymmetric
markings (symmetric ones never give a loop factor), or the instances a run closed (``--loops``,
its ``loops.csv``, true loops only). Each with the heading-bias estimate on and off
(``backend.heading_bias.enabled``). The floor of Table 2's ATE for a route, and what each part of
the loop closing is worth on it.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np
from sgf_plugins.backend.isam2 import Isam2Backend
from sgf_plugins.backend.params import HeadingBiasParams, Isam2Params
from sgf_plugins.world.world import CampusWorld, build_world

from sgf_pipeline.context import RunContext
from sgf_pipeline.evaluation import ate_rmse
from sgf_pipeline.geometry import invert
from sgf_pipeline.trajectory import Trajectory
from sgf_pipeline.truth import RevisitPair
from sgf_pipeline.types import Frame, LoopConstraint, LoopConstraints

KEYFRAME_DISTANCE = 0.25  # m of odometry between processed frames, as the runner's default
LOOP_COVARIANCE = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])


def keyframes(odometry: np.ndarray) -> list[int]:
    """Frames at least KEYFRAME_DISTANCE of odometry path apart (the first always)."""
    out, travelled = [0], 0.0
    for k in range(1, len(odometry)):
        travelled += float(np.linalg.norm(odometry[k, :3, 3] - odometry[k - 1, :3, 3]))
        if travelled >= KEYFRAME_DISTANCE:
            out.append(k)
            travelled = 0.0
    return out


def solve(world: CampusWorld, frames: list[int], pairs: list[RevisitPair], bias: bool) -> float:
    """ATE (m, SE(3)-aligned like sgf-run's) of the back-end given true loops for ``pairs``."""
    gt, odometry, calibration = world.drive.poses, world.sensors.odometry, world.calibration
    kept = set(frames)
    loops: dict[int, list[LoopConstraint]] = {}
    for p in pairs:
        a = min(kept, key=lambda f: abs(f - (p.first.start_frame + p.first.end_frame) // 2))
        b = min(kept, key=lambda f: abs(f - (p.second.start_frame + p.second.end_frame) // 2))
        ids = (p.instance_id, p.instance_id)
        loop = LoopConstraint(a, b, invert(gt[a]) @ gt[b], LOOP_COVARIANCE, 0, p.reverse, 0.01, 1.0, ids)
        loops.setdefault(b, []).append(loop)
    backend = Isam2Backend(Isam2Params(save_map=False, heading_bias=HeadingBiasParams(enabled=bias)))
    context = RunContext(run_dir=None, calibration=calibration)
    backend.begin(context)
    imu = world.sensors.imu_roll_pitch
    for k in frames:
        roll_pitch = (float(imu[k][0]), float(imu[k][1]))
        frame = Frame(k, k / world.params.rate_hz, np.zeros((2, 2), np.uint8), odometry[k], calibration, roll_pitch)
        found = loops.get(k)
        backend.process(frame=frame, loops=LoopConstraints(tuple(found)) if found else None)
    backend.finalize(context)
    times = np.array([k / world.params.rate_hz for k in frames])
    return ate_rmse(Trajectory(times, gt[frames]), context.trajectories["sgf"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("preset", help="campus_large_loop, campus_reverse_slope, campus_delivery, ...")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--scale", type=float, default=0.3)
    parser.add_argument("--loops", type=Path, nargs="*", default=[], help="a run's loops.csv per seed (optional)")
    args = parser.parse_args()
    if args.loops and len(args.loops) != len(args.seeds):
        parser.error("give one loops.csv per seed")
    print(f"{args.preset} at {args.scale:g} of its length: ATE (m) with true loops for the chosen revisit pairs")
    print("| seed | odometry | pairs | every pair | asymmetric pairs | the run's closed pairs | same, bias off |")
    print("|---|---|---|---|---|---|---|")
    for n, seed in enumerate(args.seeds):
        t0 = time.perf_counter()
        world = build_world(args.preset, seed=seed, scale=args.scale)
        truth = world.truth
        frames = keyframes(world.sensors.odometry)
        times = np.array([k / world.params.rate_hz for k in frames])
        odometry = ate_rmse(
            Trajectory(times, world.drive.poses[frames]), Trajectory(times, world.sensors.odometry[frames])
        )
        every = solve(world, frames, truth.revisits, True)
        asymmetric = [p for p in truth.revisits if not truth.markings[p.instance_id].symmetric]
        cells = [f"{solve(world, frames, asymmetric, True):.2f} ({len(asymmetric)})"]
        if args.loops:
            with open(args.loops[n], newline="") as f:
                closed = {
                    int(r["instance_from"]) for r in csv.DictReader(f) if r["true"] == "True" and r["instance_from"]
                }
            chosen = [p for p in truth.revisits if p.instance_id in closed]
            on, off = solve(world, frames, chosen, True), solve(world, frames, chosen, False)
            cells += [f"{on:.2f} ({len(chosen)})", f"{off:.2f}"]
        else:
            cells += ["", ""]
        print(f"| {seed} | {odometry:.2f} | {len(truth.revisits)} | {every:.2f} | " + " | ".join(cells) + " |")
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
