"""dataset=rosbag: ROS 1 and ROS 2 (sqlite3, MCAP) bags give the same frames as the folder format."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from sgf_plugins.datasets.rosbag import RosbagDataset, RosbagParams

from sgf_pipeline import Pipeline
from sgf_pipeline.config import config_dir
from sgf_pipeline.evaluation import ate_rmse
from sgf_pipeline.geometry import pose_from_xyz_rpy
from sgf_pipeline.trajectory import read_tum

from .recordings import HEIGHT_M, T0_NS, TILT, calibration, make_frames, rosbag_overrides, write_bag, write_folder

BIN = Path(sys.executable).parent


def _compose(overrides: list[str]):  # type: ignore[no-untyped-def]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("config", overrides=[*overrides, "pipeline=[dataset,enhance]", "run.progress=false"])


def _stream(overrides: list[str], run_dir: Path) -> tuple[list, dict]:  # type: ignore[type-arg]
    """Every processed frame's (frame, enhanced image) and the run's metrics."""
    pipeline = Pipeline.from_config(_compose(overrides), run_dir=run_dir)
    seen = []
    for frame in pipeline.frames():
        step = pipeline.process(frame)
        seen.append((frame, step.outputs["image"].pixels))
    return seen, pipeline.finish()


CASES = [
    ("ros2_sqlite3", "rgb8", "pose", False, "/camera/image_raw"),
    ("ros2_mcap", "compressed_png", "transform", False, "/camera/image_raw/compressed"),
    ("ros1", "bgr8", "pose", True, "/camera/image_raw"),
]


@pytest.mark.parametrize(("version", "image_kind", "gt_kind", "grey", "topic"), CASES)
def test_bag_gives_the_folder_frames(
    tmp_path: Path, version: str, image_kind: str, gt_kind: str, grey: bool, topic: str
):
    frames = make_frames(8, seed=3, grey=grey)
    calib = calibration(distorted=True)
    folder = write_folder(tmp_path / "seq", frames, calib)
    bag = write_bag(
        tmp_path / ("run.bag" if version == "ros1" else "run_bag"), frames, calib, version, image_kind, gt_kind
    )
    if version == "ros2_mcap":
        bag = next(bag.glob("*.mcap"))  # a single .mcap file is a bag too

    from_bag, bag_metrics = _stream(rosbag_overrides(bag, topic), tmp_path / "run_bag_out")
    from_folder, folder_metrics = _stream(["dataset=folder", f"dataset.path={folder}"], tmp_path / "run_folder_out")

    assert len(from_bag) == len(from_folder) == 8
    for (fb, image_b), (ff, image_f) in zip(from_bag, from_folder, strict=True):
        assert fb.index == ff.index
        assert abs(fb.timestamp - ff.timestamp) < 1e-6
        assert fb.image.shape == ff.image.shape == ((120, 160) if grey else (120, 160, 3))
        assert np.array_equal(fb.image, ff.image)  # the same undistortion of the same pixels
        assert np.array_equal(image_b, image_f)
        np.testing.assert_allclose(fb.odometry, ff.odometry, atol=1e-8)
        np.testing.assert_allclose(fb.ground_truth, ff.ground_truth, atol=1e-8)
        np.testing.assert_allclose(fb.imu_roll_pitch, ff.imu_roll_pitch, atol=1e-8)
        assert fb.calibration == ff.calibration
        assert fb.calibration.distortion.model == "none"  # the frames carry undistorted images
    # and against the recording itself
    for (fb, _), f in zip(from_bag, frames, strict=True):
        np.testing.assert_allclose(fb.odometry, f.odometry, atol=1e-12)
        np.testing.assert_allclose(fb.imu_roll_pitch, f.roll_pitch, atol=1e-12)
    assert bag_metrics["dataset"] == {
        "name": "rosbag",
        "frames": 8,
        "skipped": 0,
        "skipped_by_reason": {},
        "trimmed": 0,
        "mounting": "config",
    }
    assert bag_metrics["ate_rmse_m"]["odometry"] == pytest.approx(folder_metrics["ate_rmse_m"]["odometry"], abs=1e-7)
    assert bag_metrics["ate_rmse_m"]["odometry"] > 0.01  # the synthetic odometry drifts from the ground truth


def test_sgf_run_cli_on_a_ros2_bag(tmp_path: Path):
    frames = make_frames(6, seed=5)
    calib = calibration()
    bag = write_bag(tmp_path / "bag", frames, calib, "ros2_mcap", "rgb8", "transform")
    folder = write_folder(tmp_path / "seq", frames, calib)
    env = {**os.environ, "SGF_PIPELINE_TRACEBACK": "1"}
    outs = {}
    for label, overrides in (("bag", rosbag_overrides(bag)), ("folder", ["dataset=folder", f"dataset.path={folder}"])):
        out = tmp_path / f"out_{label}"
        proc = subprocess.run(
            [
                str(BIN / "sgf-run"),
                *overrides,
                "pipeline=[dataset,enhance]",
                "enhance=none",
                "run.progress=false",
                f"hydra.run.dir={out}",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stderr
        outs[label] = out
    metrics = json.loads((outs["bag"] / "metrics.json").read_text())
    assert metrics["dataset"]["frames"] == 6 and metrics["dataset"]["skipped"] == 0
    assert metrics["stages"] == {"dataset": "rosbag", "enhance": "none"}
    odo_bag = read_tum(outs["bag"] / "trajectory_odometry.tum")
    odo_folder = read_tum(outs["folder"] / "trajectory_odometry.tum")
    gt_bag = read_tum(outs["bag"] / "trajectory_gt.tum")
    np.testing.assert_allclose(odo_bag.poses, odo_folder.poses, atol=1e-8)
    np.testing.assert_allclose(odo_bag.timestamps, [f.t for f in frames], atol=1e-6)
    assert metrics["ate_rmse_m"]["odometry"] == pytest.approx(ate_rmse(gt_bag, odo_bag), abs=1e-9)
    # nothing was written into the input
    assert sorted(p.name for p in bag.iterdir()) == ["bag.mcap", "metadata.yaml"]


def test_interpolates_fast_odometry_and_trims_frames_outside_it(tmp_path: Path):
    """Odometry at 50 Hz, offset from the 10 Hz camera: poses are interpolated at the image stamps."""
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    frames = make_frames(10, seed=1)
    calib = calibration()

    def truth(ns: int) -> np.ndarray:  # a smooth motion known at every time
        s = (ns - T0_NS) / 1e9
        return pose_from_xyz_rpy(0.8 * s, 0.2 * s * s, 0.0, 0.0, 0.0, 0.3 * s)

    extra = []
    for k in range(0, 40):  # odometry from 0.107 s to 0.887 s after the first image
        ns = T0_NS + 107_000_000 + k * 20_000_000
        pose = truth(ns)
        from sgf_pipeline.geometry import quaternion_from_rotation

        q = quaternion_from_rotation(pose[:3, :3])
        msg = types["geometry_msgs/msg/PoseStamped"](
            header=types["std_msgs/msg/Header"](
                stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="odom"
            ),
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
                orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )
        extra.append(("/fast_odom", "geometry_msgs/msg/PoseStamped", ns, msg))
    bag = write_bag(tmp_path / "bag", frames, calib, "ros2_sqlite3", extra=extra)
    params = RosbagParams(
        path=str(bag),
        image_topic="/camera/image_raw",
        odometry_topic="/fast_odom",
        camera_info_topic="/camera/camera_info",
        camera_height=HEIGHT_M,
        camera_tilt=TILT,
        max_time_diff=0.015,
    )
    dataset = RosbagDataset(params)
    got = list(dataset.frames())
    # odometry spans 0.107..0.887 s: the image at 0.0 s lies outside it (trimmed); those at 0.1 s and
    # 0.9 s are within max_time_diff of an end sample and take it
    assert [f.index for f in got] == [1, 2, 3, 4, 5, 6, 7, 8, 9]
    assert dataset.trimmed == 1
    np.testing.assert_allclose(got[0].odometry, truth(T0_NS + 107_000_000), atol=1e-12)
    np.testing.assert_allclose(got[-1].odometry, truth(T0_NS + 887_000_000), atol=1e-12)
    for f in got[1:-1]:
        expected = truth(T0_NS + f.index * 100_000_000)
        np.testing.assert_allclose(f.odometry[:3, 3], expected[:3, 3], atol=2e-4)  # quadratic y: linear interp error
        yaw = math.atan2(f.odometry[1, 0], f.odometry[0, 0])
        # constant yaw rate: slerp is exact, up to the float64 resolution of Unix seconds (2.4e-7 s)
        assert yaw == pytest.approx(0.3 * f.index * 0.1, abs=1e-6)
        assert f.imu_roll_pitch is None and f.ground_truth is None
    nearest = RosbagDataset(params.model_copy(update={"interpolate": False}))
    first = next(iter(nearest.frames()))
    sample = truth(T0_NS + 107_000_000)  # the nearest odometry message to the image at 0.1 s
    np.testing.assert_allclose(first.odometry, sample, atol=1e-12)


def test_imu_roll_pitch_from_gyro_and_accelerometer_when_no_orientation(tmp_path: Path):
    """An IMU publishing no orientation (covariance[0] = -1): roll/pitch come from the complementary filter."""
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    frames = make_frames(10, seed=2)
    roll, pitch = 0.05, -0.08
    gravity_in_imu = pose_from_xyz_rpy(0, 0, 0, roll, pitch, 0.0)[:3, :3].T @ np.array([0.0, 0.0, 9.81])
    cov = np.zeros(9)
    cov[0] = -1.0
    vec = types["geometry_msgs/msg/Vector3"]
    extra = []
    for k in range(200):  # 200 Hz for 1 s, standing still on a slope
        ns = T0_NS - 50_000_000 + k * 5_000_000
        extra.append(
            (
                "/imu/raw",
                "sensor_msgs/msg/Imu",
                ns,
                types["sensor_msgs/msg/Imu"](
                    header=types["std_msgs/msg/Header"](
                        stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="imu"
                    ),
                    orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0),
                    orientation_covariance=cov,
                    angular_velocity=vec(x=0.0, y=0.0, z=0.0),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=vec(x=gravity_in_imu[0], y=gravity_in_imu[1], z=gravity_in_imu[2]),
                    linear_acceleration_covariance=np.zeros(9),
                ),
            )
        )
    bag = write_bag(tmp_path / "bag", frames, calibration(), "ros2_sqlite3", extra=extra)
    dataset = RosbagDataset(
        RosbagParams(
            path=str(bag),
            image_topic="/camera/image_raw",
            odometry_topic="/odom",
            imu_topic="/imu/raw",
            camera_info_topic="/camera/camera_info",
            camera_height=HEIGHT_M,
        )
    )
    got = list(dataset.frames())
    assert len(got) == 10
    for f in got:
        assert f.imu_roll_pitch == pytest.approx((roll, pitch), abs=1e-9)


def test_topics_are_found_without_their_leading_slash(tmp_path: Path):
    """dataset.<role>_topic=camera/image_raw finds /camera/image_raw: the same frames as with the slash."""
    bag = write_bag(tmp_path / "drive.bag", make_frames(4, seed=3), calibration(), "ros1")
    given = dict(
        path=str(bag),
        image_topic="/camera/image_raw",
        odometry_topic="/odom",
        ground_truth_topic="/ground_truth",
        camera_info_topic="/camera/camera_info",
        camera_height=HEIGHT_M,
        camera_tilt=TILT,
    )
    exact = RosbagDataset(RosbagParams(**given))
    bare = RosbagDataset(RosbagParams(**{k: v.lstrip("/") if k.endswith("_topic") else v for k, v in given.items()}))
    assert bare.params.image_topic == "/camera/image_raw" and bare.params.odometry_topic == "/odom"
    ours, theirs = list(exact.frames()), list(bare.frames())
    assert [f.index for f in theirs] == [f.index for f in ours] == [0, 1, 2, 3]
    for a, b in zip(ours, theirs, strict=True):
        np.testing.assert_array_equal(a.odometry, b.odometry)
        np.testing.assert_array_equal(a.ground_truth, b.ground_truth)
        np.testing.assert_array_equal(a.image, b.image)
