"""Faults: signals, interrupts during the final writes, crashes in finalize, reruns into a directory, sweeps.

A run directory holds a finished run (metrics.json, written last) or the record of one that did
not finish (failure.json and trajectory_*.partial.tum); never a half-written file, never a
finished run silently replaced, never two runs writing into one directory.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from adapters.recordings import calibration, make_frames, write_folder
from sgf_testing import run_cli
from toy_stages import CALIBRATION, ToyPlugin

from sgf_pipeline import ConfigError, Dataset, Pipeline, Stage, StageError, hookimpl, load_plugins
from sgf_pipeline import io as sgf_io
from sgf_pipeline import outputs as sgf_outputs
from sgf_pipeline.context import RunContext
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.reading import READ_DEPTH
from sgf_pipeline.runner import LOCK_FILE
from sgf_pipeline.stage import Settlement
from sgf_pipeline.trajectory import read_tum
from sgf_pipeline.types import Frame

BIN = Path(sys.executable).parent


class FailingFinalize(Stage):
    """Counts frames; raises in finalize."""

    kind = "boom"
    name = "finalize"
    output = "boom"

    def process(self, frame: Frame) -> int:
        return frame.index

    def finalize(self, context: RunContext) -> None:
        raise RuntimeError("cannot save the map")


class AlsoFailingFinalize(FailingFinalize):
    """A second stage failing in finalize."""

    kind = "bang"
    name = "finalize"
    output = "bang"

    def finalize(self, context: RunContext) -> None:
        raise OSError("disk full")


class FailingSettle(FailingFinalize):
    """A stage failing at the end of the run before any stage finalizes."""

    kind = "bang"
    name = "settle"
    output = "bang"

    def settle(self, context: RunContext, settlement: Settlement) -> Settlement:
        raise OSError("disk full")

    def finalize(self, context: RunContext) -> None:
        context.metrics["bang"] = "finalized"


class BrokenDisk(Dataset):
    """Yields four frames, then the disk goes away; frame 2's image cannot be loaded when asked to."""

    name = "broken_disk"

    def frames(self) -> Iterator[Frame]:
        for i in range(10):
            if i == 4:
                raise OSError("Input/output error")
            yield Frame(i, 0.1 * i, lambda: np.zeros((60, 80), np.uint8), pose_from_xy_yaw(0.1 * i, 0, 0), CALIBRATION)


class BadImage(Dataset):
    """Frame 2's image loader has a bug."""

    name = "bad_image"

    def frames(self) -> Iterator[Frame]:
        for i in range(5):

            def load(i: int = i) -> np.ndarray:
                if i == 2:
                    raise ZeroDivisionError("division by zero")
                return np.zeros((60, 80), np.uint8)

            yield Frame(i, 0.1 * i, load, pose_from_xy_yaw(0.1 * i, 0, 0), CALIBRATION)


class InterruptAtTheEnd:
    """An observer interrupted after the run has written everything."""

    @hookimpl
    def sgf_run_end(self, run: Any, metrics: dict[str, Any]) -> None:
        raise KeyboardInterrupt


class FaultPlugin:
    """Registers the stages above."""

    @hookimpl
    def sgf_register_stages(self, registry: Any) -> None:
        for cls in (FailingFinalize, AlsoFailingFinalize, FailingSettle, BrokenDisk, BadImage):
            registry.add(cls)


@pytest.fixture(scope="module")
def plugins():
    return load_plugins(extra=[("toy", ToyPlugin()), ("faults", FaultPlugin())])


def config(frames: int = 20, **stages: Any) -> dict[str, Any]:
    cfg: dict[str, Any] = {
        "pipeline": ["dataset", *stages],
        "dataset": {"name": "figure_eight", "frames": frames},
        "run": {"progress": False},
    }
    cfg.update(stages)
    return cfg


def leftovers(run_dir: Path) -> list[str]:
    """Temporary files of atomic writes left in a directory."""
    return [p.name for p in run_dir.iterdir() if p.name.endswith(".part")]


def complete(run_dir: Path) -> None:
    """Every file the runner wrote parses whole."""
    for path in run_dir.iterdir():
        if path.suffix == ".tum":
            assert len(read_tum(path)) > 0
        elif path.suffix == ".json":
            json.loads(path.read_text())
        elif path.suffix == ".yaml":
            yaml.safe_load(path.read_text())
        elif path.suffix == ".png":
            assert cv2.imread(str(path)) is not None
        elif path.suffix == ".md":
            assert path.read_text().endswith("\n")


# -- interrupts during the final writes ------------------------------------------------------------


@contextlib.contextmanager
def interrupt_on_write(monkeypatch: pytest.MonkeyPatch, k: int, written: list[str]) -> Iterator[None]:
    """Raise KeyboardInterrupt in the k-th atomic write, after its content is written and before its rename."""
    real = sgf_io.atomic_path

    @contextlib.contextmanager
    def flaky(path: Any) -> Iterator[Path]:
        with real(path) as tmp:
            yield tmp
            written.append(Path(path).name)
            if len(written) == k:
                raise KeyboardInterrupt

    monkeypatch.setattr(sgf_io, "atomic_path", flaky)
    monkeypatch.setattr(sgf_outputs, "atomic_path", flaky)
    yield


def test_an_interrupt_during_any_final_write_leaves_whole_files_and_a_record(plugins, tmp_path, monkeypatch):
    cfg = config(backend={"name": "trust_odometry"})
    names: list[str] = []
    with interrupt_on_write(monkeypatch, 0, names):
        Pipeline.from_config(cfg, run_dir=tmp_path / "clean", plugins=plugins).run()
    assert names[-1] == "metrics.json" and len(names) == 7  # three trajectories, config, plot, report, metrics
    for k in range(1, len(names) + 1):
        run_dir = tmp_path / f"cut_{k}"
        written: list[str] = []
        with interrupt_on_write(monkeypatch, k, written), pytest.raises(KeyboardInterrupt):
            Pipeline.from_config(cfg, run_dir=run_dir, plugins=plugins).run()
        assert leftovers(run_dir) == []
        assert not (run_dir / "metrics.json").exists()
        assert not (run_dir / names[k - 1]).exists()  # the interrupted file is not there at all
        failure = json.loads((run_dir / "failure.json").read_text())
        assert failure["status"] == "interrupted" and failure["frames_processed"] == 20
        assert len(read_tum(run_dir / "trajectory_odometry.partial.tum")) == 20
        complete(run_dir)


def test_an_interrupt_after_the_last_write_keeps_the_finished_run(tmp_path: Path):
    loaded = load_plugins(extra=[("toy", ToyPlugin()), ("late", InterruptAtTheEnd())])
    with pytest.raises(KeyboardInterrupt):
        Pipeline.from_config(config(), run_dir=tmp_path, plugins=loaded).run()
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == "finished"
    assert not (tmp_path / "failure.json").exists()


def test_atomic_write_of_a_failing_block_keeps_the_old_file(tmp_path: Path):
    target = tmp_path / "metrics.json"
    target.write_text("old\n")
    with pytest.raises(ValueError, match="half"), sgf_io.atomic_path(target) as tmp:
        tmp.write_text("half of the new")
        raise ValueError("half written")
    assert target.read_text() == "old\n" and leftovers(tmp_path) == []
    sgf_io.atomic_write_text(target, "new\n")
    assert target.read_text() == "new\n" and leftovers(tmp_path) == []


# -- crashes in a stage, in finalize, in the dataset --------------------------------------------------


def test_a_finalize_error_names_the_stage_and_every_stage_still_finalizes(plugins, tmp_path: Path):
    cfg = config(boom={"name": "finalize"}, bang={"name": "finalize"}, backend={"name": "trust_odometry"})
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins)
    kinds = [n.kind for n in pipeline.order]
    assert kinds.index("boom") < kinds.index("backend")  # the backend finalizes after the failure
    with pytest.raises(
        StageError,
        match=r"^stage boom=finalize failed in finalize: RuntimeError: cannot save the map "
        r"\(also failed: bang=finalize in finalize\)$",
    ) as err:
        pipeline.run()
    assert (err.value.kind, err.value.name, err.value.frame_index) == ("boom", "finalize", None)
    failure = json.loads((tmp_path / "failure.json").read_text())
    assert failure["status"] == "failed" and failure["stage"] == "boom=finalize" and failure["frame"] is None
    assert failure["frames_processed"] == 20
    assert len(read_tum(tmp_path / "trajectory_sgf.partial.tum")) == 20  # published by the backend's finalize
    assert len(read_tum(tmp_path / "trajectory_gt.partial.tum")) == 20
    assert not (tmp_path / "metrics.json").exists() and leftovers(tmp_path) == []
    # The lock is released and its file gone; a new run is refused: the failed run's files are kept
    assert not (tmp_path / LOCK_FILE).exists()
    kept = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(kept) == [
        "failure.json",
        "trajectory_gt.partial.tum",
        "trajectory_odometry.partial.tum",
        "trajectory_sgf.partial.tum",
    ]
    with pytest.raises(
        ConfigError,
        match=rf"^{re.escape(str(tmp_path))} holds a run that did not finish \(failure.json, trajectory_gt.partial.tum, "
        r"trajectory_odometry.partial.tum, trajectory_sgf.partial.tum\); its files are kept. Choose another output "
        r"directory \(hydra.run.dir=...\), or pass run.overwrite=true to replace them$",
    ):
        Pipeline.from_config(config(), run_dir=tmp_path, plugins=plugins)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == kept
    # run.overwrite=true replaces the failure record and everything partial
    rerun = config()
    rerun["run"]["overwrite"] = True
    Pipeline.from_config(rerun, run_dir=tmp_path, plugins=plugins).run()
    assert not (tmp_path / "failure.json").exists() and not list(tmp_path.glob("*.partial.tum"))
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == "finished"
    assert not (tmp_path / LOCK_FILE).exists()


def test_a_settle_error_is_reported_first_and_every_stage_still_finalizes(plugins, tmp_path: Path):
    cfg = config(boom={"name": "finalize"}, bang={"name": "settle"}, backend={"name": "trust_odometry"})
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins)
    with pytest.raises(
        StageError,
        match=r"^stage bang=settle failed in settle: OSError: disk full \(also failed: boom=finalize in finalize\)$",
    ):
        pipeline.run()
    assert pipeline.context.metrics["bang"] == "finalized"  # its own finalize ran after its settle failed
    assert json.loads((tmp_path / "failure.json").read_text())["stage"] == "bang=settle"
    assert len(read_tum(tmp_path / "trajectory_sgf.partial.tum")) == 20


def test_a_stage_error_names_stage_and_frame_in_failure_json(plugins, tmp_path: Path):
    with pytest.raises(StageError, match=r"stage explode=on_three failed on frame 3"):
        Pipeline.from_config(config(explode={"name": "on_three"}), run_dir=tmp_path, plugins=plugins).run()
    failure = json.loads((tmp_path / "failure.json").read_text())
    assert (failure["stage"], failure["frame"], failure["error"]) == ("explode=on_three", 3, failure["error"])
    assert failure["error"].startswith("StageError: stage explode=on_three failed on frame 3 (t=0.300 s)")


def test_a_dataset_that_breaks_is_named(plugins, tmp_path: Path):
    cfg: dict[str, Any] = {"pipeline": ["dataset"], "dataset": {"name": "broken_disk"}, "run": {"progress": False}}
    with pytest.raises(StageError, match=r"^dataset dataset=broken_disk failed after 4 frame\(s\): OSError: Input/out"):
        Pipeline.from_config(cfg, run_dir=tmp_path / "a", plugins=plugins).run()
    failure = json.loads((tmp_path / "a" / "failure.json").read_text())
    assert failure["stage"] == "dataset=broken_disk" and failure["frames_processed"] == 4
    cfg["dataset"]["name"] = "bad_image"
    with pytest.raises(StageError, match=r"dataset=bad_image failed to load frame 2 \(t=0.200 s\): ZeroDivisionError"):
        Pipeline.from_config(cfg, run_dir=tmp_path / "b", plugins=plugins).run()
    assert json.loads((tmp_path / "b" / "failure.json").read_text())["frame"] == 2


# -- reruns into a directory ------------------------------------------------------------------------


def test_overwrite_replaces_every_file_of_the_old_run(plugins, tmp_path: Path):
    Pipeline.from_config(config(backend={"name": "trust_odometry"}), run_dir=tmp_path, plugins=plugins).run()
    assert (tmp_path / "trajectory_sgf.tum").exists()
    (tmp_path / "loops.csv").write_text("frame_from,frame_to\n3,9\n")  # as a run with a loop stage leaves it
    before = (tmp_path / "metrics.json").read_bytes()
    with pytest.raises(ConfigError, match=r"already holds a finished run \(metrics.json\)"):
        Pipeline.from_config(config(frames=5), run_dir=tmp_path, plugins=plugins)
    assert (tmp_path / "metrics.json").read_bytes() == before
    rerun = config(frames=5)
    rerun["run"]["overwrite"] = True
    Pipeline.from_config(rerun, run_dir=tmp_path, plugins=plugins).run()
    assert not (tmp_path / "trajectory_sgf.tum").exists()  # the old run's trajectory does not outlive it
    assert not (tmp_path / "loops.csv").exists()  # nor its loop list (this run has no loop stage)
    assert len(read_tum(tmp_path / "trajectory_odometry.tum")) == 5
    assert json.loads((tmp_path / "metrics.json").read_text())["timing"]["frames"] == 5


def test_a_second_run_into_a_directory_in_use_is_refused(plugins, tmp_path: Path):
    first = Pipeline.from_config(config(frames=6), run_dir=tmp_path, plugins=plugins)
    frames = first.frames()
    first.process(next(frames))  # the first run is under way
    second = Pipeline.from_config(config(frames=6), run_dir=tmp_path, plugins=plugins)
    with pytest.raises(
        ConfigError, match=rf"another run \(process {os.getpid()}\) is writing into {re.escape(str(tmp_path))}"
    ):
        second.run()
    for frame in frames:
        first.process(frame)
    assert (tmp_path / LOCK_FILE).read_text().strip() == str(os.getpid())  # the running one's id
    first.finish()
    assert not (tmp_path / LOCK_FILE).exists()  # gone with the run
    with pytest.raises(ConfigError, match=r"already holds a finished run"):
        Pipeline.from_config(config(frames=6), run_dir=tmp_path, plugins=plugins)
    assert not (tmp_path / "failure.json").exists()  # the refused run wrote nothing


# -- signals and concurrent processes -----------------------------------------------------------------


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for_frames(run_dir: Path, proc: subprocess.Popen[str]) -> None:
    """Wait until the toy dataset marks its frame 20 read: with every frame a keyframe, frames went
    through the stages by then (the reading thread holds only a few keyframes ahead)."""
    assert READ_DEPTH + 2 < 20
    deadline = time.time() + 120
    while not (run_dir.parent / f"{run_dir.name}.flowing").exists():
        assert time.time() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.1)


def test_sigint_and_sigterm_leave_a_record_and_exit_130_and_143(toy_plugin_site: Path, tmp_path: Path):
    env = dict(os.environ, PYTHONPATH=str(toy_plugin_site))
    procs = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        run_dir = tmp_path / sig.name
        args = ["pipeline=[dataset,enhance]", "dataset=toy_circle", "dataset.frames=10000000", "enhance=clahe"]
        args.append(f"dataset.mark_file={tmp_path / f'{sig.name}.flowing'}")
        args.append("run.keyframe_distance=0")  # every frame a keyframe: the reading thread's lead bounds the rest
        procs[sig] = (
            run_dir,
            subprocess.Popen(
                [str(BIN / "sgf-run"), *args, "run.progress=false", f"hydra.run.dir={run_dir}"],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                # a test session started in the background inherits an ignored SIGINT; the run must not
                preexec_fn=_default_sigint,
            ),
        )
    for run_dir, proc in procs.values():
        _wait_for_frames(run_dir, proc)
    # A third run into a directory in use is refused while the first one is running.
    run_dir, proc = procs[signal.SIGINT]
    third = run_cli(
        "sgf-run",
        "pipeline=[dataset,enhance]",
        "dataset=toy_circle",
        "enhance=clahe",
        f"hydra.run.dir={run_dir}",
        env={"PYTHONPATH": str(toy_plugin_site)},
    )
    assert third.returncode == 2
    assert re.search(rf"error: another run \(process {proc.pid}\) is writing into .*{run_dir.name}", third.stderr)
    for sig, (_, proc) in procs.items():
        proc.send_signal(sig)
    for sig, (run_dir, proc) in procs.items():
        _, stderr = proc.communicate(timeout=60)
        name = "SIGINT" if sig == signal.SIGINT else "SIGTERM"
        assert proc.returncode == 128 + sig, stderr
        assert f"interrupted ({name}): a run directory being written keeps failure.json" in stderr
        assert "Traceback" not in stderr
        failure = json.loads((run_dir / "failure.json").read_text())
        assert failure["status"] == "interrupted"
        assert failure["error"].startswith("Terminated: signal 15" if name == "SIGTERM" else "KeyboardInterrupt")
        assert len(read_tum(run_dir / "trajectory_odometry.partial.tum")) == failure["frames_processed"] > 0
        assert not (run_dir / "metrics.json").exists() and leftovers(run_dir) == []


class SigtermAfter:
    """Sends this process SIGTERM once the run has processed ``frames`` keyframes."""

    def __init__(self, frames: int) -> None:
        self.frames = frames

    @hookimpl
    def sgf_frame_end(self, run: Any, frame: Frame, seconds: float) -> None:
        if run.frames_processed == self.frames:
            os.kill(os.getpid(), signal.SIGTERM)


@pytest.mark.slow
def test_sigterm_keeps_the_pose_estimate_and_the_sgf_map_so_far(tmp_path: Path):
    """The main job stopped by SIGTERM after 100 keyframes: the back-end's estimate and the SGF map so far are
    kept beside the partial odometry and ground truth, as sgf-run's handler turns the signal into an interrupt."""
    from hydra import compose, initialize_config_dir

    from sgf_pipeline.cli.common import Terminated, raise_terminated
    from sgf_pipeline.config import config_dir
    from sgf_pipeline.sgf_map import load_map

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["run.progress=false"])
    plugins = load_plugins(extra=[("stop", SigtermAfter(100))])
    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        with pytest.raises(Terminated):
            Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins).run()
    finally:
        signal.signal(signal.SIGTERM, previous)
    failure = json.loads((tmp_path / "failure.json").read_text())
    assert failure["status"] == "interrupted" and failure["frames_processed"] == 100
    sgf = read_tum(tmp_path / "trajectory_sgf.partial.tum")
    odometry = read_tum(tmp_path / "trajectory_odometry.partial.tum")
    truth = read_tum(tmp_path / "trajectory_gt.partial.tum")
    assert len(sgf) == len(odometry) == len(truth) == 100
    np.testing.assert_array_equal(sgf.timestamps, odometry.timestamps)
    # the back-end's estimate, not the odometry: its scale factor (measured over the first metres) is applied
    assert float(np.abs(sgf.positions - odometry.positions).max()) > 0.01
    sgf_map = load_map(tmp_path / "sgf_map.partial.safetensors")
    assert len(sgf_map.groups) >= 1 and len(sgf_map.views) >= 1
    for view in sgf_map.views:  # each view seen from the pose the estimate had for its frame (TUM: 9 decimals)
        row = int(np.argmin(np.abs(sgf.timestamps - view.timestamp)))
        assert abs(sgf.timestamps[row] - view.timestamp) < 1e-6
        np.testing.assert_allclose(view.pose, sgf.poses[row], atol=1e-6)
    assert not (tmp_path / "metrics.json").exists() and leftovers(tmp_path) == []
    # a new run into the directory is refused; with run.overwrite=true it replaces the record and everything partial
    with pytest.raises(
        ConfigError,
        match=r"holds a run that did not finish \(failure.json, sgf_map.partial.safetensors, trajectory_gt.partial.tum, "
        r"trajectory_odometry.partial.tum and 1 more\); its files are kept",
    ):
        Pipeline.from_config(config(frames=5), run_dir=tmp_path, plugins=load_plugins(extra=[("toy", ToyPlugin())]))
    assert json.loads((tmp_path / "failure.json").read_text())["frames_processed"] == 100
    overwrite = config(frames=5)
    overwrite["run"]["overwrite"] = True
    rerun = Pipeline.from_config(overwrite, run_dir=tmp_path, plugins=load_plugins(extra=[("toy", ToyPlugin())]))
    rerun.run()
    assert not list(tmp_path.glob("*.partial.*")) and not (tmp_path / "failure.json").exists()


def test_two_runs_started_together_get_two_directories(tmp_path: Path):
    folder = write_folder(tmp_path / "seq", make_frames(2, seed=2), calibration())
    args = ["dataset=folder", f"dataset.path={folder}", "pipeline=[dataset]", "run.progress=false", "run.plots=false"]
    procs = [
        subprocess.Popen([str(BIN / "sgf-run"), *args], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for _ in range(2)
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
    runs = sorted((tmp_path / "outputs" / "runs").iterdir())
    assert len(runs) == 2
    for run in runs:
        assert re.fullmatch(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d_\d{6}", run.name)
        assert json.loads((run / "metrics.json").read_text())["status"] == "finished"


def test_a_sweep_with_one_failing_job_runs_the_others_and_names_the_failure(tmp_path: Path):
    folder = write_folder(tmp_path / "seq", make_frames(4, seed=3), calibration())
    image = folder / "images" / "000001.png"
    image.write_bytes(image.read_bytes()[:200])
    sweep = tmp_path / "sweep"
    result = run_cli(
        "sgf-run",
        "-m",
        "dataset=folder",
        f"dataset.path={folder}",
        "dataset.strict=true,false",
        "pipeline=[dataset,enhance]",
        "run.progress=false",
        "run.plots=false",
        f"hydra.sweep.dir={sweep}",
    )
    output = result.stdout + result.stderr
    assert result.returncode == 2, output
    assert re.search(
        r"job 0 \(dataset=folder .*dataset.strict=True .*\) in \S*sweep/\S*strict=True\S* failed: dataset=folder: frame 1",
        output,
    )
    assert "error: dataset=folder: frame 1 (000001.png): image" in result.stderr and "Traceback" not in output
    jobs = {p.name: p for p in sweep.iterdir() if p.is_dir()}  # named by their overrides
    (failed,) = [p for name, p in jobs.items() if "dataset.strict=True" in name]
    (finished,) = [p for name, p in jobs.items() if "dataset.strict=False" in name]
    failure = json.loads((failed / "failure.json").read_text())
    assert failure["status"] == "failed" and "the PNG has no end chunk (truncated)" in failure["error"]
    assert failure["frames_processed"] == 1 and not (failed / "metrics.json").exists()
    metrics = json.loads((finished / "metrics.json").read_text())
    assert metrics["dataset"]["skipped_by_reason"] == {"bad image": 1} and metrics["timing"]["frames"] == 3
