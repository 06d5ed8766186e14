"""Benchmark of ``odometry_scale=bev_motion`` per keyframe at 640x480, against ``ipm=mc`` on the same frames.

    .venv/bin/python bench/bench_odometry_scale.py            # print the figures
    .venv/bin/python bench/bench_odometry_scale.py --write    # also record them in bench/RESULTS.md

Both run in the same process on one thread (cv2.setNumThreads(1)); each figure is the median of
repeated batches. The frames are rendered campus keyframes (campus_large_loop, 30 %), rendered
once before timing.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import cv2
from bench_ipm import RESULTS, machine, write_section
from sgf_plugins.ipm import MotionCompensatedIPM, MotionCompensatedIpmParams
from sgf_plugins.odometry.scale import BevMotionParams, BevMotionScale
from sgf_plugins.world import build_world

from sgf_pipeline import RunContext
from sgf_pipeline.types import CameraImage


def _batch(stage_process: Callable[[int], object], begin: Callable[[], None], n: int, repeats: int) -> float:
    """Median over batches (each from the sequence's start) of the mean seconds per keyframe."""
    batches = []
    for _ in range(repeats):
        begin()
        t0 = time.perf_counter()
        for i in range(n):
            stage_process(i)
        batches.append((time.perf_counter() - t0) / n)
    return statistics.median(batches)


def run(n: int, repeats: int) -> tuple[dict[str, float], float]:
    """Per-keyframe seconds of each stage, and the odometry factor the scale stage ended with."""
    cv2.setNumThreads(1)
    world = build_world("campus_large_loop", seed=0, scale=0.3)
    frames = [world.frame(2 * k) for k in range(n)]  # about 0.25 m apart, like the pipeline's keyframes
    images = [CameraImage(f.image, f.index) for f in frames]
    scale = BevMotionScale(BevMotionParams())
    mc = MotionCompensatedIPM(MotionCompensatedIpmParams())
    out = {
        "scale": _batch(
            lambda i: scale.process(frames[i], images[i]), lambda: scale.begin(RunContext(run_dir=None)), n, repeats
        ),
        "mc": _batch(
            lambda i: mc.process(frames[i], images[i]), lambda: mc.begin(RunContext(run_dir=None)), n, repeats
        ),
    }
    return out, scale.estimate().factor


def report(t: dict[str, float], factor: float, n: int) -> str:
    """The figures as a Markdown section."""
    import datetime
    import os

    ms = {k: v * 1e3 for k, v in t.items()}
    return "\n".join(
        [
            "## odometry_scale",
            "",
            f"{machine()}; {datetime.date.today().isoformat()}; load average {os.getloadavg()[0]:.1f} (shared machine: "
            "figures are noisy). `python bench/bench_odometry_scale.py` (median of batches).",
            f"{n} rendered keyframes of campus_large_loop (30 %), 640x480; cv2 on one thread.",
            "",
            "| per keyframe | ms | x ipm=mc |",
            "|---|---:|---:|",
            f"| ipm=mc process() (reference) | {ms['mc']:.2f} | 1.00 |",
            f"| **odometry_scale=bev_motion** process(): plain-IPM near view, Lucas-Kanade fit, median "
            f"| {ms['scale']:.2f} | {ms['scale'] / ms['mc']:.2f} |",
            "",
            f"The odometry factor after these keyframes: {factor:.4f}.",
            "",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150, help="keyframes per batch")
    parser.add_argument("--repeats", type=int, default=3, help="batches (the median is reported)")
    parser.add_argument("--write", action="store_true", help="record the figures in bench/RESULTS.md")
    args = parser.parse_args()
    times, factor = run(args.frames, args.repeats)
    section = report(times, factor, args.frames)
    print(section)
    if args.write:
        write_section(section, "odometry_scale")
        print(f"written to {RESULTS}")


if __name__ == "__main__":
    main()
