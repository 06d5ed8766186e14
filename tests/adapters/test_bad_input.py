"""Bad recordings give clear errors (strict) or counted, logged skips (strict: false); inputs stay untouched."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from sgf_plugins.datasets.euroc import EurocDataset, EurocParams
from sgf_plugins.datasets.folder import FolderDataset, FolderParams
from sgf_plugins.datasets.kitti import KittiDataset, KittiParams
from sgf_plugins.datasets.rosbag import RosbagDataset, RosbagParams

from sgf_pipeline import ConfigError, DataError, Pipeline
from sgf_pipeline.config import config_dir
from sgf_pipeline.context import RunContext

from .recordings import HEIGHT_M, TILT, calibration, make_frames, rosbag_overrides, write_bag, write_folder
from .test_euroc_dataset import make_euroc


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    return write_folder(tmp_path / "seq", make_frames(10, seed=2), calibration())


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _write_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n")


def _run(overrides: list[str], run_dir: Path) -> dict:  # type: ignore[type-arg]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*overrides, "pipeline=[dataset,enhance]", "run.progress=false"])
    Pipeline.from_config(cfg, run_dir=run_dir).run()
    return json.loads((run_dir / "metrics.json").read_text())


# -- folder -----------------------------------------------------------------------------------


def test_folder_missing_file_lists_what_is_there(folder: Path):
    (folder / "timestamps.txt").unlink()
    with pytest.raises(
        DataError, match=r"has no timestamps.txt, which the folder format requires; .* holds: .*images/"
    ):
        FolderDataset(FolderParams(path=str(folder)))
    with pytest.raises(DataError, match=r"does not exist \(.* holds: seq/\)"):
        FolderDataset(FolderParams(path=str(folder.parent / "nope")))
    with pytest.raises(DataError, match=r"needs the sequence folder: dataset\.path=<folder>"):
        FolderDataset(FolderParams())


def test_folder_mismatched_lengths(folder: Path):
    _write_lines(folder / "timestamps.txt", [*_lines(folder / "timestamps.txt"), "1700000009.0"])
    with pytest.raises(DataError, match=r"timestamps.txt has 11 timestamps but images/ holds 10 images"):
        FolderDataset(FolderParams(path=str(folder)))
    (folder / "images" / "000009.png").unlink()
    with pytest.raises(DataError, match=r"sequence.yaml says frames: 10 but images/ holds 9 images"):
        FolderDataset(FolderParams(path=str(folder)))


@pytest.mark.parametrize(("kind", "row"), [("timestamp out of order", 4), ("duplicated timestamp", 4)])
def test_folder_unsorted_or_duplicated_timestamps(folder: Path, tmp_path: Path, kind: str, row: int):
    stamps, odometry = _lines(folder / "timestamps.txt"), _lines(folder / "odometry.tum")
    previous = stamps[row - 1] if kind == "duplicated timestamp" else stamps[row - 2]
    stamps[row] = previous
    odometry[row] = " ".join([previous, *odometry[row].split()[1:]])
    _write_lines(folder / "timestamps.txt", stamps)
    _write_lines(folder / "odometry.tum", odometry)
    (folder / "imu.csv").unlink()
    with pytest.raises(DataError, match=r"image 4 \(000004.png\) at t=.* is not after t=.*set dataset.strict=false"):
        FolderDataset(FolderParams(path=str(folder)))
    metrics = _run(["dataset=folder", f"dataset.path={folder}", "dataset.strict=false"], tmp_path / "run")
    assert metrics["dataset"]["skipped"] == 1
    assert metrics["dataset"]["skipped_by_reason"] == {kind: 1}
    assert metrics["dataset"]["frames"] == 9


def test_folder_nan_pose(folder: Path):
    odometry = _lines(folder / "odometry.tum")
    fields = odometry[3].split()
    odometry[3] = " ".join([fields[0], "nan", *fields[2:]])
    _write_lines(folder / "odometry.tum", odometry)
    with pytest.raises(DataError, match=r"odometry.tum: pose 3 is not finite \(NaN or inf\)"):
        FolderDataset(FolderParams(path=str(folder)))
    dataset = FolderDataset(FolderParams(path=str(folder), strict=False))
    assert [f.index for f in dataset.frames()] == [0, 1, 2, 4, 5, 6, 7, 8, 9]
    assert dataset.skips.counts == {"bad pose": 1}


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda data: data[: len(data) // 2], "the PNG has no end chunk \\(truncated\\)"),
        (lambda data: data[:40] + b"\x00" * (len(data) - 52) + data[-12:], "cannot decode the image"),
        (lambda data: b"", "the file is empty"),
    ],
)
def test_folder_corrupt_or_truncated_image(folder: Path, tmp_path: Path, damage, message: str):  # type: ignore[no-untyped-def]
    image = folder / "images" / "000006.png"
    image.write_bytes(damage(image.read_bytes()))
    frames = list(FolderDataset(FolderParams(path=str(folder))).frames())
    assert frames[5].image.shape == (120, 160, 3)  # the others decode
    with pytest.raises(DataError, match=rf"frame 6 \(000006.png\): image .*000006.png: {message}"):
        _ = frames[6].image
    before = _snapshot(folder)
    metrics = _run(["dataset=folder", f"dataset.path={folder}", "dataset.strict=false"], tmp_path / "run")
    assert metrics["dataset"] == {"name": "folder", "frames": 9, "skipped": 1, "skipped_by_reason": {"bad image": 1}}
    assert metrics["timing"]["dataset_frames"] == 9
    assert _snapshot(folder) == before  # nothing written into the input


def test_folder_bad_calibration_and_format(folder: Path):
    (folder / "sequence.yaml").write_text("format: kitti\nversion: 1\n")
    with pytest.raises(DataError, match="format is 'kitti', not 'sgf-folder'"):
        FolderDataset(FolderParams(path=str(folder)))
    (folder / "sequence.yaml").unlink()
    (folder / "calibration.yaml").write_text("intrinsics: {fx: -1}\n")
    with pytest.raises(DataError, match=r"calibration\.yaml: invalid calibration"):
        FolderDataset(FolderParams(path=str(folder)))


# -- KITTI ------------------------------------------------------------------------------------


def test_kitti_missing_calibration_and_mismatched_times(shared_data: Path, tmp_path: Path):
    src = shared_data / "kitti00_first6"
    with pytest.raises(
        DataError, match=r"calib.txt not found \(.*kitti00_first6 holds: .*image_0/.*dataset.intrinsics"
    ):
        KittiDataset(KittiParams(path=str(src), times=str(src / "times_00_first6.txt")))
    short = tmp_path / "times.txt"
    short.write_text("0.0\n0.1\n0.2\n0.3\n0.4\n")
    intrinsics = {"fx": 718.856, "fy": 718.856, "cx": 607.1928, "cy": 185.2157}
    with pytest.raises(DataError, match=r"times.txt has 5 timestamps but .*image_0 holds 6 images"):
        KittiDataset(KittiParams.model_validate({"path": str(src), "times": str(short), "intrinsics": intrinsics}))
    short.write_text("0.0\n0.1\n0.1\n0.3\n0.4\n0.5\n")
    with pytest.raises(DataError, match=r"times.txt:3: timestamp 0.1 is duplicated"):
        KittiDataset(KittiParams.model_validate({"path": str(src), "times": str(short), "intrinsics": intrinsics}))
    with pytest.raises(DataError, match=r"no PNG images in .*image_2 \(dataset.camera=image_2\)"):
        KittiDataset(KittiParams(path=str(src), camera="image_2"))


# -- EuRoC ------------------------------------------------------------------------------------


def test_euroc_missing_files(tmp_path: Path):
    root = make_euroc(tmp_path / "seq", frames=6)
    params = EurocParams(path=str(root), body_to_base=np.eye(4).tolist())
    image = sorted((root / "mav0" / "cam0" / "data").glob("*.png"))[4]
    image.unlink()
    with pytest.raises(DataError, match=rf"image 4: .*{image.name} not found; .* holds: "):
        list(EurocDataset(params).frames())
    lenient = EurocDataset(params.model_copy(update={"strict": False}))
    assert [f.index for f in lenient.frames()] == [2, 3, 5]
    assert lenient.skips.counts == {"missing image": 1}
    (root / "mav0" / "cam0" / "data.csv").unlink()
    with pytest.raises(DataError, match=r"cam0/data.csv not found; .*cam0 holds: data/, sensor.yaml"):
        EurocDataset(params)


# -- ROS bags ---------------------------------------------------------------------------------


def _bag_params(bag: Path, **extra: object) -> RosbagParams:
    return RosbagParams.model_validate(
        {
            "path": str(bag),
            "image_topic": "/camera/image_raw",
            "odometry_topic": "/odom",
            "imu_topic": "/imu/data",
            "ground_truth_topic": "/ground_truth",
            "camera_info_topic": "/camera/camera_info",
            "camera_height": HEIGHT_M,
            "camera_tilt": TILT,
            **extra,
        }
    )


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    return write_bag(tmp_path / "bag", make_frames(6, seed=7), calibration(), "ros2_sqlite3")


def test_bag_missing_or_mistyped_topic_lists_the_topics(bag: Path):
    with pytest.raises(
        DataError,
        match=r"dataset.image_topic=/cam/image: no such topic in .*Topics in the bag: "
        r"/camera/image_raw \(sensor_msgs/msg/Image, 6 msgs\), .*/odom \(nav_msgs/msg/Odometry, 6 msgs\)",
    ):
        RosbagDataset(_bag_params(bag, image_topic="/cam/image"))
    with pytest.raises(DataError, match=r"odometry_topic=/imu/data carries sensor_msgs/msg/Imu, but it must be one of"):
        RosbagDataset(_bag_params(bag, odometry_topic="/imu/data"))
    with pytest.raises(
        DataError,
        match=r"dataset.image_topic is not set; topics of type Image or CompressedImage in .*"
        r": /camera/image_raw",
    ):
        RosbagDataset(_bag_params(bag, image_topic=""))
    with pytest.raises(DataError, match=r"no camera calibration. .*CameraInfo topics in the bag: /camera/camera_info"):
        RosbagDataset(_bag_params(bag, camera_info_topic=""))
    with pytest.raises(
        DataError, match=r"the camera's mounting is unknown: .*bag has no tf .*give the mounting: dataset.camera_height"
    ):
        RosbagDataset(_bag_params(bag, camera_height=None))
    with pytest.raises(DataError, match=r"bag not found: .*nope does not exist \(.* holds: bag/\)"):
        RosbagDataset(_bag_params(bag.parent / "nope"))


def test_sgf_run_reports_a_missing_topic_before_the_first_frame(bag: Path, tmp_path: Path):
    overrides = [
        o if not o.startswith("dataset.odometry_topic") else "dataset.odometry_topic=/wheel"
        for o in rosbag_overrides(bag)
    ]
    with pytest.raises(ConfigError, match=r"dataset=rosbag cannot start: dataset.odometry_topic=/wheel: no such topic"):
        _run(overrides, tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_bag_unknown_encoding(tmp_path: Path):
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    frames = make_frames(4, seed=1)
    stamp = types["builtin_interfaces/msg/Time"](sec=frames[1].ns // 10**9, nanosec=frames[1].ns % 10**9)
    depth = types["sensor_msgs/msg/Image"](
        header=types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera"),
        height=2,
        width=2,
        encoding="32FC1",
        is_bigendian=0,
        step=8,
        data=np.zeros(16, np.uint8),
    )
    extra = [("/depth", "sensor_msgs/msg/Image", frames[1].ns, depth)]
    bag = write_bag(tmp_path / "bag", frames, calibration(), "ros2_mcap", extra=extra)
    for strict in (True, False):  # every frame would fail alike: an error even when skipping is allowed
        dataset = RosbagDataset(_bag_params(bag, image_topic="/depth", strict=strict))
        with pytest.raises(DataError, match=r"unknown image encoding '32FC1'; supported: mono8, 8uc1, mono16"):
            list(dataset.frames())


def test_bag_corrupt_and_truncated_messages(tmp_path: Path):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    frames = make_frames(8, seed=3)
    calib = calibration()
    sample = store.serialize_cdr(
        store.types["sensor_msgs/msg/Image"](
            header=store.types["std_msgs/msg/Header"](
                stamp=store.types["builtin_interfaces/msg/Time"](
                    sec=frames[5].ns // 10**9, nanosec=frames[5].ns % 10**9
                ),
                frame_id="camera",
            ),
            height=120,
            width=160,
            encoding="rgb8",
            is_bigendian=0,
            step=480,
            data=np.zeros(480 * 60, np.uint8),
        ),
        "sensor_msgs/msg/Image",
    )
    corrupt = {("/camera/image_raw", 2): bytes(40), ("/camera/image_raw", 5): bytes(sample)}
    bag = write_bag(tmp_path / "bad", frames, calib, "ros2_sqlite3", corrupt=corrupt)
    with pytest.raises(
        DataError,
        match=r"/camera/image_raw: message 2 \(received at t=.*\) cannot be decoded .*corrupt or "
        r"truncated there.*dataset.strict=false",
    ):
        list(RosbagDataset(_bag_params(bag)).frames())
    lenient = RosbagDataset(_bag_params(bag, strict=False))
    assert [f.index for f in lenient.frames()] == [0, 1, 3, 4, 6, 7]  # message 2 undecodable, 5 truncated
    assert lenient.skips.counts == {"corrupt message": 1, "bad image": 1}
    metrics = _run([*rosbag_overrides(bag), "dataset.strict=false"], tmp_path / "run")
    assert metrics["dataset"]["skipped"] == 2
    assert metrics["dataset"]["skipped_by_reason"] == {"bad image": 1, "corrupt message": 1}


def test_bag_truncated_file(tmp_path: Path):
    frames = make_frames(6, seed=3)
    ros1 = write_bag(tmp_path / "run.bag", frames, calibration(), "ros1")
    ros1.write_bytes(ros1.read_bytes()[: ros1.stat().st_size // 2])
    with pytest.raises(DataError, match=r"cannot open bag .*run.bag: .*truncated or corrupt .*rosbag reindex"):
        RosbagDataset(_bag_params(ros1))
    mcap_dir = write_bag(tmp_path / "mcap", frames, calibration(), "ros2_mcap")
    mcap = next(mcap_dir.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(DataError, match=r"cannot open bag .*mcap.*truncated or corrupt"):
        RosbagDataset(_bag_params(mcap))


@pytest.mark.parametrize(
    ("kind", "offset_ns"), [("timestamp out of order", -150_000_000), ("duplicated timestamp", -100_000_000)]
)
def test_bag_unsorted_or_duplicated_image_stamps(tmp_path: Path, kind: str, offset_ns: int):
    frames = make_frames(6, seed=4)
    # the recorder received the messages in order, but image 3's header stamp is earlier than image 2's
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    ns = frames[3].ns + offset_ns
    header = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="camera"
    )
    image = store.types["sensor_msgs/msg/Image"](
        header=header,
        height=120,
        width=160,
        encoding="rgb8",
        is_bigendian=0,
        step=480,
        data=frames[3].image.reshape(-1),
    )
    corrupt = {("/camera/image_raw", 3): bytes(store.serialize_cdr(image, "sensor_msgs/msg/Image"))}
    bag = write_bag(tmp_path / "bag", frames, calibration(), "ros2_sqlite3", corrupt=corrupt)
    with pytest.raises(DataError, match=r"/camera/image_raw: header stamp .* is not after the previous message's"):
        list(RosbagDataset(_bag_params(bag)).frames())
    lenient = RosbagDataset(_bag_params(bag, strict=False))
    assert [f.index for f in lenient.frames()] == [0, 1, 2, 4, 5]
    assert lenient.skips.counts == {kind: 1}
    by_bag_time = RosbagDataset(_bag_params(bag, stamps="bag"))
    assert [f.index for f in by_bag_time.frames()] == [0, 1, 2, 3, 4, 5]


def test_bag_nan_odometry(tmp_path: Path):
    frames = make_frames(6, seed=4)
    frames[2].odometry = frames[2].odometry.copy()
    frames[2].odometry[0, 3] = np.nan
    misnamed = write_bag(tmp_path / "bag", frames, calibration(), "ros1")
    with pytest.raises(DataError, match=r"bag is a ROS 1 bag; its name must end in .bag to be read as one"):
        RosbagDataset(_bag_params(misnamed))
    bag = misnamed.rename(tmp_path / "run.bag")
    with pytest.raises(DataError, match=r"/odom: odometry pose at t=.* is not finite \(NaN or inf\)"):
        RosbagDataset(_bag_params(bag))
    lenient = RosbagDataset(_bag_params(bag, strict=False, max_time_diff=0.001))
    got = list(lenient.frames())
    # the image at the bad pose has no odometry within 1 ms: skipped; the others are fine
    assert [f.index for f in got] == [0, 1, 3, 4, 5]
    assert lenient.skips.counts == {"bad pose": 1, "no odometry": 1}
    context = RunContext(run_dir=None)
    lenient.finalize(context)
    assert context.metrics["dataset"]["skipped"] == 2


def test_bag_unset_header_stamps(tmp_path: Path):
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    frames = make_frames(5, seed=6)
    zero = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="c")
    extra = [
        (
            "/camera/unstamped",
            "sensor_msgs/msg/Image",
            f.ns,
            types["sensor_msgs/msg/Image"](
                header=zero, height=120, width=160, encoding="rgb8", is_bigendian=0, step=480, data=f.image.reshape(-1)
            ),
        )
        for f in frames
    ]
    bag = write_bag(tmp_path / "bag", frames, calibration(), "ros2_sqlite3", extra=extra)
    with pytest.raises(DataError, match=r"/camera/unstamped: message 0 has header.stamp 0 .*dataset\.stamps=bag"):
        list(RosbagDataset(_bag_params(bag, image_topic="/camera/unstamped")).frames())
    got = list(RosbagDataset(_bag_params(bag, image_topic="/camera/unstamped", stamps="bag")).frames())
    assert [f.timestamp for f in got] == pytest.approx([f.t for f in frames], abs=1e-6)
    assert all(np.array_equal(g.image, f.image) for g, f in zip(got, frames, strict=True))
