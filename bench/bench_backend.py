"""Back-end speed: iSAM2 update time per keyframe up to 10,000 poses, batch LM on a 2.7 km sequence.

    .venv/bin/python bench/bench_backend.py            # both benchmarks
    .venv/bin/python bench/bench_backend.py --quick    # smaller sizes (a smoke run)
    .venv/bin/python bench/bench_backend.py --growth 16000   # update time per window as the graph grows
    .venv/bin/python bench/bench_backend.py --replay rec.npz # a recorded soak's back-end input (bench_soak --record)

Budgets: iSAM2 median update under 10 ms at 10,000 poses with loop closures; batch
Levenberg-Marquardt over ~9,000 Pose2 keyframes (2.7 km) with a few dozen loops under 1 s.
The route is laps of a 400 m x 250 m block with drifting odometry; loop constraints join the
current keyframe to the same place on the first lap, measured from the ground truth.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import statistics
import time

import numpy as np
from omegaconf import OmegaConf
from sgf_plugins.backend.isam2 import Isam2Backend
from sgf_plugins.backend.lm import GtsamLmBackend
from sgf_plugins.backend.params import Isam2Params, Isam2Solver, LmParams, LmSolver

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.context import RunContext
from sgf_pipeline.geometry import invert, pose_from_xy_yaw, xy_yaw
from sgf_pipeline.types import Frame, LoopConstraint, LoopConstraints

CALIBRATION = Calibration.from_mounting(
    Intrinsics(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480), height=0.8, tilt=0.35
)
BLOCK = (400.0, 250.0)


def route(n: int, step: float) -> np.ndarray:
    """(n, 4, 4) ground-truth poses every ``step`` m around the block, lap after lap."""
    length, width = BLOCK
    sides = [((0.0, 0.0), 0.0, length), ((length, 0.0), math.pi / 2, width)]
    sides += [((length, width), math.pi, length), ((0.0, width), -math.pi / 2, width)]
    perimeter = 2 * (length + width)
    poses = []
    for k in range(n):
        s = (k * step) % perimeter
        side = 0
        while s >= sides[side][2]:
            s -= sides[side][2]
            side += 1
        (x0, y0), heading, _ = sides[side]
        poses.append(pose_from_xy_yaw(x0 + s * math.cos(heading), y0 + s * math.sin(heading), heading))
    return np.stack(poses)


def odometry(gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Odometry with a heading random walk, a heading bias and a scale error."""
    out = [gt[0]]
    for a, b in itertools.pairwise(gt):
        x, y, yaw = xy_yaw(invert(a) @ b)
        d = math.hypot(x, y)
        noisy = pose_from_xy_yaw(
            x * 1.01 + rng.normal(0, 0.02 * math.sqrt(d)),
            y + rng.normal(0, 0.02 * math.sqrt(d)),
            yaw + math.radians(0.02) * d + rng.normal(0, math.radians(0.3) * math.sqrt(d)),
        )
        out.append(out[-1] @ noisy)
    return np.stack(out)


def loops(gt: np.ndarray, step: float, every: float, rng: np.random.Generator) -> dict[int, list[LoopConstraint]]:
    """Loop constraints every ``every`` m after the first lap, to the same place on the first lap."""
    perimeter = 2 * sum(BLOCK)
    per_lap = round(perimeter / step)
    stride = max(1, round(every / step))
    cov = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])
    out: dict[int, list[LoopConstraint]] = {}
    for b in range(per_lap + stride, len(gt), stride):
        a = b % per_lap
        rel = invert(gt[a]) @ gt[b]
        x, y, yaw = xy_yaw(rel)
        noisy = pose_from_xy_yaw(x + rng.normal(0, 0.03), y + rng.normal(0, 0.03), yaw + rng.normal(0, 0.01))
        out.setdefault(b + 2, []).append(LoopConstraint(a, b, noisy, cov, 0, False, 0.01, 1.0))
    return out


def frames(gt: np.ndarray, odo: np.ndarray) -> list[Frame]:
    image = np.zeros((1, 1), np.uint8)
    return [
        Frame(k, 0.1 * k, image, o, CALIBRATION, ground_truth=g) for k, (g, o) in enumerate(zip(gt, odo, strict=True))
    ]


def ate(est: np.ndarray, gt: np.ndarray) -> float:
    p, q = est[:, :2, 3], gt[:, :2, 3]
    mp, mq = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - mp).T @ (q - mq))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, d]) @ u.T
    return float(np.sqrt(np.mean(np.sum(((p - mp) @ rot.T + mq - q) ** 2, axis=1))))


def bench_isam2(n: int, seed: int) -> dict[str, float]:
    """Stream n keyframes (1 m apart) into backend=isam2; wall and CPU time of each update.

    The CPU time (``time.process_time``) is the figure to trust on a shared machine: it leaves
    out the time this process waited for a core.
    """
    rng = np.random.default_rng(seed)
    gt = route(n, 1.0)
    odo = odometry(gt, rng)
    found = loops(gt, 1.0, 50.0, rng)
    backend = Isam2Backend(Isam2Params(save_map=False))
    backend.begin(RunContext(run_dir=None))
    cpu = []
    t0 = time.perf_counter()
    for frame in frames(gt, odo):
        items = found.get(frame.index)
        c0 = time.process_time()
        backend.process(frame=frame, loops=LoopConstraints(tuple(items)) if items else None)
        cpu.append(time.process_time() - c0)
    total = time.perf_counter() - t0
    wall = np.asarray(backend.update_seconds) * 1e3
    ms = np.asarray(cpu) * 1e3
    loop_frames = np.array(sorted(k for k in found if k < n))
    context = RunContext(run_dir=None)
    backend.finalize(context)
    return {
        "poses": n,
        "loops": sum(len(v) for k, v in found.items() if k < n),
        "cpu_median_ms": float(np.median(ms)),
        "cpu_median_last_1000_ms": float(np.median(ms[-1000:])),
        "cpu_p90_ms": float(np.percentile(ms, 90)),
        "cpu_median_loop_frame_ms": float(np.median(ms[loop_frames])) if loop_frames.size else math.nan,
        "cpu_max_ms": float(ms.max()),
        "wall_median_ms": float(np.median(wall)),
        "wall_median_last_1000_ms": float(np.median(wall[-1000:])),
        "wall_total_s": total,
        "ate_odometry_m": ate(odo, gt),
        "ate_isam2_m": ate(context.trajectories["sgf"].poses, gt),
    }


def bench_growth(n: int, seed: int, window: int = 2000) -> dict[str, list[float]]:
    """Mean CPU ms per keyframe of backend=isam2 per window, keyframes 0.3 m apart (the pipeline's
    spacing), loops every 10 m after the first lap: with a node per keyframe, and with the defaults.

    Keys: ``"node_distance=<m>"``, each a list of window means; ``"partial_check_off"`` is the
    node-per-keyframe graph with GTSAM's full relinearization check.
    """
    rng = np.random.default_rng(seed)
    gt = route(n, 0.3)
    odo = odometry(gt, rng)
    found = loops(gt, 0.3, 10.0, rng)
    default = Isam2Params().node_distance
    variants = {
        "partial_check_off": Isam2Params(
            save_map=False, node_distance=0.0, solver=Isam2Solver(partial_relinearization_check=False)
        ),
        "node_distance=0": Isam2Params(save_map=False, node_distance=0.0),
        f"node_distance={default:g}": Isam2Params(save_map=False),
    }
    out: dict[str, list[float]] = {}
    for name, params in variants.items():
        backend = Isam2Backend(params)
        backend.begin(RunContext(run_dir=None))
        cpu = []
        for frame in frames(gt, odo):
            items = found.get(frame.index)
            c0 = time.process_time()
            backend.process(frame=frame, loops=LoopConstraints(tuple(items)) if items else None)
            cpu.append(time.process_time() - c0)
        ms = np.asarray(cpu) * 1e3
        out[name] = [float(ms[k : k + window].mean()) for k in range(0, n, window)]
    return out


def bench_lm(n: int, seed: int, every: float) -> dict[str, float]:
    """Batch LM over n Pose2 keyframes 0.3 m apart (2.7 km at n = 9,000) with loops every ``every`` m.

    ``cold``: from dead reckoning (``solver.every_loop: false``, the worst case at the end of a
    run); ``warm``: the final optimisation of a default run (``solver.every_loop: true``), which
    starts from the estimate of the last loop frame.
    """
    import gtsam

    rng = np.random.default_rng(seed)
    gt = route(n, 0.3)
    odo = odometry(gt, rng)
    found = loops(gt, 0.3, every, rng)
    result: dict[str, float] = {"poses": n, "length_km": n * 0.3 / 1000}
    for mode in ("cold", "warm"):
        backend = GtsamLmBackend(LmParams(save_map=False, solver=LmSolver(every_loop=mode == "warm")))
        backend.begin(RunContext(run_dir=None))
        t0 = time.perf_counter()
        for frame in frames(gt, odo):
            items = found.get(frame.index)
            backend.process(frame=frame, loops=LoopConstraints(tuple(items)) if items else None)
        run_s = time.perf_counter() - t0
        initial = gtsam.Values(backend.graph.values)
        times, cpu = [], []
        for _ in range(3):
            backend.graph.values = gtsam.Values(initial)
            t0, c0 = time.perf_counter(), time.process_time()
            backend.batch_optimize()
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        result[f"lm_{mode}_wall_s"] = statistics.median(times)
        result[f"lm_{mode}_cpu_s"] = statistics.median(cpu)
        if mode == "warm":
            result["run_with_lm_every_loop_s"] = run_s
        result["loops"] = backend.graph.loop_factors
        result[f"ate_{mode}_m"] = ate(backend.graph.store.snapshot().array(), gt)
    result["ate_odometry_m"] = ate(odo, gt)
    return result


class _TimedSolver:
    """An iSAM2 wrapper that adds the CPU time of its updates and full estimates to ``seconds``."""

    def __init__(self, solver: object, seconds: dict[str, float]) -> None:
        self._solver = solver
        self._seconds = seconds

    def _timed(self, name: str, *args: object) -> object:
        c0 = time.process_time()
        out = getattr(self._solver, name)(*args)
        self._seconds[name] = self._seconds.get(name, 0.0) + time.process_time() - c0
        return out

    def update(self, *args: object) -> object:
        return self._timed("update", *args)

    def calculateEstimate(self) -> object:
        return self._timed("calculateEstimate")

    def __getattr__(self, name: str) -> object:
        return getattr(self._solver, name)


def bench_replay(path: str, window: int = 2000, **overrides: object) -> tuple[list[dict[str, float]], np.ndarray]:
    """Replay a recorded soak's back-end input into backend=isam2 (``overrides`` of its parameters).

    Returns, per window of ``window`` frames, the mean CPU ms per frame, split into iSAM2 updates,
    full estimates and the rest (and the window's CPU seconds), and the loops added; and the final trajectory.
    """
    with np.load(path) as data:
        rec = {name: data[name] for name in data.files}
    params = Isam2Params(save_map=False, **overrides)
    backend = Isam2Backend(params)
    backend.begin(RunContext(run_dir=None))
    seconds: dict[str, float] = {}
    by_frame: dict[int, list[LoopConstraint]] = {}
    for k in range(len(rec["loop_at"])):
        by_frame.setdefault(int(rec["loop_at"][k]), []).append(
            LoopConstraint(
                int(rec["loop_from"][k]),
                int(rec["loop_to"][k]),
                rec["loop_relative"][k],
                rec["loop_covariance"][k],
                int(rec["loop_group"][k]),
                bool(rec["loop_reverse"][k]),
                1.0,
                1.0,
            )
        )
    rows: list[dict[str, float]] = []
    total, loops_in_window = 0.0, 0
    for i, index in enumerate(rec["frames"]):
        imu = rec["imu"][i]
        frame = Frame(
            int(index),
            float(rec["timestamps"][i]),
            np.zeros((1, 1), np.uint8),
            rec["odometry"][i],
            CALIBRATION,
            None if np.isnan(imu).any() else (float(imu[0]), float(imu[1])),
        )
        items = by_frame.get(int(index))
        if not isinstance(backend.isam, _TimedSolver):  # a new solver (the run anchored in a map) is wrapped too
            backend.isam = _TimedSolver(backend.isam, seconds)
        c0 = time.process_time()
        backend.process(frame=frame, loops=LoopConstraints(tuple(items)) if items else None)
        total += time.process_time() - c0
        loops_in_window += len(items) if items else 0
        if (i + 1) % window == 0 or i + 1 == len(rec["frames"]):
            count = (i % window) + 1
            update, estimate = seconds.get("update", 0.0), seconds.get("calculateEstimate", 0.0)
            rows.append(
                {
                    "frames": i + 1,
                    "seconds": total,
                    "ms": 1e3 * total / count,
                    "update_ms": 1e3 * update / count,
                    "estimate_ms": 1e3 * estimate / count,
                    "rest_ms": 1e3 * (total - update - estimate) / count,
                    "loops": loops_in_window,
                }
            )
            seconds.clear()
            total, loops_in_window = 0.0, 0
    context = RunContext(run_dir=None)
    backend.finalize(context)
    return rows, context.trajectories["sgf"].poses


def rss_mb() -> float:
    """Current resident memory (MiB)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def bench_memory(n: int, seed: int) -> dict[str, float]:
    """Resident memory per keyframe of backend=isam2 (default config), loop-free, between n/4 and n keyframes.

    The soak (``bench_soak.py``) sees memory grow with the route; this isolates the pose graph's
    share: keyframes 0.3 m apart, a pose node every ``node_distance`` (1 m), all kept for loops to
    any earlier place, and every keyframe's pose in the published estimate.
    """
    rng = np.random.default_rng(seed)
    gt = route(n, 0.3)
    odo = odometry(gt, rng)
    backend = Isam2Backend(Isam2Params(save_map=False))
    backend.begin(RunContext(run_dir=None))
    marks = {}
    for frame in frames(gt, odo):
        backend.process(frame=frame, loops=None)
        if frame.index + 1 in (n // 4, n):
            marks[frame.index + 1] = rss_mb()
    per_node = (marks[n] - marks[n // 4]) * 2**20 / (n - n // 4)
    return {"poses": n, "rss_start_mb": marks[n // 4], "rss_end_mb": marks[n], "bytes_per_keyframe": per_node}


def cpu_model() -> str:
    """The CPU's model name (Linux), or the platform's machine type."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--memory", action="store_true", help="only the memory per keyframe")
    parser.add_argument("--growth", type=int, metavar="N", help="only the update time per window over N keyframes")
    parser.add_argument("--replay", metavar="FILE", help="only a recorded soak's back-end input (bench_soak --record)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="K=V[,K=V]", help="with --replay: also replay with these settings"
    )
    args = parser.parse_args()
    isam_n, lm_n = (3000, 5000) if args.quick else (10_000, 9_000)
    from importlib.metadata import version

    print(
        f"machine: {cpu_model()}, {os.cpu_count()} CPUs, python {platform.python_version()}, gtsam {version('gtsam')}"
    )
    if args.replay:
        reference = None
        for setting in ["", *args.set]:
            overrides = OmegaConf.to_container(OmegaConf.from_dotlist([i for i in setting.split(",") if i]))
            assert isinstance(overrides, dict)
            rows, poses = bench_replay(args.replay, **{str(k): v for k, v in overrides.items()})
            print(
                f"backend=isam2 {setting or '(defaults)'} on {args.replay}: mean CPU ms per frame per window "
                "(update, estimate, rest), loops"
            )
            for row in rows:
                print(
                    f"  {row['frames']:6.0f} {row['ms']:7.2f} ({row['update_ms']:6.2f} {row['estimate_ms']:6.2f} "
                    f"{row['rest_ms']:6.2f}) {row['loops']:4.0f}"
                )
            print(f"  whole replay {sum(r['seconds'] for r in rows):.1f} s CPU")
            if reference is None:
                reference = poses
            else:
                gap = np.linalg.norm(poses[:, :2, 3] - reference[:, :2, 3], axis=1)
                print(f"  final trajectory against the defaults': mean {gap.mean():.3f} m, max {gap.max():.3f} m")
        return
    if args.growth:
        growth = bench_growth(args.growth, args.seed)
        print(
            f"iSAM2 mean CPU ms per keyframe, windows of 2000 keyframes 0.3 m apart (loops every 10 m after lap 1, "
            f"a lap = {round(2 * sum(BLOCK) / 0.3)} keyframes):"
        )
        for name, means in growth.items():
            print(f"  {name:>18}: " + " ".join(f"{m:6.2f}" for m in means))
        return
    memory = bench_memory(5000 if args.quick else 20_000, args.seed)
    print(
        f"memory (backend=isam2, Pose2, no loops): RSS {memory['rss_start_mb']:.0f} MiB after "
        f"{memory['poses'] // 4} keyframes, {memory['rss_end_mb']:.0f} MiB after {memory['poses']}: "
        f"{memory['bytes_per_keyframe']:.0f} bytes per keyframe"
    )
    if args.memory:
        return
    isam = bench_isam2(isam_n, args.seed)
    print(
        "iSAM2 (backend=isam2, Pose2):",
        ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in isam.items()),
    )
    lm = bench_lm(lm_n, args.seed, 37.5)
    print(
        "batch LM (backend=gtsam_lm, Pose2):",
        ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in lm.items()),
    )
    print(
        f"budgets: iSAM2 median update {isam['cpu_median_ms']:.2f} ms CPU, {isam['cpu_median_last_1000_ms']:.2f} ms "
        f"over the last 1,000 of {isam_n} poses (< 10 ms); batch LM from dead reckoning {lm['lm_cold_cpu_s']:.3f} s "
        f"CPU, warm {lm['lm_warm_cpu_s']:.3f} s CPU (< 1 s); load average {os.getloadavg()[0]:.1f} "
        f"on {os.cpu_count()} CPUs"
    )


if __name__ == "__main__":
    main()
