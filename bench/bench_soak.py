"""Soak: the default pipeline over a synthetic route of 10 km or more; memory and time per frame as it goes.

Usage: ``.venv/bin/python bench/bench_soak.py [--laps 4] [--preset NAME] [--record FILE.npz] [--state] [--trim]
[hydra overrides...]``

The route is ``campus_large_loop`` (2.8 km) driven ``--laps`` times in a row: a bench-only dataset
replays the preset's frames lap after lap. The route ends 55 m from its start, facing the other
way; between laps the robot is carried back, and the odometry moves by the true pose of the
start seen from the end, so that loops between laps agree with it (odometry that went on from the
end as if the start were there would pull every loop between laps against it). The ground-truth
pose is not passed on (the ATE of a soak is not its point); the marking instances are, so that
``saliency=ground_truth`` soaks the pipeline without the network. An observer records,
per window of 1000 processed frames, the distance driven, the peak and current resident memory,
and the wall and CPU time per frame; the script then prints per lap the median time per frame and
the memory, the memory growth per kilometre after the first lap (when the caches are warm), and
the ratio of the CPU time per frame over the last quarter of the route to the first quarter's.

Memory per window: the RSS and its peak, and glibc malloc's bytes in use and held free; with
``--state``, what each stage holds (:func:`state_mb`); with ``--trim``, the RSS after
``malloc_trim(0)``. Growth per km is the least-squares slope over the windows after the first lap.

With ``--record``, what the back-end received (every processed frame's odometry and the loop
constraints) is saved, so that ``bench_backend.py --replay FILE`` times the back-end alone on it.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import os
import platform
import resource
import statistics
import sys
import time
import types
from collections.abc import Iterator
from typing import Any, cast

import numpy as np
from hydra import compose, initialize_config_dir
from pydantic import Field

from sgf_pipeline import Dataset, Pipeline, RunContext, StageParams, hookimpl, load_plugins
from sgf_pipeline.config import config_dir
from sgf_pipeline.geometry import invert
from sgf_pipeline.types import Frame


class LapsParams(StageParams):
    laps: int = Field(4, ge=1)
    preset: str = "campus_large_loop"
    seed: int = 0


class Laps(Dataset):
    """The preset's drive repeated ``laps`` times; between laps the odometry carries the robot back to the start."""

    name = "soak_laps"
    Params = LapsParams
    params: LapsParams

    def __init__(self, params: LapsParams) -> None:
        super().__init__(params)
        from sgf_plugins.world import build_world

        self.world = build_world(params.preset, seed=params.seed)
        end, start = self.world.frame(len(self.world) - 1), self.world.frame(0)
        assert end.ground_truth is not None and start.ground_truth is not None
        self.carry_back = invert(end.ground_truth) @ start.ground_truth

    def __len__(self) -> int:
        return len(self.world) * self.params.laps

    def begin(self, context: RunContext) -> None:
        context.calibration = self.world.calibration
        context.sequence = f"{self.params.preset} x{self.params.laps}"

    def frames(self) -> Iterator[Frame]:
        n = len(self.world)
        period = n / 10.0 + 1.0
        offset = np.eye(4)
        for lap in range(self.params.laps):
            first = None
            last = None
            for frame in self.world.frames():
                if first is None:
                    first = frame.odometry
                odometry = offset @ invert(first) @ frame.odometry
                last = odometry
                yield Frame(
                    lap * n + frame.index,
                    lap * period + frame.timestamp,
                    lambda f=frame: f.image,  # type: ignore[misc]
                    odometry,
                    frame.calibration,
                    frame.imu_roll_pitch,
                    None,
                    frame.truth_ids,  # saliency=ground_truth still works; the ground-truth pose is not passed on
                )
            assert last is not None
            # carried back to the start between laps: the odometry moves by the true pose of the route's
            # start seen from its end, so that loops between laps agree with it
            offset = last @ self.carry_back


def rss_mb() -> float:
    """Current resident memory (MiB)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            *("arena", "ordblks", "smblks", "hblks", "hblkhd"),
            *("usmblks", "fsmblks", "uordblks", "fordblks", "keepcost"),
        )
    ]


def _libc() -> Any:
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        return libc
    except (OSError, AttributeError):  # not glibc, or glibc before 2.33
        return None


LIBC = _libc()


def native_heap_mb() -> tuple[float, float]:
    """glibc malloc's bytes in use (all arenas and mmapped blocks) and free bytes it holds (MiB); NaN off glibc."""
    if LIBC is None:
        return float("nan"), float("nan")
    info = LIBC.mallinfo2()
    return (info.uordblks + info.hblkhd) / 2**20, info.fordblks / 2**20


_NOT_STATE = (types.ModuleType, type, types.FunctionType, types.BuiltinFunctionType, types.MethodType)


def state_mb(root: object, seen: set[int]) -> float:
    """What an object holds (MiB): every object reachable from it not in ``seen``, numpy arrays by their data.

    Modules, classes and functions are not followed; objects counted once go into ``seen``, so
    stages measured one after the other do not count shared state twice. GTSAM's C++ objects count
    only their Python wrapper (``bench_backend.py --replay`` measures the pose graph's native memory).
    """
    total = 0
    stack = [root]
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, _NOT_STATE):
            continue
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            total += sys.getsizeof(obj)  # the header, and the data when the array owns it
            if isinstance(obj.base, np.ndarray):
                stack.append(obj.base)
            continue
        with contextlib.suppress(TypeError):
            total += sys.getsizeof(obj)
        stack.extend(gc.get_referents(obj))
    return total / 2**20


class SoakObserver:
    """Per window of 1000 processed frames: distance, peak and current RSS, wall and CPU time per frame."""

    def __init__(self, trim: bool = False, state: bool = False) -> None:
        self.rows: list[tuple[float, ...]] = []
        self.trim = trim
        self.state = state
        self.states: list[dict[str, float]] = []
        self._wall = time.perf_counter()
        self._cpu = time.process_time()
        self._count = 0
        self._distance = 0.0
        self._last: np.ndarray | None = None
        self._stage: dict[str, float] = {}
        self.stages: list[dict[str, float]] = []

    @hookimpl
    def sgf_after_stage(self, run: Any, stage: Any, frame: Frame, output: Any, seconds: float) -> None:
        self._stage[stage.kind] = self._stage.get(stage.kind, 0.0) + seconds

    @hookimpl
    def sgf_frame_end(self, run: Any, frame: Frame, seconds: float) -> None:
        position = frame.odometry[:3, 3]
        if self._last is not None:
            self._distance += float(np.linalg.norm(position - self._last))
        self._last = position
        self._count += 1
        if self._count % 1000 == 0:
            wall, cpu = time.perf_counter(), time.process_time()
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            used, free = native_heap_mb()
            row: tuple[float, ...] = (
                self._count,
                self._distance / 1000.0,
                peak,
                rss_mb(),
                wall - self._wall,
                cpu - self._cpu,
                used,
                free,
            )
            if self.trim and LIBC is not None:
                LIBC.malloc_trim(0)
                row = (*row, rss_mb())
            if self.state:
                seen: set[int] = {id(node.stage) for node in run.stages if node.kind == "dataset"}
                sizes = {node.kind: state_mb(node.stage, seen) for node in run.stages if node.kind != "dataset"}
                self.states.append(sizes)
                print("  state MiB: " + ", ".join(f"{k} {v:.2f}" for k, v in sizes.items() if v >= 0.01), flush=True)
            self.rows.append(row)
            self.stages.append({k: v for k, v in self._stage.items()})
            self._stage = {}
            print(
                f"{row[0]:7.0f} {row[1]:6.2f} {row[2]:9.0f} {row[3]:9.0f} {row[4]:9.1f} {row[5]:9.1f}"
                f" {used:9.1f} {free:9.1f}" + (f" {row[8]:9.0f}" if len(row) > 8 else ""),
                flush=True,
            )
            self._wall, self._cpu = wall, cpu


class BackendRecorder:
    """What the back-end receives on each processed frame: odometry, IMU attitude and loop constraints."""

    def __init__(self) -> None:
        self.frames: list[tuple[int, float]] = []
        self.odometry: list[np.ndarray] = []
        self.imu: list[tuple[float, float]] = []
        self.loops: list[tuple[Any, ...]] = []

    @hookimpl
    def sgf_after_stage(self, run: Any, stage: Any, frame: Frame, output: Any, seconds: float) -> None:
        if stage.kind != "loop" or output is None:
            return
        for c in output.items:
            self.loops.append((frame.index, c.frame_from, c.frame_to, c.relative, c.covariance, c.group_id, c.reverse))

    @hookimpl
    def sgf_frame_end(self, run: Any, frame: Frame, seconds: float) -> None:
        self.frames.append((frame.index, float(frame.timestamp)))
        self.odometry.append(np.asarray(frame.odometry, dtype=np.float64))
        imu = frame.imu_roll_pitch
        self.imu.append((float(imu[0]), float(imu[1])) if imu is not None else (np.nan, np.nan))

    def save(self, path: str) -> None:
        loops = self.loops
        np.savez_compressed(
            path,
            frames=np.asarray([f[0] for f in self.frames], dtype=np.int64),
            timestamps=np.asarray([f[1] for f in self.frames]),
            odometry=np.asarray(self.odometry).reshape(-1, 4, 4),
            imu=np.asarray(self.imu, dtype=np.float64).reshape(-1, 2),
            loop_at=np.asarray([c[0] for c in loops], dtype=np.int64),
            loop_from=np.asarray([c[1] for c in loops], dtype=np.int64),
            loop_to=np.asarray([c[2] for c in loops], dtype=np.int64),
            loop_relative=np.asarray([c[3] for c in loops]).reshape(-1, 4, 4),
            loop_covariance=np.asarray([c[4] for c in loops]).reshape(-1, 3, 3),
            loop_group=np.asarray([c[5] for c in loops], dtype=np.int64),
            loop_reverse=np.asarray([c[6] for c in loops], dtype=bool),
        )


class SoakPlugin:
    @hookimpl
    def sgf_register_stages(self, registry: Any) -> None:
        registry.add(Laps)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--laps", type=int, default=4)
    ap.add_argument("--preset", default="campus_large_loop", help="the synthetic route driven lap after lap")
    ap.add_argument("--record", metavar="FILE", help="save the back-end input (.npz) for bench_backend --replay")
    ap.add_argument("--trim", action="store_true", help="malloc_trim(0) after each window; RSS after it is printed")
    ap.add_argument("--state", action="store_true", help="print what each stage holds after each window (MiB)")
    args, overrides = ap.parse_known_args()
    observer = SoakObserver(trim=args.trim, state=args.state)
    extra: list[tuple[str, Any]] = [("soak", SoakPlugin()), ("soak_observer", observer)]
    recorder = BackendRecorder() if args.record else None
    if recorder is not None:
        extra.append(("soak_recorder", recorder))
    plugins = load_plugins(extra=extra)
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*overrides, "run.progress=false", "run.plots=false"])
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(plain, dict)
    plain["dataset"] = {"name": "soak_laps", "laps": args.laps, "preset": args.preset}
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()}")
    print(
        f"{'frames':>7} {'km':>6} {'peak MiB':>9} {'RSS MiB':>9} {'wall ms':>9} {'CPU ms':>9} {'heap MiB':>9}"
        f" {'free MiB':>9}"
        + (f" {'trimmed':>9}" if args.trim else "")
        + "  (ms per frame; heap: glibc malloc's in use / free)",
        flush=True,
    )
    t0 = time.perf_counter()
    metrics = Pipeline.from_config(cast(dict[str, Any], plain), plugins=plugins).run()
    wall = time.perf_counter() - t0
    if recorder is not None:
        recorder.save(args.record)
        print(f"recorded {len(recorder.frames)} frames and {len(recorder.loops)} loops to {args.record}")
    rows = observer.rows
    if len(rows) >= 4:
        lap_km = rows[-1][1] / args.laps
        print("per lap: median wall / CPU ms per frame, RSS at the lap's end")
        for lap in range(args.laps):
            sel = [r for r in rows if lap * lap_km < r[1] <= (lap + 1) * lap_km + 1e-9]
            if sel:
                print(
                    f"  lap {lap + 1}: {statistics.median(r[4] for r in sel):.1f} / "
                    f"{statistics.median(r[5] for r in sel):.1f} ms, RSS {sel[-1][3]:.0f} MiB (peak {sel[-1][2]:.0f})"
                )
        print("per lap: median ms per frame in each stage (wall)")
        kinds = list(observer.stages[0])
        print("  lap " + " ".join(f"{k[:11]:>11}" for k in kinds))
        for lap in range(args.laps):
            idx = [i for i, r in enumerate(rows) if lap * lap_km < r[1] <= (lap + 1) * lap_km + 1e-9]
            if idx:
                cells = [statistics.median(observer.stages[i].get(k, 0.0) for i in idx) for k in kinds]
                print(f"  {lap + 1:3d} " + " ".join(f"{c:11.2f}" for c in cells))
        after = [k for k, r in enumerate(rows) if r[1] >= lap_km]
        if len(after) >= 3:
            # least-squares slopes over the windows after the first lap: the endpoints alone move by
            # the tens of MiB that malloc holds free from one window to the next
            km = np.array([rows[k][1] for k in after])

            def slope(values: list[float]) -> float:
                return float(np.polyfit(km, np.asarray(values, dtype=np.float64), 1)[0])

            a, b = rows[after[0]], rows[after[-1]]
            endpoints = (b[3] - a[3]) / max(b[1] - a[1], 1e-9)
            print(
                f"memory growth after the first lap (MiB/km): RSS {slope([rows[k][3] for k in after]):.1f} "
                f"(endpoints {endpoints:.1f}), peak RSS {slope([rows[k][2] for k in after]):.1f}, "
                f"malloc in use {slope([rows[k][6] for k in after]):.1f}"
                + (f", RSS after malloc_trim {slope([rows[k][8] for k in after]):.1f}" if args.trim else "")
            )
            if observer.states:
                held = list(observer.states[0])
                print(
                    "  what the stages hold (MiB/km): "
                    + ", ".join(f"{k} {slope([observer.states[i].get(k, 0.0) for i in after]):.2f}" for k in held)
                )
        first = statistics.median(r[5] for r in rows[: max(1, len(rows) // 4)])
        last = statistics.median(r[5] for r in rows[-max(1, len(rows) // 4) :])
        print(f"CPU time per frame, last quarter / first quarter of the route: {last / first:.2f}")
    timing = metrics["timing"]
    sgf, loops, backend = metrics.get("sgf", {}), metrics.get("loops", {}), metrics.get("backend", {})
    print(
        f"SGF groups {sgf.get('groups')}, loop candidates {loops.get('candidates')}, accepted loops "
        f"{loops.get('accepted')}, loop factors {backend.get('loop_factors')}, frames {backend.get('nodes')}, "
        f"pose nodes {backend.get('pose_nodes')}"
    )
    print(
        f"route {rows[-1][1] if rows else 0:.1f} km, {timing['frames']} frames, {wall:.0f} s wall, "
        f"robot {timing['fps']:.1f} frames/s, peak RSS {metrics['peak_rss_mb']:.0f} MiB"
    )


if __name__ == "__main__":
    main()
