"""The front-end's levers, measured in one run on the main job's keyframes.

Usage: ``.venv/bin/python bench/bench_frontend.py [keyframes]``  (default 150)

Runs the main job's first keyframes through ``dataset -> enhance -> ipm`` and keeps the BEVs, then,
on those same BEVs, in one run:

- the per-keyframe CPU time of rendering a keyframe and of SelfReformer* at its input size (256)
  and at 224, 192, 160 and 128 (what a smaller input would save; its accuracy is Table 1's to tell);
- the same network on one and on two threads;
- how many keyframes hold a region the detector could take (pixels at or above its threshold, at
  least ``min_area`` of them, inside the view): the most a test that skips the network on keyframes
  where nothing can be salient could save.
"""

from __future__ import annotations

import os
import platform
import sys
import time

import cv2
import numpy as np
from hydra import compose, initialize_config_dir
from sgf_plugins.saliency.inference import SaliencyPredictor
from sgf_plugins.saliency.stages import SelfReformerParams, SelfReformerSaliency

from sgf_pipeline import Pipeline
from sgf_pipeline.config import config_dir


def cpu_ms(fn, items) -> float:
    """Median CPU milliseconds of ``fn`` over the items (process CPU time: every thread)."""
    times = []
    for item in items:
        t0 = time.process_time()
        fn(item)
        times.append(1000.0 * (time.process_time() - t0))
    return float(np.median(times))


def main() -> None:
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 150
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    overrides = ["pipeline=[dataset,enhance,ipm]", "run.progress=false", "run.plots=false", "run.cache=false"]
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    pipeline = Pipeline.from_config(cfg)
    bevs = []
    for frame in pipeline.frames():  # the reader renders each keyframe (dataset time)
        bevs.append(pipeline.process(frame).outputs["bev"])
        if len(bevs) >= count:
            break
    render_ms = 1000.0 * pipeline.info.dataset_seconds / len(bevs)
    print(f"{len(bevs)} keyframes; producing them (the world, its drive, rendering): {render_ms:.1f} ms per keyframe")
    stage = SelfReformerSaliency(SelfReformerParams())
    base = 0.0
    print(f"{'lever':<40} {'CPU ms/keyframe':>16} {'x default':>10}")
    for size in (256, 224, 192, 160, 128):
        predictor = SaliencyPredictor("selfreformer", stage.architecture(), stage.weights_path, size, "onnx", 1)
        ms = cpu_ms(lambda bev, p=predictor: p.predict(bev.image), bevs)
        base = base or ms
        print(f"{f'selfreformer input {size}, 1 thread':<40} {ms:16.1f} {ms / base:10.3f}")
    two = SaliencyPredictor("selfreformer", stage.architecture(), stage.weights_path, 256, "onnx", 2)
    wall = []
    for bev in bevs:
        t0 = time.perf_counter()
        two.predict(bev.image)
        wall.append(1000.0 * (time.perf_counter() - t0))
    print(f"{'selfreformer input 256, 2 threads (wall)':<40} {np.median(wall):16.1f} {np.median(wall) / base:10.3f}")
    default = SaliencyPredictor("selfreformer", stage.architecture(), stage.weights_path, 256, "onnx", 1)
    salient = 0
    for bev in bevs:
        prob = default.predict(bev.image) * bev.valid
        mask = (prob >= 0.5).astype(np.uint8)
        n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        salient += int(any(stats[i, cv2.CC_STAT_AREA] >= 150 for i in range(1, n)))
    share = 100.0 * salient / len(bevs)
    print(f"keyframes with a region the detector could take: {salient} of {len(bevs)} ({share:.0f} %)")


if __name__ == "__main__":
    main()
