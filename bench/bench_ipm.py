"""Benchmark of the ipm stages: MC-IPM per frame at 640x480 -> 256x256 BEV, against one cv2.remap.

    .venv/bin/python bench/bench_ipm.py            # print the figures
    .venv/bin/python bench/bench_ipm.py --write    # also record them in bench/RESULTS.md under "## ipm"

Every ratio is measured in the same run. cv2 runs on one thread (cv2.setNumThreads(1)) for the
one-core figures; the machine is shared, so each figure is the median of repeated batches.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import re
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
from sgf_plugins.ipm import (
    HindsightMotionCompensatedIPM,
    HindsightMotionCompensatedIpmParams,
    InversePerspectiveMapping,
    IpmParams,
    MotionCompensatedIPM,
    MotionCompensatedIpmParams,
    PlaneMotionCompensatedIPM,
    PlaneMotionCompensatedIpmParams,
    PoseQueue,
)
from sgf_plugins.ipm.stages import AHEAD_MC
from sgf_plugins.shared.bev_homography import bev_to_image_homography, visible_mask

from sgf_pipeline.calibration import Calibration, Intrinsics, camera_to_base_from_mounting
from sgf_pipeline.io import atomic_write_text
from sgf_pipeline.runner import read_ahead
from sgf_pipeline.types import CameraImage, Frame

RESULTS = Path(__file__).with_name("RESULTS.md")
CALIBRATION = Calibration(
    intrinsics=Intrinsics(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480),
    camera_to_base=camera_to_base_from_mounting(0.8, 0.35, x=0.25),
)


def _timed(fn, n: int, repeats: int) -> float:
    """Median over ``repeats`` batches of the mean seconds per call of ``fn(i)``."""
    fn(0)
    batches = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        batches.append((time.perf_counter() - t0) / n)
    return statistics.median(batches)


def _frames(count: int) -> list[Frame]:
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), (0, 0), 1.0)
    frames = []
    for k in range(count):
        pitch = 0.06 * math.sin(k / 3.0) if k % 40 < 8 else 0.001 * math.sin(k)  # bumps now and then
        odometry = np.eye(4)
        odometry[0, 3] = 0.12 * k  # 1.2 m/s at 10 Hz: the line fit of MC-IPM's reference has distances to fit
        frames.append(Frame(k, 0.1 * k, image, odometry, CALIBRATION, (0.01 * math.sin(k / 5.0), pitch)))
    return frames


def run(n: int, repeats: int) -> dict[str, float]:
    """Per-frame seconds of each measured operation."""
    cv2.setNumThreads(1)
    frames = _frames(n)
    images = [CameraImage(f.image, f.index) for f in frames]
    mc = MotionCompensatedIPM(MotionCompensatedIpmParams())
    plain = InversePerspectiveMapping(IpmParams())
    grid = mc.grid
    h = bev_to_image_homography(CALIBRATION, grid, 0.01, 0.03)
    v, u = np.mgrid[0 : grid.height, 0 : grid.width].astype(np.float64)
    p = np.stack([u, v, np.ones_like(u)], axis=-1) @ h.T
    map_x, map_y = (p[..., 0] / p[..., 2]).astype(np.float32), (p[..., 1] / p[..., 2]).astype(np.float32)
    image = frames[0].image
    ahead = MotionCompensatedIPM(MotionCompensatedIpmParams(**AHEAD_MC))
    queue = PoseQueue()
    line_queue = PoseQueue(fit="line", lookahead=AHEAD_MC["lookahead"])
    out: dict[str, float] = {}
    out["remap"] = _timed(lambda i: cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR), n, repeats)
    out["warp_perspective"] = _timed(
        lambda i: cv2.warpPerspective(
            image, h, (grid.width, grid.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        ),
        n,
        repeats,
    )

    def queue_step(i: int) -> None:
        queue.push(0.0, 0.001 * i, 0.12)
        queue.reference()

    def line_step(i: int) -> None:
        line_queue.push(0.0, 0.001 * i, 0.12)
        line_queue.reference()

    out["queue_and_reference"] = _timed(queue_step, n, repeats)
    out["queue_line"] = _timed(line_step, n, repeats)
    out["homography"] = _timed(lambda i: bev_to_image_homography(CALIBRATION, grid, 0.01, 0.001 * (i % 7)), n, repeats)
    out["visible_mask"] = _timed(lambda i: visible_mask(h, grid, 640, 480), n, repeats)
    out["plain_frame"] = _timed(lambda i: plain.process(frames[i], images[i]), n, repeats)
    out["mc_frame"] = _timed(lambda i: mc.process(frames[i], images[i]), n, repeats)
    out["mc_ahead_frame"] = _timed(lambda i: ahead.process(frames[i], images[i]), n, repeats)
    plane = PlaneMotionCompensatedIPM(PlaneMotionCompensatedIpmParams(**AHEAD_MC))
    out["mc_plane_frame"] = _timed(lambda i: plane.process(frames[i], images[i]), max(10, n // 4), repeats)
    hindsight = HindsightMotionCompensatedIPM(HindsightMotionCompensatedIpmParams())
    # the runner's read-ahead gives each frame the path after it (the last ones: what is left of it)
    ahead_frames = list(read_ahead(((f, True) for f in frames), hindsight.read_ahead))
    out["mc_hindsight_frame"] = _timed(lambda i: hindsight.process(ahead_frames[i], images[i]), n, repeats)
    try:
        import torch

        torch.set_num_threads(1)
        kornia_stage = MotionCompensatedIPM(MotionCompensatedIpmParams(backend="kornia", device="cpu"))
        out["mc_frame_kornia_cpu"] = _timed(
            lambda i: kornia_stage.process(frames[i], images[i]), max(10, n // 20), repeats
        )
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    cv2.setNumThreads(os.cpu_count() or 1)
    out["mc_frame_all_cores"] = _timed(lambda i: mc.process(frames[i], images[i]), n, repeats)
    return out


def machine() -> str:
    """CPU model and core count."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores, Python {platform.python_version()}, OpenCV {cv2.__version__}"


def report(t: dict[str, float]) -> str:
    """The figures as a Markdown section."""
    ms = {k: v * 1e3 for k, v in t.items()}
    lines = [
        "## ipm",
        "",
        f"{machine()}; {datetime.date.today().isoformat()}; load average {os.getloadavg()[0]:.1f} (shared machine: "
        "figures are noisy). `python bench/bench_ipm.py` (median of batches).",
        "640x480 RGB camera image -> default BEV 256x256 (0.02 m/px, x 0.5-5.62 m, y +-2.56 m); cv2 on one thread.",
        "",
        "| per frame | ms | x cv2.remap |",
        "|---|---:|---:|",
    ]
    for key, label in (
        ("remap", "cv2.remap, precomputed maps (reference)"),
        ("warp_perspective", "cv2.warpPerspective (the fast path's warp)"),
        ("queue_and_reference", "pose queue push + reference (N=50)"),
        ("queue_line", "pose queue push + reference (N=50, line fit: ipm=mc_ahead)"),
        ("homography", "H(psi, theta) (eq. 1-4)"),
        ("visible_mask", "visibility mask (row intervals)"),
        ("plain_frame", "**ipm=plain** process()"),
        ("mc_frame", "**ipm=mc** process(): queue, H, mask, warp"),
        ("mc_ahead_frame", "**ipm=mc_ahead** process()"),
        ("mc_plane_frame", "**ipm=mc_plane** process(): mc_ahead + the two-view plane fit (3 levels)"),
        ("mc_hindsight_frame", "**ipm=mc_hindsight** process(): mc_ahead + the plane of the 6.5 m path ahead"),
        ("mc_frame_all_cores", "ipm=mc process(), cv2 on all cores"),
        ("mc_frame_kornia_cpu", "ipm=mc backend=kornia, CPU, 1 torch thread"),
    ):
        if key in ms:
            lines.append(f"| {label} | {ms[key]:.3f} | {ms[key] / ms['remap']:.2f} |")
    verdict = "within" if ms["mc_frame"] <= 2.0 else "OVER"
    lines += [
        "",
        f"MC-IPM costs {ms['mc_frame']:.2f} ms per frame on one core ({verdict} the 2 ms budget), "
        f"{ms['mc_frame'] / ms['remap']:.2f}x one cv2.remap of the same sizes.",
        "",
    ]
    return "\n".join(lines)


def write_section(section: str, name: str = "ipm") -> None:
    """Replace (or append) the ``## <name>`` section of bench/RESULTS.md atomically."""
    text = RESULTS.read_text() if RESULTS.exists() else "# Benchmark results\n\n"
    pattern = re.compile(rf"^## {re.escape(name)}\n.*?(?=^## |\Z)", re.S | re.M)
    text = pattern.sub(section + "\n", text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + section + "\n"
    atomic_write_text(RESULTS, text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400, help="calls per batch")
    parser.add_argument("--repeats", type=int, default=7, help="batches (the median is reported)")
    parser.add_argument("--write", action="store_true", help="record the figures in bench/RESULTS.md")
    args = parser.parse_args()
    section = report(run(args.frames, args.repeats))
    print(section)
    if args.write:
        write_section(section)
        print(f"written to {RESULTS}")


if __name__ == "__main__":
    main()
