"""What a Rerun recording (``viz=rerun``) costs the main job: its wall time with and without it, in one sitting.

Usage: ``.venv/bin/python bench/bench_viz.py [--pairs N | --lockstep] [hydra overrides...]``,
or ``.venv/bin/python bench/bench_viz.py --replay N``

Runs the default ``sgf-run`` configuration (the main job, campus_delivery at full length; overrides
such as ``dataset.scale=0.2`` shorten it) into a temporary run directory, alternately without and
with ``viz=rerun`` (off, on, on, off, ... so that a drifting machine load falls on both sides
alike), and prints each run's wall time, the process's CPU time (what a machine shared with other
jobs measures more steadily), the robot's work (the stages after ``dataset``, whose
time includes the observers' per-stage hooks), the recording's own time per keyframe on its thread
and on the pipeline's, and the size of ``run.rrd``; then the ratios of the summed times, on over off.

``--lockstep`` runs the two at once in one process, one keyframe of each in turn, each keyframe's
recording waited for before the other pipeline goes on: both sides see the same load, and the
ratio of their times (work, and work plus rendering) is an upper bound of the recording's cost.

``--replay N`` measures the recording alone: N keyframes of the main job's first camera image
(640 x 480) with a BEV, a saliency map and a growing estimate of the main job's sizes, through the
recording on this thread; it prints the process's CPU time per keyframe (the SDK's threads included).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import sgf_plugins.viz.rerun as rerun_viz
from hydra import compose, initialize_config_dir
from sgf_plugins.viz.rerun.options import RECORDING, RerunOptions
from sgf_plugins.viz.rerun.recording import Keyframe, Recording
from sgf_plugins.viz.rerun.worker import RecordingWorker

from sgf_pipeline import Pipeline
from sgf_pipeline.config import config_dir
from sgf_pipeline.runner import RunInfo
from sgf_pipeline.types import Bev, BevGrid, CameraImage, PoseEstimate, SaliencyMap


def observer_clock() -> list[float]:
    """Wrap the recording's methods so that their wall times add up: [recording thread, pipeline thread]."""
    spent = [0.0, 0.0]
    methods: list[tuple[type, str, int]] = [(Recording, n, 0) for n in ("log_frame", "log_end", "close")]
    methods += [(RecordingWorker, n, 1) for n in ("__init__", "stage_done", "frame_done")]
    for cls, name, cell in methods:
        original = getattr(cls, name)

        def timed(self: Any, *args: Any, _original: Any = original, _cell: int = cell, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return _original(self, *args, **kwargs)
            finally:
                spent[_cell] += time.perf_counter() - t0

        setattr(cls, name, timed)
    return spent


def run(overrides: list[str], viz: bool, out: Path, spent: list[float]) -> dict[str, Any]:
    """One run of the main job; its wall time, work, keyframes, the observer's time and the recording's size."""
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*overrides, "run.progress=false", *(["viz=rerun"] if viz else [])])
    spent[:] = [0.0, 0.0]
    t0, cpu0 = time.perf_counter(), time.process_time()
    metrics = Pipeline.from_config(cfg, run_dir=out).run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    recording = out / RECORDING
    return {
        "wall": wall,
        "cpu": cpu,
        "work": metrics["timing"]["seconds"],
        "frames": metrics["timing"]["frames"],
        "recording": spent[0],
        "pipeline": spent[1],
        "mib": recording.stat().st_size / 2**20 if recording.exists() else 0.0,
        "ate": metrics["ate_rmse_m"]["sgf"],
    }


def replay(frames: int) -> None:
    """The recording alone, on the main job's first camera image and outputs of its sizes: CPU time per keyframe."""
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["pipeline=[dataset]", "run.progress=false"])
    pipeline = Pipeline.from_config(cfg)
    camera = next(iter(pipeline.frames())).image  # a rendered campus frame: the JPEG a camera image makes
    rng = np.random.default_rng(0)
    grid = BevGrid(0.02, 0.5, 5.62, -2.56, 2.56)
    bev = Bev(camera[-256:, 192:448].copy(), np.ones((256, 256), bool), grid, 0, 0.0)
    saliency = SaliencyMap(rng.random((256, 256)).astype(np.float32), bev)
    stages = ("enhance", "ipm", "odometry_scale", "saliency", "detector", "descriptor", "association", "loop")
    poses: dict[int, np.ndarray] = {}
    keys = []
    for i in range(frames):
        odometry = np.eye(4)
        odometry[:2, 3] = 0.25 * i, 0.01 * i
        poses[i] = odometry
        outputs = {CameraImage: CameraImage(camera, i), Bev: bev, SaliencyMap: saliency}
        outputs[PoseEstimate] = PoseEstimate(i, dict(poses))
        keys.append(Keyframe(i, 0.1 * i, camera, odometry, odometry, outputs, dict.fromkeys(stages, 1e-3), 0, []))
    with tempfile.TemporaryDirectory() as tmp:
        run = RunInfo(run_dir=Path(tmp), stages=[], sequence="replay", total_frames=frames)
        t0 = time.process_time()  # every thread of the process: the SDK's own ones too
        recording = Recording(run, RerunOptions())
        for key in keys:
            recording.log_frame(key)
        recording.close(finished=True)
        spent = time.process_time() - t0
        size = (Path(tmp) / RECORDING).stat().st_size
    print(f"recording alone: {1000 * spent / frames:.2f} ms of CPU per keyframe, {size / frames / 1024:.0f} KiB each")


def lockstep(overrides: list[str]) -> None:
    """The main job twice at once, without and with the recording, one keyframe of each in turn.

    The recording of each keyframe is waited for before the other pipeline goes on, so that its
    whole cost counts against the run that records (none of it overlaps the other's work): an
    upper bound of what the recording's thread costs, measured under the same load on both sides.
    """
    with tempfile.TemporaryDirectory() as tmp:
        pipelines = {}
        for viz in (False, True):
            with initialize_config_dir(str(config_dir()), version_base="1.3"):
                cfg = compose("config", overrides=[*overrides, "run.progress=false", *(["viz=rerun"] if viz else [])])
            pipelines[viz] = Pipeline.from_config(cfg, run_dir=Path(tmp) / ("on" if viz else "off"))
        spent = {False: 0.0, True: 0.0}

        def drained(pipeline: Pipeline) -> None:
            worker = rerun_viz._OBSERVER._runs.get(id(pipeline.info))
            if worker is not None:
                done = threading.Event()
                worker.jobs.put(done.set)
                done.wait()

        streams = zip(pipelines[False].frames(), pipelines[True].frames(), strict=True)
        for k, frames in enumerate(streams):
            for viz in (False, True) if k % 2 == 0 else (True, False):
                t0 = time.perf_counter()
                pipelines[viz].process(frames[viz])
                drained(pipelines[viz])
                spent[viz] += time.perf_counter() - t0
        for viz in (False, True):
            t0 = time.perf_counter()
            metrics = pipelines[viz].finish()
            spent[viz] += time.perf_counter() - t0
            info = pipelines[viz].info
            print(
                f"viz {'on ' if viz else 'off'}: {info.frames_processed} keyframes, work and recording "
                f"{spent[viz]:.1f} s, rendering {info.dataset_seconds:.1f} s, ATE {metrics['ate_rmse_m']['sgf']:.3f} m"
            )
        rendering = {viz: pipelines[viz].info.dataset_seconds for viz in (False, True)}
        work = spent[True] / spent[False]
        job = (spent[True] + rendering[True]) / (spent[False] + rendering[False])
        print(
            f"keyframe by keyframe, with the recording over without: the robot's work {work:.3f}, "
            f"the whole job (work and rendering) {job:.3f}; load average {os.getloadavg()[0]:.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2, help="pairs of runs, without and with the recording")
    parser.add_argument("--replay", type=int, default=0, help="only replay this many synthetic keyframes")
    parser.add_argument("--lockstep", action="store_true", help="both runs at once, a keyframe of each in turn")
    args, overrides = parser.parse_known_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    if args.replay:
        replay(args.replay)
        return
    if args.lockstep:
        lockstep(overrides)
        return
    print(f"overrides: {' '.join(overrides) or '(the main job)'}")
    spent = observer_clock()
    order = [k % 4 in (1, 2) for k in range(2 * args.pairs)]  # off, on, on, off, ...
    results: dict[bool, list[dict[str, Any]]] = {False: [], True: []}
    with tempfile.TemporaryDirectory() as tmp:
        for k, viz in enumerate(order):
            r = run(overrides, viz, Path(tmp) / f"run{k}", spent)
            results[viz].append(r)
            print(
                f"viz {'on ' if viz else 'off'}: wall {r['wall']:6.1f} s, CPU {r['cpu']:6.1f} s, "
                f"work {r['work']:6.1f} s, {r['frames']} keyframes, recording "
                f"{1000 * r['recording'] / r['frames']:5.2f} ms per keyframe on its thread and "
                f"{1000 * r['pipeline'] / r['frames']:4.2f} ms on the pipeline's, run.rrd "
                f"{r['mib']:.1f} MiB, ATE {r['ate']:.3f} m; load average {os.getloadavg()[0]:.2f}"
            )
    total = {key: [sum(r[key] for r in results[v]) for v in (False, True)] for key in ("wall", "cpu", "work")}
    wall, cpu, work = (on / off for off, on in total.values())
    print(f"with the recording over without: wall time {wall:.3f}, the process's CPU time {cpu:.3f}, work {work:.3f}")


if __name__ == "__main__":
    main()
