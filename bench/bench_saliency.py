"""Saliency benchmark: inference frames/s of every variant on a default BEV, and training images/s per network.

    .venv/bin/python bench/bench_saliency.py                 # print the tables
    .venv/bin/python bench/bench_saliency.py --write         # and replace `## saliency` in bench/RESULTS.md

Inference runs each variant's `process(bev)` on 256x256 BEVs (0.02 m/px, the default grid) with its
default parameters (each network at its default input_size: selfreformer 256, the BEV's own
2 cm/px; the others 128, the probability resized back to 256), in PyTorch and in onnxruntime, with
1 and 2 threads. Weights are freshly initialised (speed does not depend on their values). Training
runs forward, loss, backward and an AdamW step on in-memory batches of 8 at 128x128 (selfreformer
trains on 128 crops of the 256 BEV); data loading (PNG decoding, augmentation) is timed apart, per
image. All figures come from one run; the ratios compare them with the 20 frames/s target.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from sgf_plugins.saliency import procedural
from sgf_plugins.saliency.augment import Augmentation
from sgf_plugins.saliency.cli_sod_eval import bev_of
from sgf_plugins.saliency.models import ARCHITECTURES, build_model
from sgf_plugins.saliency.preprocess import normalize_image, resize_mask
from sgf_plugins.saliency.stages import (
    LEARNED_VARIANTS,
    ClassicalParams,
    ClassicalSaliency,
    default_architecture,
)
from sgf_plugins.saliency.weights import save_weights

TARGET_FPS = 20.0
RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def machine() -> str:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{cpu}, {os.cpu_count()} cores, load average {load:.1f} at start"


def time_calls(fn, repeats: int, warmup: int) -> tuple[float, float]:
    """Median wall seconds and median process CPU seconds (all threads) per call."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def inference(frames: int, cache: Path) -> list[dict]:
    rng = np.random.default_rng(0)
    bevs = []
    for i in range(8):
        rgb, _, meta = procedural.sample(rng, 256)
        bevs.append(bev_of(rgb, meta["valid"], 0.02, i))
    rows = []
    counter = iter(range(10**9))

    def run(stage):
        stage.process(bevs[next(counter) % len(bevs)])

    for threads in (1, 2):
        torch.set_num_threads(threads)
        classical = ClassicalSaliency(ClassicalParams())
        s, c = time_calls(lambda stage=classical: run(stage), frames, 2)
        rows.append(
            {"model": "classical", "input": 256, "runtime": "numpy/cv2", "threads": threads, "seconds": s, "cpu": c}
        )
    for cls in LEARNED_VARIANTS:
        arch = default_architecture(cls.name)
        torch.manual_seed(0)
        weights = save_weights(build_model(cls.name, arch), cache / f"{cls.name}.safetensors", cls.name, arch)
        for runtime in ("torch", "onnx"):
            for threads in (1, 2):
                torch.set_num_threads(threads)
                params = cls.Params.model_validate(
                    {
                        "weights": str(weights),
                        "runtime": runtime,
                        "threads": threads,
                        "onnx_path": str(cache / f"{cls.name}.onnx"),
                    }
                )
                stage = cls(params)
                s, c = time_calls(lambda stage=stage: run(stage), frames, 3)
                rows.append(
                    {
                        "model": cls.name,
                        "input": params.input_size,  # type: ignore[attr-defined]
                        "runtime": runtime,
                        "threads": threads,
                        "seconds": s,
                        "cpu": c,
                    }
                )
    return rows


def training(steps: int, batch: int, size: int) -> list[dict]:
    rng = np.random.default_rng(1)
    samples = [procedural.sample(rng, 256) for _ in range(batch)]
    aug = Augmentation()
    import cv2

    def load_one(i: int = 0):
        rgb, mask, _ = samples[i % batch]
        rgb = cv2.resize(rgb, (size, size), interpolation=cv2.INTER_AREA)
        m = resize_mask(mask.astype(np.uint8) * 255, size)
        rgb, m = aug(rgb, m, np.random.default_rng(i))
        return normalize_image(rgb, size), m

    prepared = [load_one(i) for i in range(batch)]
    x = torch.from_numpy(np.stack([p[0] for p in prepared]))
    masks = np.stack([p[1] for p in prepared])
    rows = []
    torch.set_num_threads(1)
    data_s, data_c = time_calls(lambda: load_one(3), 20, 2)
    rows.append({"model": "data (resize, augment, normalise)", "threads": 1, "images_per_s": 1 / data_s, "cpu": data_c})
    for model in ARCHITECTURES:
        net = build_model(model, default_architecture(model)).train()
        targets = {"mask": torch.from_numpy(masks[:, None])}
        extra = getattr(net, "targets_from_mask", None)
        if extra is not None:
            for key in extra(masks[0]):
                targets[key] = torch.from_numpy(np.stack([extra(m)[key] for m in masks])[:, None])
        opt = torch.optim.AdamW(net.parameters(), lr=1e-4)

        def step(net=net, targets=targets, opt=opt):
            loss, _ = net.loss(net(x), targets)
            opt.zero_grad()
            loss.backward()
            opt.step()

        for threads in (1, 2):
            torch.set_num_threads(threads)
            s, c = time_calls(step, steps, 1)
            rows.append({"model": model, "threads": threads, "images_per_s": batch / s, "cpu": c / batch})
    return rows


def render(inf: list[dict], train: list[dict], args: argparse.Namespace) -> str:
    date = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    import onnxruntime

    lines = [
        "## saliency",
        "",
        f"`bench/bench_saliency.py` on {date}: {machine()}; torch {torch.__version__}, "
        f"onnxruntime {onnxruntime.__version__}. The machine is shared with other jobs: medians of "
        f"{args.frames} frames / {args.steps} steps, all in one run.",
        "",
        "### Inference: `process(bev)` on a 256x256 BEV (0.02 m/px)",
        "",
        "Each network at its default input size (column `input`; the probability is resized to 256).",
        "",
        "Wall time is what the pipeline sees on this shared machine; CPU time (all threads of the process) is",
        "the work itself: with 1 thread, 1000 / CPU ms is the frame rate on one otherwise idle core.",
        "",
        "| model | input | runtime | threads | wall ms/frame | frames/s (wall) | x 20 fps | CPU ms/frame "
        "| frames/s (1 core, CPU) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in inf:
        fps = 1.0 / r["seconds"]
        core = f"{1.0 / r['cpu']:.1f}" if r["threads"] == 1 else "-"
        lines.append(
            f"| {r['model']} | {r['input']} | {r['runtime']} | {r['threads']} | {1000 * r['seconds']:.1f} "
            f"| {fps:.1f} | {fps / TARGET_FPS:.2f} | {1000 * r['cpu']:.1f} | {core} |"
        )
    lines += [
        "",
        f"### Training: forward + loss + backward + AdamW step, batches of {args.batch} at {args.size}x{args.size}",
        "",
        "Two threads help on an idle machine and lose to one when other jobs share the two cores (threads",
        "wait for each other at every operation: at load 4.7, selfreformer trains 0.7",
        "images/s with 2 threads and 11.4 with 1); `sgf-train` uses `train.threads=1` by default. Hours are",
        "at the measured wall rate.",
        "",
        "| model | threads | images/s (wall) | CPU ms/image | images/s (1 core, CPU) "
        "| hours for 3000 images x 30 epochs |",
        "|---|---|---|---|---|---|",
    ]
    for r in train:
        hours = 3000 * 30 / r["images_per_s"] / 3600
        core = f"{1.0 / r['cpu']:.1f}" if r["threads"] == 1 else "-"
        lines.append(
            f"| {r['model']} | {r['threads']} | {r['images_per_s']:.1f} | {1000 * r['cpu']:.0f} | {core} "
            f"| {hours:.1f} |"
        )
    return "\n".join(lines) + "\n"


def write_section(text: str) -> None:
    old = RESULTS.read_text() if RESULTS.is_file() else "# Benchmark results\n"
    pattern = re.compile(r"^## saliency\n.*?(?=^## |\Z)", re.S | re.M)
    new = pattern.sub(text + "\n", old) if pattern.search(old) else old.rstrip("\n") + "\n\n" + text
    RESULTS.write_text(new)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="timed frames per configuration")
    parser.add_argument("--steps", type=int, default=5, help="timed training steps per configuration")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--write", action="store_true", help="replace the `## saliency` section of bench/RESULTS.md")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        inf = inference(args.frames, Path(tmp))
    train = training(args.steps, args.batch, args.size)
    text = render(inf, train, args)
    print(text)
    if args.write:
        write_section(text)
        print(f"written to {RESULTS}")


if __name__ == "__main__":
    main()
