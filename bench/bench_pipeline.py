"""The default pipeline's speed: frames per second and real-time factor of `sgf-run` on its default config.

Usage: ``.venv/bin/python bench/bench_pipeline.py [hydra overrides...]``

Runs the composed default configuration (the README's first command, without writing a run
directory), then prints the per-stage milliseconds, the robot's frames per second (the stages
after ``dataset``), the time spent producing frames (rendering the synthetic campus), and the
real-time factor: the sequence's duration over the wall time of the robot's work.
"""

from __future__ import annotations

import os
import platform
import sys
import time

from hydra import compose, initialize_config_dir

from sgf_pipeline import Pipeline
from sgf_pipeline.config import config_dir


def main() -> None:
    overrides = [*sys.argv[1:], "run.progress=false", "run.plots=false"]
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    print(f"overrides: {' '.join(sys.argv[1:]) or '(default config)'}")
    t0 = time.perf_counter()
    metrics = Pipeline.from_config(cfg).run()
    wall = time.perf_counter() - t0
    timing = metrics["timing"]
    print(f"sequence {metrics['sequence']}: {timing['frames']} frames processed of {timing['dataset_frames']}")
    print(f"{'stage':<12} {'variant':<16} {'mean ms':>8}")
    for kind, row in timing["stages"].items():
        print(f"{kind:<12} {row['variant']:<16} {row['mean_ms'] or 0.0:8.2f}")
    print(f"robot's work: {timing['seconds']:.1f} s, {timing['fps']:.1f} frames/s")
    print(f"producing frames (rendering): {timing['dataset_seconds']:.1f} s")
    print(f"real-time factor: {timing['realtime_factor']:.2f} (sequence {timing['sequence_seconds']:.0f} s)")
    print(f"wall time of the whole run: {wall:.0f} s; peak RSS {metrics['peak_rss_mb']:.0f} MiB")
    ate = metrics["ate_rmse_m"]
    print(f"ATE odometry {ate['odometry']}, odometry + SGF {ate['sgf']}")


if __name__ == "__main__":
    main()
