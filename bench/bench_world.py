"""Benchmark of the synthetic campus world: one frame's render cost, streaming a preset, memory.

Run: .venv/bin/python bench/bench_world.py [--frames-stream N] [--repeats R]
Everything runs on one core (numpy/BLAS, OpenCV and torch limited to one thread). CPU time
(process_time) is what the machine spent on this process; wall time includes waiting for the
other jobs on a shared machine. Medians over repeats.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import partial

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[var] = "1"  # before numpy is imported: one core

import argparse  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)
try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    pass

from sgf_plugins.world import build_world  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    cpu: list[float] = []
    wall: list[float] = []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return statistics.median(cpu) * 1000, statistics.median(wall) * 1000


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--stream-frames", type=int, default=0, help="frames of campus_delivery to stream (0 = all)")
    ap.add_argument("--memory-frames", type=int, default=3000)
    args = ap.parse_args()
    processor = platform.processor() or platform.machine()
    print(f"machine: {processor}, {os.cpu_count()} cores, python {platform.python_version()}")
    print(f"load average: {os.getloadavg()}")

    # 1. one frame (warm tiles): the renderer alone, day and night, with and without the far field
    world = build_world("campus_delivery", seed=0)
    truth = world.truth
    p = max(truth.passes, key=lambda q: q.end_frame - q.start_frame)
    k = (p.start_frame + p.end_frame) // 2
    pose = world.drive.poses[k]
    for label, cond in (
        ("day", world.frame_conditions(k)),
        ("night", world.conditions(night=True, time=float(world.drive.timestamps[k]), noise_seed=k)),
        ("day, no far field", world.conditions(far_field=False, time=float(world.drive.timestamps[k]))),
    ):
        world.render_layers(pose, cond)
        cpu, wall = timed(partial(world.render_layers, pose, cond), args.repeats)
        print(f"render one 640x480 frame ({label}): {cpu:.1f} ms CPU, {wall:.1f} ms wall (median of {args.repeats})")

    # 2. stream the whole campus_delivery preset (fresh world: cold tiles, every frame rendered)
    world = build_world("campus_delivery", seed=0)
    world.renderer.stopwatch.enabled = True
    n = len(world) if args.stream_frames <= 0 else min(args.stream_frames, len(world))
    c0, w0 = time.process_time(), time.perf_counter()
    per_frame = []
    for frame in world.frames(stop=n):
        f0 = time.process_time()
        image = frame.image
        ids = frame.truth_ids()
        per_frame.append(time.process_time() - f0)
        assert image.shape == (480, 640, 3) and ids is not None
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    duration = float(world.drive.timestamps[n - 1] - world.drive.timestamps[0])
    tiles = world.renderer.cache.generated
    print(
        f"stream campus_delivery: {n} frames in {cpu:.1f} s CPU / {wall:.1f} s wall "
        f"({1000 * cpu / n:.1f} ms CPU per frame, median {1000 * statistics.median(per_frame):.1f} ms, "
        f"{tiles} tiles generated); the sequence lasts {duration:.0f} s: "
        f"{duration / cpu:.1f}x faster than real time (CPU)"
    )
    print(
        "  mean CPU ms per frame by stage: "
        + ", ".join(f"{k} {v:.1f}" for k, v in world.renderer.stopwatch.report().items())
    )

    # 3. memory along a long route: RSS after N/4 frames and after N frames of the large loop
    world = build_world("campus_large_loop", seed=0)
    marks = {}
    quarter = args.memory_frames // 4
    for frame in world.frames(stop=args.memory_frames):
        _ = frame.image
        if frame.index + 1 in (quarter, args.memory_frames):
            marks[frame.index + 1] = rss_mb()
    a, b = marks[quarter], marks[args.memory_frames]
    dist_a = float(np.linalg.norm(np.diff(world.drive.poses[:quarter, :3, 3], axis=0), axis=1).sum())
    dist_b = float(np.linalg.norm(np.diff(world.drive.poses[: args.memory_frames, :3, 3], axis=0), axis=1).sum())
    print(
        f"memory on campus_large_loop: RSS {a:.0f} MiB after {quarter} frames ({dist_a:.0f} m), "
        f"{b:.0f} MiB after {args.memory_frames} frames ({dist_b:.0f} m): ratio {b / a:.2f} "
        f"for {dist_b / max(dist_a, 1e-9):.1f}x the distance"
    )


if __name__ == "__main__":
    main()
