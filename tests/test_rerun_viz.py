"""viz=rerun: the Rerun recording of a run, read back with Rerun's own reader (``rerun.chunk.RrdReader``)."""

from __future__ import annotations

import csv
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from adapters.recordings import calibration, make_frames, rosbag_overrides, write_bag, write_folder
from adapters.test_euroc_dataset import make_euroc
from hydra import compose, initialize_config_dir
from toy_stages import ToyPlugin

from sgf_pipeline import ConfigError, Pipeline, StageError, hookimpl, load_plugins
from sgf_pipeline.config import config_dir
from sgf_pipeline.sgf_map import load_map
from sgf_pipeline.trajectory import read_tum

if os.environ.get("CI") == "true":
    import rerun  # noqa: F401  (scripts/setup.sh --dev installs it: under CI a missing SDK fails)
else:
    pytest.importorskip("rerun")

from sgf_plugins.loop.outcomes import OUTCOMES
from sgf_plugins.viz.rerun.drawing import OUTCOME_COLOURS, nanoseconds, outcome_colour
from sgf_plugins.viz.rerun.options import PARTIAL_RECORDING, RECORDING

BIN = Path(sys.executable).parent
#: The main job, short: a tenth of campus_delivery (220 keyframes, loops accepted and refused), a
#: quarter of its camera's pixels and the classical saliency, so that the test takes seconds.
CAMPUS = [
    "dataset.scale=0.1",
    "dataset.width=320",
    "dataset.height=240",
    "dataset.fx=200",
    "dataset.fy=200",
    "saliency=classical",
    "run.progress=false",
    "run.plots=false",
]


def compose_config(overrides: list[str]) -> Any:
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=overrides)


def read(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every entity's rows: static ones first, then in (frame, logging) order; ``time`` in ns, ``clock`` its type."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        clock = batch.column(names.index("time")) if "time" in names else None
        times = None if clock is None else clock.cast(pa.int64()).to_pylist()
        for k, row in enumerate(batch.drop_columns([n for n in ("time",) if n in names]).to_pylist()):
            row["static"] = chunk.is_static
            row["time"] = None if times is None else times[k]
            row["clock"] = None if clock is None else str(clock.type)
            rows[chunk.entity_path].append(row)
    for entity in rows.values():
        entity.sort(key=lambda r: (not r["static"], r.get("frame") or 0, r["rerun.controls.RowId"]))
    return rows


def temporal(rows: dict[str, list[dict[str, Any]]], entity: str) -> list[dict[str, Any]]:
    return [r for r in rows[entity] if not r["static"]]


def last_vertices(rows: list[dict[str, Any]], component: str) -> np.ndarray:
    """The last vertex of each row's one strip (a trajectory drawn a segment per keyframe)."""
    return np.array([r[component][0][-1] for r in rows], dtype=np.float64)


def float32_tolerance(values: np.ndarray) -> float:
    """Rerun keeps positions as float32: half a unit in the last place of the largest, plus the TUM file's 1e-9."""
    return float(np.abs(values).max()) * 2.0**-24 + 1e-9


@pytest.fixture(scope="module")
def campus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The short main job through the library API (``Pipeline.process``), recording on; what it saw and wrote."""
    run_dir = tmp_path_factory.mktemp("campus") / "run"
    pipeline = Pipeline.from_config(compose_config(["viz=rerun", *CAMPUS]), run_dir=run_dir)
    seen: dict[int, dict[str, Any]] = {}
    for frame in pipeline.frames():
        step = pipeline.process(frame)
        bev = step.outputs["bev"]
        seen[frame.index] = {"image": step.outputs["image"].pixels, "bev": bev.image}
    metrics = pipeline.finish()
    return {"dir": run_dir, "seen": seen, "metrics": metrics, "rows": read(run_dir / RECORDING)}


def test_the_recording_is_written_to_run_rrd_with_its_entities(campus: dict[str, Any]) -> None:
    run_dir, rows = campus["dir"], campus["rows"]
    assert (run_dir / RECORDING).is_file() and not (run_dir / PARTIAL_RECORDING).exists()
    stages = set(campus["metrics"]["stages"]) - {"dataset"}
    expected = {
        "/camera/image",
        "/bev/image",
        "/bev/saliency",
        "/bev/sgfs",
        "/sgf/descriptor",
        "/log/sgfs",
        "/log/loops",
        "/world",
        *(f"/{root}/{name}" for root in ("map", "world") for name in ("odometry", "ground_truth", "correction")),
        *(f"/{root}/estimate/{part}" for root in ("map", "world") for part in ("path", "recent")),
        "/map/robot",
        *(f"/timing/{kind}" for kind in stages),
    }
    candidates = list(csv.DictReader((run_dir / "loop_candidates.csv").open()))
    expected |= {f"/{root}/loops/{k}" for root in ("map", "world") for k in range(len(candidates))}
    assert expected <= set(rows)
    unexpected = {e for e in rows if e not in expected and not e.startswith("/__")}
    assert not unexpected


def test_one_jpeg_image_per_keyframe_on_both_timelines(campus: dict[str, Any]) -> None:
    rows, seen = campus["rows"], campus["seen"]
    odometry = read_tum(campus["dir"] / "trajectory_odometry.tum")
    keyframes = sorted(seen)
    assert len(keyframes) == len(odometry) == campus["metrics"]["timing"]["frames"] > 100
    for entity in ("/camera/image", "/bev/image", "/bev/saliency"):
        images = temporal(rows, entity)
        assert [r["frame"] for r in images] == keyframes, entity  # one per keyframe, in order
        # the time timeline holds each keyframe's stamp, in whole nanoseconds
        assert [r["time"] for r in images] == [nanoseconds(t) for t in odometry.timestamps]
    assert {r["EncodedImage:media_type"][0] for r in temporal(rows, "/camera/image")} == {"image/jpeg"}
    assert rows["/bev/saliency"][0]["static"] and rows["/bev/saliency"][0]["EncodedImage:media_type"] == ["image/jpeg"]

    def decoded(row: dict[str, Any]) -> np.ndarray:
        image = cv2.imdecode(np.frombuffer(bytes(row["EncodedImage:blob"][0]), np.uint8), cv2.IMREAD_UNCHANGED)
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if image.ndim == 3 else image

    cameras = temporal(rows, "/camera/image")
    bevs = temporal(rows, "/bev/image")
    for k in range(1, len(keyframes), 25):
        own, other = seen[keyframes[k]], seen[keyframes[k - 1]]
        for row, key in ((cameras[k], "image"), (bevs[k], "bev")):
            image = decoded(row).astype(float)
            assert image.shape == own[key].shape  # the BEV at its own resolution, the camera at its own
            # lossy, but the keyframe's own image and not its neighbour's
            assert np.abs(image - own[key]).mean() < np.abs(image - other[key].astype(float)).mean()


def test_trajectories_equal_the_tum_files(campus: dict[str, Any]) -> None:
    rows, run_dir = campus["rows"], campus["dir"]
    for name, tum in (("odometry", "odometry"), ("ground_truth", "gt")):
        trajectory = read_tum(run_dir / f"trajectory_{tum}.tum")
        world = temporal(rows, f"/world/{name}")
        flat = temporal(rows, f"/map/{name}")
        assert [r["time"] for r in world] == [nanoseconds(t) for t in trajectory.timestamps]
        xyz = trajectory.positions
        tolerance = float32_tolerance(xyz)
        np.testing.assert_allclose(last_vertices(world, "LineStrips3D:strips"), xyz, rtol=0, atol=tolerance)
        np.testing.assert_allclose(last_vertices(flat, "LineStrips2D:strips"), xyz[:, :2] * [1, -1], atol=tolerance)
        # each segment starts where the one before ended
        starts = np.array([r["LineStrips3D:strips"][0][0] for r in world[1:]])
        np.testing.assert_array_equal(starts, last_vertices(world[:-1], "LineStrips3D:strips"))
    # the estimate's last state (one frame after the last keyframe) is the final trajectory
    final = read_tum(run_dir / "trajectory_sgf.tum")
    last = max(campus["seen"])
    for entity, component, flip in (
        ("/world/estimate/path", "LineStrips3D:strips", [1, 1, 1]),
        ("/map/estimate/path", "LineStrips2D:strips", [1, -1]),
    ):
        row = temporal(rows, entity)[-1]
        assert row["frame"] == last + 1
        path = np.array(row[component][0], dtype=np.float64)
        expected = final.positions[:, : len(flip)] * flip
        np.testing.assert_allclose(path, expected, rtol=0, atol=float32_tolerance(expected))
        assert temporal(rows, entity.replace("path", "recent"))[-1][component] == []


def test_loop_candidates_equal_loop_candidates_csv(campus: dict[str, Any]) -> None:
    rows = campus["rows"]
    candidates = list(csv.DictReader((campus["dir"] / "loop_candidates.csv").open()))
    outcomes = {c["outcome"] for c in candidates}
    assert "accepted" in outcomes and len(outcomes) >= 2  # the run accepts some and refuses others
    for k, row in enumerate(candidates):
        label = row["outcome"] + (f": {row['detail']}" if row["detail"] else "")
        for root, component in (("map", "LineStrips2D"), ("world", "LineStrips3D")):
            drawn = [r for r in temporal(rows, f"/{root}/loops/{k}") if r.get(f"{component}:strips") is not None]
            latest = drawn[-1]
            assert latest[f"{component}:labels"] == [label]
            colour = latest[f"{component}:colors"][0]
            assert colour >> 8 == int.from_bytes(bytes(outcome_colour(row["outcome"])), "big")
            strip = np.array(latest[f"{component}:strips"][0])
            assert strip.shape == (2, 2 if root == "map" else 3)  # a line between the candidate's two poses
            assert drawn[0]["frame"] >= int(row["frame_to"])  # decided once its newer view was seen
    texts = [r["TextLog:text"][0] for r in temporal(rows, "/log/loops")]
    for row in candidates:  # the log says the same, the outcome as its level
        said = f"frame {row['frame_from']} -> {row['frame_to']}, group {row['group_id']}: {row['outcome']}"
        assert any(t.startswith(said) for t in texts), said
    levels = {r["TextLog:level"][0] for r in temporal(rows, "/log/loops")}
    assert outcomes <= levels


def test_every_loop_outcome_has_a_colour_of_its_own() -> None:
    assert set(OUTCOME_COLOURS) == set(OUTCOMES)
    assert len(set(OUTCOME_COLOURS.values())) == len(OUTCOMES)


def test_stage_times_sum_to_the_metrics(campus: dict[str, Any]) -> None:
    rows, stages = campus["rows"], campus["metrics"]["timing"]["stages"]
    for kind, timing in stages.items():
        logged = [r["Scalars:scalars"][0] for r in temporal(rows, f"/timing/{kind}")]
        assert len(logged) == timing["calls"]
        # the same seconds as the timing observer's, which rounds its total to 0.1 ms
        assert sum(logged) / 1000.0 == pytest.approx(timing["total_s"], abs=5e-5 + 1e-9 * len(logged))


def test_sgfs_outlines_and_descriptors_are_those_of_the_map(campus: dict[str, Any]) -> None:
    rows = campus["rows"]
    sgf_map = load_map(campus["dir"] / "sgf_map.safetensors")
    views = {(v.frame_index, v.track_id): v for v in sgf_map.views}
    descriptors = temporal(rows, "/sgf/descriptor")
    assert descriptors
    for row in descriptors:
        view = views[(row["sgf_frame"][0], row["sgf_track"][0])]
        data = row["Tensor:data"][0]
        assert data["shape"] == list(view.matrix.shape) and data["names"] == ["ring", "sector"]
        np.testing.assert_array_equal(
            np.array(data["buffer"]).reshape(view.matrix.shape), view.matrix.astype(np.float32)
        )
    outlined = temporal(rows, "/bev/sgfs")
    times = {r["frame"]: r["time"] for r in temporal(rows, "/camera/image")}
    # each SGF outlined once, on the BEV of the frame it was selected from, labelled with its track
    assert sorted(r["frame"] for r in outlined) == sorted(f for f, _ in views)
    for r in outlined:
        tracks = {int(label.split()[1]) for label in r["LineStrips2D:labels"]}
        assert len(tracks) == 1 and (r["frame"], tracks.pop()) in views
        assert r["time"] == times[r["frame"]]
        strips = [np.array(s) for s in r["LineStrips2D:strips"]]
        assert all(np.array_equal(s[0], s[-1]) and s.min() >= 0.0 and s.max() <= 256.0 for s in strips)


def test_the_blueprint_lays_out_the_views(campus: dict[str, Any]) -> None:
    from rerun.chunk import RrdReader

    reader = RrdReader(campus["dir"] / RECORDING)
    (blueprint,) = reader.blueprints()
    views = {}
    for chunk in reader.stream(store=blueprint).to_chunks():
        for row in chunk.to_record_batch().to_pylist():
            if row.get("ViewBlueprint:class_identifier"):
                views[row["ViewBlueprint:space_origin"][0]] = row["ViewBlueprint:class_identifier"][0]
    assert views == {
        "camera": "2D",
        "bev": "2D",
        "sgf/descriptor": "Tensor",
        "map": "2D",
        "world": "3D",
        "timing": "TimeSeries",
        "log": "TextLog",
    }


def adapter(kind: str, root: Path, shared_data: Path) -> list[str]:
    """Overrides that read a recording of each dataset adapter (synthetic ones written into ``root``)."""
    if kind == "kitti":  # 51 real frames of KITTI 00 (grey); its camera, 1.65 m up, sees the road from 6.2 m on
        region = ["ipm.resolution=0.04", "ipm.x_min=6.5", "ipm.x_max=12.5", "ipm.y_min=-3.0", "ipm.y_max=4.2"]
        return ["dataset=kitti", f"dataset.path={shared_data / 'kitti_clip51'}", *region]
    if kind == "euroc":  # grey images, Unix time in ns, the ground truth as odometry
        return ["dataset=euroc", f"dataset.path={make_euroc(root / 'euroc')}", "dataset.camera_height=0.6"]
    frames = make_frames(12, seed=7)
    if kind == "rosbag":  # a ROS 2 bag (MCAP), Unix time
        bag = write_bag(root / "bag", frames, calibration(), "ros2_mcap", "rgb8", "transform")
        return rosbag_overrides(bag)
    return ["dataset=folder", f"dataset.path={write_folder(root / 'seq', frames, calibration())}"]


@pytest.mark.parametrize("kind", ["folder", "rosbag", "kitti", "euroc"])
def test_every_dataset_adapter_is_recorded(kind: str, tmp_path: Path, shared_data: Path) -> None:
    overrides = [*adapter(kind, tmp_path, shared_data), "viz=rerun", "saliency=classical"]
    overrides += ["run.keyframe_distance=0", "run.progress=false", "run.plots=false"]  # every frame
    pipeline = Pipeline.from_config(compose_config(overrides), run_dir=tmp_path / "run")
    images = {}
    for frame in pipeline.frames():
        images[frame.index] = pipeline.process(frame).outputs["image"].pixels
    pipeline.finish()
    rows = read(tmp_path / "run" / RECORDING)
    odometry = read_tum(tmp_path / "run" / "trajectory_odometry.tum")
    cameras = temporal(rows, "/camera/image")
    assert [r["frame"] for r in cameras] == sorted(images) and len(images) == len(odometry) >= 5
    unix = odometry.timestamps[0] > 1e9  # a bag's or EuRoC's clock: shown as dates
    assert {r["clock"] for r in cameras} == {"timestamp[ns]" if unix else "duration[ns]"}
    # whole nanoseconds of the stamps, as close as the TUM file's float seconds can say
    slack = 2e9 * np.spacing(odometry.timestamps) + 1.0
    assert np.all(np.abs(np.array([r["time"] for r in cameras]) - odometry.timestamps * 1e9) <= slack)
    for row, (index, image) in zip(cameras, sorted(images.items()), strict=True):
        decoded = cv2.imdecode(np.frombuffer(bytes(row["EncodedImage:blob"][0]), np.uint8), cv2.IMREAD_UNCHANGED)
        assert decoded.shape == image.shape, index  # grey stays grey, at the camera's own size
    world = temporal(rows, "/world/odometry")
    xyz = odometry.positions
    np.testing.assert_allclose(last_vertices(world, "LineStrips3D:strips"), xyz, atol=float32_tolerance(xyz))
    truth = tmp_path / "run" / "trajectory_gt.tum"
    assert ("/world/ground_truth" in rows) == truth.is_file()
    assert (tmp_path / "run" / "trajectory_sgf.tum").is_file() and "/map/estimate/path" in rows


def test_a_run_without_the_recording_writes_none(tmp_path: Path) -> None:
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    config = {"pipeline": ["dataset"], "dataset": {"name": "figure_eight", "frames": 5}, "run": {"progress": False}}
    Pipeline.from_config(config, run_dir=tmp_path / "off", plugins=plugins).run()
    assert not list((tmp_path / "off").glob("*.rrd"))


def toy(frames: int = 12, **viz: Any) -> dict[str, Any]:
    return {
        "pipeline": ["dataset", "backend"],
        "dataset": {"name": "figure_eight", "frames": frames},
        "backend": {"name": "trust_odometry"},
        "viz": {"name": "rerun", **viz},
        "run": {"progress": False, "plots": False},
    }


def test_a_minimal_pipeline_records_the_dataset_images(tmp_path: Path) -> None:
    # no enhance, IPM or saliency: the camera image is the dataset's (grey), the rest is left out
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    Pipeline.from_config(toy(), run_dir=tmp_path / "run", plugins=plugins).run()
    rows = read(tmp_path / "run" / RECORDING)
    images = temporal(rows, "/camera/image")
    assert [r["frame"] for r in images] == list(range(12))
    for k, row in enumerate(images):  # the figure eight's images are flat: grey level k
        image = cv2.imdecode(np.frombuffer(bytes(row["EncodedImage:blob"][0]), np.uint8), cv2.IMREAD_UNCHANGED)
        assert image.shape == (60, 80) and np.abs(image.astype(int) - k).max() <= 1
    assert "/bev/image" not in rows and "/sgf/descriptor" not in rows
    final = read_tum(tmp_path / "run" / "trajectory_sgf.tum")
    path = np.array(temporal(rows, "/world/estimate/path")[-1]["LineStrips3D:strips"][0])
    np.testing.assert_allclose(path, final.positions, atol=float32_tolerance(final.positions))


def test_a_failed_run_keeps_its_partial_recording(tmp_path: Path) -> None:
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    config = toy()
    config["pipeline"] = ["dataset", "explode"]
    config["explode"] = {"name": "on_three"}
    with pytest.raises(StageError, match="kaboom"):
        Pipeline.from_config(config, run_dir=tmp_path / "run", plugins=plugins).run()
    assert not (tmp_path / "run" / RECORDING).exists()
    rows = read(tmp_path / "run" / PARTIAL_RECORDING)  # complete up to the failure
    assert [r["frame"] for r in temporal(rows, "/camera/image")] == [0, 1, 2]


def test_an_overwritten_run_loses_its_old_recording(tmp_path: Path) -> None:
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    Pipeline.from_config(toy(), run_dir=tmp_path / "run", plugins=plugins).run()
    assert (tmp_path / "run" / RECORDING).is_file()
    again = toy()
    del again["viz"]
    again["run"]["overwrite"] = True
    Pipeline.from_config(again, run_dir=tmp_path / "run", plugins=plugins).run()
    assert not (tmp_path / "run" / RECORDING).exists()


def test_without_a_run_directory_a_viewer_is_needed(tmp_path: Path) -> None:
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    pipeline = Pipeline.from_config(toy(), plugins=plugins)
    with pytest.raises(ConfigError, match=r"nowhere to send the recording.*viz\.spawn"):
        pipeline.begin()


@pytest.mark.parametrize(
    ("viz", "message"),
    [
        ({"spawn": True, "serve": True}, "choose one of them"),
        ({"connect": "http://localhost:9876"}, "host:port or a rerun://"),
        ({"colour": "red"}, "unknown parameter"),
    ],
)
def test_bad_options_are_refused_before_the_first_frame(viz: dict[str, Any], message: str) -> None:
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    with pytest.raises(ConfigError, match=message):
        Pipeline.from_config(toy(**viz), plugins=plugins)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # the viewer's server saves a stream as it comes
def test_connect_streams_to_a_running_viewer(tmp_path: Path) -> None:
    port = free_port()
    received = tmp_path / "received.rrd"
    server = subprocess.Popen(
        [str(BIN / "rerun"), "--serve-grpc", "--bind", "127.0.0.1", "--port", str(port), "--save", str(received)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # the `rerun` script's child (the server) is stopped with it
    )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # wait until it listens
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.2)
        plugins = load_plugins(extra=[("toy", ToyPlugin())])
        config = toy(save=False, connect=f"127.0.0.1:{port}")
        Pipeline.from_config(config, run_dir=tmp_path / "run", plugins=plugins).run()
        assert not list((tmp_path / "run").glob("*.rrd"))  # viz.save=false
        deadline = time.monotonic() + 60  # the server writes what it received as it comes: wait for all of it
        while time.monotonic() < deadline and _images_saved(received) < 12:
            time.sleep(0.5)
    finally:
        os.killpg(server.pid, signal.SIGINT)  # the viewer's server finishes its file on Ctrl-C
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:  # it may hang on Ctrl-C: the file holds what it received without a footer
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(timeout=30)
    rows = read(received)
    assert [r["frame"] for r in temporal(rows, "/camera/image")] == list(range(12))


def _images_saved(path: Path) -> int:
    """Camera images in a recording the viewer's server is still writing (0 while it cannot be read yet)."""
    if not path.exists():
        return 0
    try:
        return len(temporal(read(path), "/camera/image"))
    except Exception:  # a chunk half written
        return 0


class _FetchWebViewer:
    """A test observer that fetches the served web viewer's page while the run lasts."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.page = ""

    @hookimpl
    def sgf_frame_end(self, run: Any, frame: Any, seconds: float) -> None:
        if frame.index == 5:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/", timeout=30) as response:
                self.page = response.read().decode("utf-8", "replace")


def test_serve_serves_the_web_viewer_while_the_run_lasts(tmp_path: Path) -> None:
    web, grpc = free_port(), free_port()
    fetch = _FetchWebViewer(web)
    plugins = load_plugins(extra=[("toy", ToyPlugin()), ("fetch", fetch)])
    config = toy(serve=True, web_port=web, grpc_port=grpc)
    Pipeline.from_config(config, run_dir=tmp_path / "run", plugins=plugins).run()
    assert "<html" in fetch.page.lower() and "rerun" in fetch.page.lower()
    assert (tmp_path / "run" / RECORDING).is_file()  # saved as well


def test_without_rerun_sdk_viz_rerun_says_how_to_install_it(tmp_path: Path) -> None:
    hide = (
        "import importlib.metadata as m, sys\n"
        "version = m.version\n"
        "def hidden(name):\n"
        "    if name == 'rerun-sdk':\n"
        "        raise m.PackageNotFoundError(name)\n"
        "    return version(name)\n"
        "m.version = hidden\n"
        "from sgf_pipeline.cli.run import main\n"
        "sys.argv[0] = 'sgf-run'\n"
        "main()\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", hide, "viz=rerun", *CAMPUS, f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr
    message = proc.stderr.strip()
    assert message.startswith("error:") and "\n\n" not in message and "Traceback" not in message
    assert "rerun-sdk" in message and "pip install 'sgf-pipeline[viz]'" in message
    assert not (tmp_path / "run" / "metrics.json").exists()
