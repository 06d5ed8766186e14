"""The stage cache's effect: wall time of the main job uncached, filling the cache, and from it.

Usage: ``.venv/bin/python bench/bench_cache.py [hydra overrides...]``

All in one run, in a fresh cache folder: the main job with ``run.cache=false``; the same filling
an empty cache (what the cache costs a first run); then, from that cache, the same job again
(every front-end stage hits), a job that changes only the association (a leave-one-out entry), one
that changes only the detector (the network's and the IPM's outputs reused), and one that changes
the IPM (everything computed again). Prints each wall time, its ratio to the uncached run, the
stages that hit, the cache's own seconds and the size of the entries.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from sgf_pipeline import Pipeline
from sgf_pipeline.cache import STAGE_CACHE_ENV, StageCache
from sgf_pipeline.config import config_dir

CASES = [
    ("uncached", ["run.cache=false"]),
    ("filling the cache", []),
    ("the same job, cached", []),
    ("association changed", ["association.match.new_group_distance=0.6"]),
    ("detector changed", ["detector.min_area=41"]),
    ("ipm changed", ["ipm.region=fixed"]),
]


def main() -> None:
    os.environ.pop(STAGE_CACHE_ENV, None)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    extra = [*sys.argv[1:], "run.progress=false", "run.plots=false"]
    print(f"overrides: {' '.join(sys.argv[1:]) or '(the main job)'}")
    with tempfile.TemporaryDirectory(prefix="sgf_bench_cache") as folder:
        cache = Path(folder) / "cache"
        base = 0.0
        print(f"{'case':<24} {'wall s':>7} {'x uncached':>10} {'cache s':>8}  hits")
        for name, overrides in CASES:
            with initialize_config_dir(str(config_dir()), version_base="1.3"):
                cfg = compose("config", overrides=[*extra, f"run.cache_dir={cache}", *overrides])
            t0 = time.perf_counter()
            metrics = Pipeline.from_config(cfg).run()
            wall = time.perf_counter() - t0
            base = base or wall
            report = metrics.get("cache", {})
            hits = ", ".join(report.get("hits", [])) or "-"
            print(f"{name:<24} {wall:7.1f} {wall / base:10.3f} {report.get('seconds', 0.0):8.1f}  {hits}")
        entries = StageCache(cache, 0).entries()
        by_kind: dict[str, int] = {}
        for entry in entries:
            by_kind[entry.kind] = by_kind.get(entry.kind, 0) + entry.bytes
        frames = max((e.frames for e in entries), default=0)
        sizes = ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in sorted(by_kind.items()))
        print(f"entries: {len(entries)}, {frames} keyframes each; {sizes}")


if __name__ == "__main__":
    main()
