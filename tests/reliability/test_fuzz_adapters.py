"""Dataset adapters under damaged recordings: every file of a folder, EuRoC and KITTI recording, and bag bytes.

Each property: building the dataset and reading every frame either works (and then every frame is
well formed) or raises a DataError; with ``strict: false`` a bad frame is a counted skip. The
hand-made cases complete tests/adapters/test_bad_input.py (NaN/inf poses, time going back,
empty sequences) for the adapters and files it does not cover.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from adapters.recordings import HEIGHT_M, TILT, calibration, make_frames, write_bag, write_folder
from adapters.test_euroc_dataset import make_euroc
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sgf_plugins.datasets.euroc import EurocDataset, EurocParams
from sgf_plugins.datasets.folder import FolderDataset, FolderParams
from sgf_plugins.datasets.kitti import KittiDataset, KittiParams
from sgf_plugins.datasets.rosbag import RosbagDataset, RosbagParams

from sgf_pipeline import DataError, Pipeline
from sgf_pipeline.types import Frame

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
INTRINSICS = {"fx": 718.856, "fy": 718.856, "cx": 607.1928, "cy": 185.2157}

TOKENS = st.sampled_from(["0", "1", "-1", "0.5", "nan", "inf", "1e999", "1700000000.1", "abc", "", "#", "timestamp"])


def _garbage() -> st.SearchStrategy[bytes]:
    line = st.lists(TOKENS, max_size=9).flatmap(lambda xs: st.sampled_from([" ", ",", "\t"]).map(lambda s: s.join(xs)))
    text = st.lists(line, max_size=6).map("\n".join).map(str.encode)
    return st.one_of(text, st.binary(max_size=200))


def _mutations(original: bytes) -> st.SearchStrategy[bytes]:
    """Garbage, or the original file with a few lines dropped, duplicated, swapped or bytes flipped."""
    lines = original.split(b"\n")

    def edit(ops: list[tuple[int, int, int]]) -> bytes:
        out = list(lines)
        for kind, i, j in ops:
            if not out:
                break
            i, j = i % len(out), j % len(out)
            if kind == 0:
                del out[i]
            elif kind == 1:
                out.insert(i, out[j])
            elif kind == 2:
                out[i], out[j] = out[j], out[i]
            else:
                b = bytearray(out[i])
                if b:
                    b[j % len(b)] ^= 0x20 + (j % 7)
                out[i] = bytes(b)
        return b"\n".join(out)

    ops = st.lists(st.tuples(st.integers(0, 3), st.integers(0, 50), st.integers(0, 500)), min_size=1, max_size=4)
    return st.one_of(_garbage(), ops.map(edit))


def _read_all(frames: Iterator[Frame]) -> list[Frame]:
    """Every frame with its image decoded, each checked for the Frame contract."""
    out = []
    last = -np.inf
    for frame in frames:
        assert np.isfinite(frame.timestamp) and frame.timestamp > last
        last = frame.timestamp
        assert frame.odometry.shape == (4, 4) and np.all(np.isfinite(frame.odometry))
        if frame.imu_roll_pitch is not None:
            assert all(np.isfinite(frame.imu_roll_pitch))
        if frame.ground_truth is not None:
            assert np.all(np.isfinite(frame.ground_truth))
        image = frame.image
        assert image.dtype == np.uint8 and image.ndim in (2, 3)
        out.append(frame)
    return out


# -- folder -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def folder_original(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = write_folder(tmp_path_factory.mktemp("folder") / "seq", make_frames(4, seed=5), calibration())
    return root


FOLDER_FILES = [
    "timestamps.txt",
    "odometry.tum",
    "imu.csv",
    "groundtruth.tum",
    "sequence.yaml",
    "calibration.yaml",
    "images/000002.png",
]


@pytest.mark.parametrize("name", FOLDER_FILES)
def test_any_damage_to_one_folder_file_gives_frames_or_a_data_error(folder_original: Path, name: str):
    target = folder_original / name
    original = target.read_bytes()

    @FUZZ
    @given(content=_mutations(original), strict=st.booleans())
    def check(content: bytes, strict: bool) -> None:
        target.write_bytes(content)
        try:
            dataset = FolderDataset(FolderParams(path=str(folder_original), strict=strict))
            frames = _read_all(dataset.frames())
        except DataError as exc:
            assert str(folder_original) in str(exc) or "dataset=folder" in str(exc)
        else:
            assert len(frames) + dataset.skips.total >= 1
            assert len(frames) == dataset.yielded
        finally:
            target.write_bytes(original)

    check()


def test_folder_inf_pose_nan_ground_truth_and_nan_imu(tmp_path: Path):
    root = write_folder(tmp_path / "seq", make_frames(6, seed=8), calibration())
    odometry = (root / "odometry.tum").read_text().splitlines()
    fields = odometry[1].split()
    odometry[1] = " ".join([fields[0], "inf", *fields[2:]])
    (root / "odometry.tum").write_text("\n".join(odometry) + "\n")
    truth = (root / "groundtruth.tum").read_text().splitlines()
    fields = truth[3].split()
    truth[3] = " ".join([*fields[:4], "nan", *fields[5:]])
    (root / "groundtruth.tum").write_text("\n".join(truth) + "\n")
    imu = (root / "imu.csv").read_text().splitlines()
    imu[5] = imu[5].split(",")[0] + ",nan,0.0"  # row 5 is image 4 (the header is line 1)
    (root / "imu.csv").write_text("\n".join(imu) + "\n")
    with pytest.raises(DataError, match=r"odometry.tum: pose 1 is not finite"):
        FolderDataset(FolderParams(path=str(root)))
    dataset = FolderDataset(FolderParams(path=str(root), strict=False))
    frames = _read_all(dataset.frames())
    assert [f.index for f in frames] == [0, 2, 3, 5]
    assert dataset.skips.counts == {"bad pose": 1, "bad imu": 1}
    assert frames[2].ground_truth is None and frames[1].ground_truth is not None  # image 3: its NaN truth left out


def test_folder_with_no_images_or_all_frames_skipped(tmp_path: Path):
    root = write_folder(tmp_path / "seq", make_frames(3, seed=1), calibration())
    for image in (root / "images").iterdir():
        image.write_bytes(b"")
    with pytest.raises(DataError, match=r"frame 0 \(000000.png\): image .*the file is empty"):
        _read_all(FolderDataset(FolderParams(path=str(root))).frames())
    everything_bad = FolderDataset(FolderParams(path=str(root), strict=False))
    assert _read_all(everything_bad.frames()) == []
    assert everything_bad.skips.counts == {"bad image": 3}
    shutil.rmtree(root / "images")
    (root / "images").mkdir()
    with pytest.raises(DataError, match=r"images has no PNG or JPEG images; .*images holds: nothing \(empty folder\)"):
        FolderDataset(FolderParams(path=str(root)))


def test_a_run_over_a_folder_whose_frames_are_all_skipped_still_finishes(tmp_path: Path):
    root = write_folder(tmp_path / "seq", make_frames(3, seed=1), calibration())
    for image in (root / "images").iterdir():
        image.write_bytes(image.read_bytes()[:100])
    cfg = {
        "pipeline": ["dataset", "enhance"],
        "dataset": {"name": "folder", "path": str(root), "strict": False},
        "enhance": {"name": "none"},
        "run": {"progress": False},
    }
    Pipeline.from_config(cfg, run_dir=tmp_path / "run").run()
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["status"] == "finished"
    assert metrics["dataset"]["skipped_by_reason"] == {"bad image": 3}
    assert metrics["timing"]["frames"] == 0 and metrics["timing"]["fps"] is None
    assert metrics["ate_rmse_m"] == {"odometry": None, "sgf": None}
    assert not list((tmp_path / "run").glob("trajectory_*.tum"))


# -- EuRoC ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def euroc_original(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_euroc(tmp_path_factory.mktemp("euroc") / "seq", frames=6)


EUROC_FILES = ["cam0/data.csv", "cam0/sensor.yaml", "imu0/data.csv", "state_groundtruth_estimate0/data.csv"]


@pytest.mark.parametrize("name", EUROC_FILES)
def test_any_damage_to_one_euroc_file_gives_frames_or_a_data_error(euroc_original: Path, name: str):
    target = euroc_original / "mav0" / name
    original = target.read_bytes()

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(content=_mutations(original), strict=st.booleans())
    def check(content: bytes, strict: bool) -> None:
        target.write_bytes(content)
        try:
            params = EurocParams(path=str(euroc_original), body_to_base=np.eye(4).tolist(), strict=strict)
            dataset = EurocDataset(params)
            frames = _read_all(dataset.frames())
        except DataError as exc:
            assert "euroc" in str(exc) or str(euroc_original) in str(exc)
        else:
            assert len(frames) == dataset.yielded
        finally:
            target.write_bytes(original)

    check()


def test_euroc_image_stamps_going_back_and_names_leaving_the_folder(tmp_path: Path):
    root = make_euroc(tmp_path / "seq", frames=8)
    csv = root / "mav0" / "cam0" / "data.csv"
    rows = csv.read_text().splitlines()
    rows[5], rows[6] = rows[6], rows[5]  # image 5 before image 4
    csv.write_text("\n".join(rows) + "\n")
    params = EurocParams(path=str(root), body_to_base=np.eye(4).tolist())
    with pytest.raises(DataError, match=r"data.csv:7: image timestamp \d+ ns is not after \d+ ns"):
        EurocDataset(params)
    lenient = EurocDataset(params.model_copy(update={"strict": False}))
    assert lenient.skips.counts == {"timestamp out of order": 1}
    assert len(_read_all(lenient.frames())) == 5  # 7 listed in order; 2 before the ground truth starts
    rows[5], rows[6] = rows[6], rows[5]
    rows[3] = rows[3].split(",")[0] + ",../../../../etc/passwd"
    csv.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match=r"data.csv:4: image name '../../../../etc/passwd' must be a file name inside"):
        EurocDataset(params)
    rows[3] = rows[3].split(",")[0] + ",/etc/passwd"
    csv.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match=r"data.csv:4: image name '/etc/passwd' must be a file name inside"):
        EurocDataset(params)
    csv.write_text("#timestamp [ns],filename\n")
    with pytest.raises(DataError, match=r"cam0/data.csv lists no images"):
        EurocDataset(params)


def test_euroc_nan_ground_truth_is_named(tmp_path: Path):
    root = make_euroc(tmp_path / "seq", frames=6)
    gt = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    rows = gt.read_text().splitlines()
    fields = rows[10].split(",")
    rows[10] = ",".join([fields[0], "nan", *fields[2:]])
    gt.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match=r"data.csv:11: non-finite pose \(NaN or inf\)"):
        EurocDataset(EurocParams(path=str(root), body_to_base=np.eye(4).tolist()))


# -- KITTI ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def kitti_copy(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = shared_data / "kitti00_first6"
    root = tmp_path_factory.mktemp("kitti") / "00"
    shutil.copytree(src / "image_0", root / "image_0")
    shutil.copy(src / "times_00_first6.txt", root / "times.txt")
    shutil.copy(src / "poses_00_first6.txt", root / "poses.txt")
    (root / "calib.txt").write_text(
        "P0: 7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0\ncalib_time: 09-Jan-2012 13:57:47\n"
    )
    return root


@pytest.mark.parametrize("name", ["times.txt", "poses.txt", "calib.txt", "image_0/000003.png"])
def test_any_damage_to_one_kitti_file_gives_frames_or_a_data_error(kitti_copy: Path, name: str):
    target = kitti_copy / name
    original = target.read_bytes()

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(content=_mutations(original), strict=st.booleans())
    def check(content: bytes, strict: bool) -> None:
        target.write_bytes(content)
        try:
            dataset = KittiDataset(KittiParams(path=str(kitti_copy), strict=strict))
            frames = _read_all(dataset.frames())
        except DataError as exc:
            assert str(kitti_copy) in str(exc) or "dataset=kitti" in str(exc)
        else:
            assert len(frames) + dataset.skips.total == 6
        finally:
            target.write_bytes(original)

    check()


def test_kitti_inf_pose_and_empty_image_folder(kitti_copy: Path, tmp_path: Path):
    root = tmp_path / "00"
    shutil.copytree(kitti_copy, root)
    poses = (root / "poses.txt").read_text().splitlines()
    poses[2] = " ".join(["inf", *poses[2].split()[1:]])
    (root / "poses.txt").write_text("\n".join(poses) + "\n")
    with pytest.raises(DataError, match=r"poses.txt:3: non-finite pose"):
        KittiDataset(KittiParams(path=str(root)))
    for image in (root / "image_0").iterdir():
        image.unlink()
    with pytest.raises(DataError, match=r"no PNG images in .*image_0 \(dataset.camera=image_0\)"):
        KittiDataset(KittiParams(path=str(root)))


# -- ROS bags ---------------------------------------------------------------------------------


def _bag_params(bag: Path, strict: bool) -> RosbagParams:
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
            "strict": strict,
        }
    )


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    out = {}
    frames = make_frames(4, seed=9)
    base = tmp_path_factory.mktemp("bags")
    out["ros1"] = write_bag(base / "a.bag", frames, calibration(), "ros1").read_bytes()
    mcap_dir = write_bag(base / "mcap", frames, calibration(), "ros2_mcap")
    out["mcap"] = next(mcap_dir.glob("*.mcap")).read_bytes()
    return out


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_flipped_bytes_in_a_bag_give_frames_a_counted_skip_or_a_data_error(bags: dict[str, bytes], kind: str, tmp_path):
    original = bags[kind]
    path = tmp_path / ("run.bag" if kind == "ros1" else "run.mcap")

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(
        flips=st.lists(st.tuples(st.integers(0, len(original) - 1), st.integers(1, 255)), min_size=1, max_size=6),
        cut=st.one_of(st.none(), st.integers(0, len(original))),
        strict=st.booleans(),
    )
    def check(flips: list[tuple[int, int]], cut: int | None, strict: bool) -> None:
        data = bytearray(original)
        for at, mask in flips:
            data[at] ^= mask
        path.write_bytes(bytes(data[:cut]) if cut is not None else bytes(data))
        try:
            dataset = RosbagDataset(_bag_params(path, strict))
            frames = _read_all(dataset.frames())
        except DataError as exc:
            assert str(path) in str(exc) or "/" in str(exc)
        else:
            assert len(frames) == dataset.yielded <= 4

    check()


def test_a_bag_whose_image_topic_is_empty(tmp_path: Path):
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    frames = make_frames(3, seed=2)
    # a topic that exists in the bag but carries no message: declared with one message, then removed
    bag = write_bag(tmp_path / "bag", frames, calibration(), "ros2_sqlite3")
    import sqlite3

    db = next(bag.glob("*.db3"))
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM messages WHERE topic_id = (SELECT id FROM topics WHERE name = '/camera/image_raw')")
    meta = (bag / "metadata.yaml").read_text()
    import yaml

    data = yaml.safe_load(meta)
    for topic in data["rosbag2_bagfile_information"]["topics_with_message_count"]:
        if topic["topic_metadata"]["name"] == "/camera/image_raw":
            topic["message_count"] = 0
    (bag / "metadata.yaml").write_text(yaml.safe_dump(data))
    assert types  # the typestore loads
    with pytest.raises(DataError, match=r"dataset.image_topic=/camera/image_raw: the topic has no messages"):
        RosbagDataset(_bag_params(bag, True))


def test_a_damaged_record_inside_a_ros1_bag_stops_the_reading_with_a_count(bags: dict[str, bytes], tmp_path: Path):
    """Found by the byte-flip property: rosbags raises while iterating a damaged chunk, after the bag opened."""
    data = bytearray(bags["ros1"])
    at = -1
    for _ in range(20):  # the 20th message record (camera info, then odometry, IMU, ... in time order)
        at = data.index(b"conn=", at + 1)
    data[at : at + 4] = b"cXnn"
    bag = tmp_path / "run.bag"
    bag.write_bytes(bytes(data))
    params = {
        "path": str(bag),
        "image_topic": "/camera/image_raw",
        "odometry_topic": "/odom",
        "camera_info_topic": "/camera/camera_info",
        "camera_height": HEIGHT_M,
        "camera_tilt": TILT,
    }
    with pytest.raises(
        DataError,
        match=r"run.bag: the bag cannot be read past this point \(ReaderError: Could not read uint32 field 'conn'\.\); "
        r"messages read so far: 1 on /camera/camera_info, 3 on /odom\. It is corrupt or truncated there",
    ):
        RosbagDataset(RosbagParams.model_validate(params))
    lenient = RosbagDataset(RosbagParams.model_validate({**params, "strict": False}))
    assert [f.index for f in _read_all(lenient.frames())] == [0, 1, 2]
    assert lenient.skips.counts == {"unreadable bag": 1} and lenient.trimmed == 1
