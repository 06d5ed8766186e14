"""Reading the dataset in a thread ahead of the stages, against reading it in the stages' thread.

Usage: ``.venv/bin/python bench/bench_reading.py [hydra overrides...]``

The main job uncached (``run.cache=false``), in one process: the keyframes read (the world driven
and rendered) in the stages' own thread, then by the reading thread ahead of them, each with the
network's default threads and with one torch thread, in the order A B C C B A so that a drift of
the machine's load falls on every case alike. Prints each case's wall time, real-time factor, its
ratio to the reading in the stages' thread, and the ATE (the same in every case).
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time

from hydra import compose, initialize_config_dir

from sgf_pipeline import Pipeline
from sgf_pipeline.config import config_dir

CASES = {
    "stages' thread": (False, []),
    "reading thread": (True, []),
    "reading thread, 1 torch thread": (True, ["run.torch_threads=1"]),
}


def run(background: bool, overrides: list[str]) -> tuple[float, dict]:
    """One main job; its wall time and metrics."""
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    pipeline = Pipeline.from_config(cfg)
    pipeline.reader.load_images = background  # False: each image rendered when a stage reads it, in its thread
    t0 = time.perf_counter()
    metrics = pipeline.run()
    return time.perf_counter() - t0, metrics


def main() -> None:
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    extra = [*sys.argv[1:], "run.cache=false", "run.progress=false", "run.plots=false"]
    print(f"overrides: {' '.join(sys.argv[1:]) or '(the main job)'}")
    names = list(CASES)
    walls: dict[str, list[float]] = {name: [] for name in names}
    results: dict[str, dict] = {}
    for name in [*names, *reversed(names)]:
        background, overrides = CASES[name]
        wall, metrics = run(background, [*extra, *overrides])
        walls[name].append(wall)
        results[name] = metrics
        print(f"  {name}: {wall:.1f} s", flush=True)
    base = statistics.mean(walls[names[0]])
    print(f"{'case':<32} {'wall s':>7} {'x own thread':>12} {'RTF':>6} {'ATE m':>7}")
    for name in names:
        wall = statistics.mean(walls[name])
        metrics = results[name]
        rtf = metrics["timing"]["sequence_seconds"] / wall
        print(f"{name:<32} {wall:7.1f} {wall / base:12.3f} {rtf:6.2f} {metrics['ate_rmse_m']['sgf']:7.3f}")


if __name__ == "__main__":
    main()
