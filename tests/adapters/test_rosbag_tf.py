"""A ROS 2 bag of real KITTI frames that places its camera on /tf_static: it runs with its topic names alone."""

from __future__ import annotations

import json
import math
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sgf_plugins.datasets.bag_info import bag_summary, looks_like_truth, rank_candidates, render
from sgf_plugins.datasets.rosbag import RosbagDataset, RosbagParams

from sgf_pipeline.bags import TopicRow, TransformTree
from sgf_pipeline.calibration import camera_to_base_from_mounting
from sgf_pipeline.errors import DataError
from sgf_pipeline.geometry import pose_from_xyz_rpy
from sgf_pipeline.trajectory import read_tum

from .recordings import (
    KITTI_TILT,
    T0_NS,
    kitti_mounting,
    tf_message,
    transform_stamped,
    typestore,
    write_kitti_bag,
    write_messages,
)

BIN = Path(sys.executable).parent
#: The KITTI camera's optical frame in base_footprint, as the bag's /tf_static chain puts it.
EXPECTED = camera_to_base_from_mounting(1.65, KITTI_TILT, x=0.27)


@pytest.fixture(scope="module")
def kitti_bag(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_kitti_bag(tmp_path_factory.mktemp("kitti") / "kitti six frames", shared_data / "kitti00_first6")


def _params(bag: Path, **extra: object) -> RosbagParams:
    return RosbagParams.model_validate(
        {
            "path": str(bag),
            "image_topic": "/camera/image_raw",
            "camera_info_topic": "/camera/camera_info",
            "odometry_topic": "/odom",
            **extra,
        }
    )


def test_the_mounting_comes_from_tf_static(kitti_bag: Path):
    footprint_link, link_camera, camera_optical = kitti_mounting()
    np.testing.assert_allclose(footprint_link @ link_camera @ camera_optical, EXPECTED, atol=1e-12)  # the fixture
    dataset = RosbagDataset(_params(kitti_bag))
    calibration = dataset.calibration
    np.testing.assert_allclose(calibration.camera_to_base_matrix, EXPECTED, atol=1e-9)
    assert calibration.height == pytest.approx(1.65, abs=1e-9) and calibration.tilt == pytest.approx(KITTI_TILT)
    assert dataset.mounting_source.startswith(
        "tf (/tf_static): camera_optical_frame in base_footprint, optical frame: 1.650 m above the ground, optical "
        "axis 1.00 deg below the horizon"
    )
    # the config's mounting still wins over tf
    configured = RosbagDataset(_params(kitti_bag, camera_height=1.2, camera_tilt=0.1))
    assert configured.calibration.height == pytest.approx(1.2) and configured.mounting_source == "config"
    # the base frame named: base_link, 0.3 m above the road, so the camera is 1.35 m above its origin
    on_link = RosbagDataset(_params(kitti_bag, base_frame="base_link"))
    assert on_link.calibration.height == pytest.approx(1.35, abs=1e-9)
    assert "camera_optical_frame in base_link" in on_link.mounting_source


def test_an_image_frame_with_body_axes_is_turned_to_the_optical_frame(shared_data: Path, tmp_path: Path):
    """REP 103: camera_link has x forward, z up; the images' frame_id naming it still gives the optical frame."""
    bag = write_kitti_bag(tmp_path / "body", shared_data / "kitti00_first6", image_frame="camera_link")
    dataset = RosbagDataset(_params(bag))
    np.testing.assert_allclose(dataset.calibration.camera_to_base_matrix, EXPECTED, atol=1e-9)
    assert "camera_link in base_footprint, body axes (REP 103) turned to the optical frame" in dataset.mounting_source


def _tf_bag(path: Path, transforms: list[tuple[str, str, np.ndarray]], kitti_bag: Path) -> Path:
    """The KITTI bag's camera, odometry and calibration topics with another /tf_static."""
    from rosbags.highlevel import AnyReader

    types = typestore().types
    msgs: list[tuple[str, str, int, object]] = []
    with AnyReader([kitti_bag]) as reader:
        keep = [c for c in reader.connections if c.topic in ("/camera/image_raw", "/camera/camera_info", "/odom")]
        for connection, ns, raw in reader.messages(connections=keep):
            msgs.append((connection.topic, connection.msgtype, ns, reader.deserialize(raw, connection.msgtype)))
    statics = [transform_stamped(types, T0_NS, parent, child, pose) for parent, child, pose in transforms]
    msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", T0_NS, tf_message(types, statics)))
    return write_messages(path, msgs, "ros2_sqlite3")


def test_a_tree_that_does_not_join_the_camera_lists_its_frames(kitti_bag: Path, tmp_path: Path):
    lone = _tf_bag(
        tmp_path / "lone", [("base_footprint", "base_link", np.eye(4)), ("map", "odom", np.eye(4))], kitti_bag
    )
    with pytest.raises(
        DataError,
        match=r"the tf tree \(/tf_static\) does not join base_footprint and camera_optical_frame; the frames it has: "
        r"base_footprint, base_link, map, odom .*give the mounting: dataset.camera_height",
    ):
        RosbagDataset(_params(lone))
    baseless = _tf_bag(tmp_path / "baseless", [("chassis", "camera_optical_frame", EXPECTED)], kitti_bag)
    with pytest.raises(
        DataError,
        match=r"has neither base_footprint nor base_link; name the robot's base frame with "
        r"dataset.base_frame=<frame> \(the frames it has: camera_optical_frame, chassis\)",
    ):
        RosbagDataset(_params(baseless))
    chassis = RosbagDataset(_params(baseless, base_frame="chassis"))
    np.testing.assert_allclose(chassis.calibration.camera_to_base_matrix, EXPECTED, atol=1e-9)


def test_transform_tree_paths_chains_and_moving_frames():
    tree = TransformTree()
    types = typestore().types
    a = pose_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2)
    b = pose_from_xyz_rpy(0.0, 2.0, 0.5, 0.1, 0.0, 0.0)
    tree.add_message(tf_message(types, [transform_stamped(types, T0_NS, "/map", "odom", a)]), "/tf_static", True)
    tree.add_message(tf_message(types, [transform_stamped(types, T0_NS, "odom", "base", b)]), "/tf_static", True)
    np.testing.assert_allclose(tree.fixed_pose("map", "base"), a @ b, atol=1e-12)  # leading '/' of ROS 1 dropped
    np.testing.assert_allclose(tree.fixed_pose("base", "map"), np.linalg.inv(a @ b), atol=1e-12)
    for k in range(3):  # a mounting published over and over on /tf, as a ROS 1 static publisher does: still fixed
        fixed = transform_stamped(types, T0_NS + k * 10**8, "base", "lidar", pose_from_xyz_rpy(0.2, 0, 1.1, 0, 0, 0))
        tree.add_message(tf_message(types, [fixed]), "/tf", False)
    np.testing.assert_allclose(
        tree.fixed_pose("odom", "lidar"), b @ pose_from_xyz_rpy(0.2, 0, 1.1, 0, 0, 0), atol=1e-12
    )
    for k, x in enumerate((0.0, 0.1)):  # a camera on a slide: it moves on the base
        moving = transform_stamped(types, T0_NS + k * 10**7, "base", "camera", pose_from_xyz_rpy(x, 0, 1, 0, 0, 0))
        tree.add_message(tf_message(types, [moving]), "/tf", False)
    with pytest.raises(DataError, match=r"the transform base -> camera .* changes over the bag"):
        tree.fixed_pose("odom", "camera")
    seconds, poses = tree.trajectory("map", "camera")
    assert len(seconds) == 2 and poses[1][:3, 3] == pytest.approx(
        (a @ b @ pose_from_xyz_rpy(0.1, 0, 1, 0, 0, 0))[:3, 3]
    )


def test_bag_info_ranks_topics_by_type_and_role():
    rows = [
        TopicRow("/camera/depth/image_raw", "sensor_msgs/msg/Image", 10, 10.0),
        TopicRow("/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage", 10, 10.0),
        TopicRow("/camera/color/image_raw", "sensor_msgs/msg/Image", 10, 10.0),
        TopicRow("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", 10, 10.0),
        TopicRow("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", 10, 10.0),
        TopicRow("/ground_truth", "nav_msgs/msg/Odometry", 10, 10.0),
        TopicRow("/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", 10, 10.0),
        TopicRow("/odom", "nav_msgs/msg/Odometry", 10, 10.0),
        TopicRow("/vicon/robot", "geometry_msgs/msg/TransformStamped", 10, 10.0),
        TopicRow("/imu/data_raw", "sensor_msgs/msg/Imu", 10, 10.0),
        TopicRow("/imu/data", "sensor_msgs/msg/Imu", 10, 10.0),
    ]
    ranked = rank_candidates(rows)
    assert ranked["image_topic"] == [
        "/camera/color/image_raw",
        "/camera/color/image_raw/compressed",
        "/camera/depth/image_raw",
    ]
    assert ranked["camera_info_topic"] == ["/camera/color/camera_info", "/camera/depth/camera_info"]
    # Odometry before PoseWithCovarianceStamped; the ground truth is never the odometry, though alphabetically first
    assert ranked["odometry_topic"] == ["/odom", "/amcl_pose"]
    assert ranked["ground_truth_topic"] == ["/ground_truth", "/vicon/robot"]
    assert ranked["imu_topic"] == ["/imu/data", "/imu/data_raw"]
    assert [looks_like_truth(t) for t in ("/gt/pose", "/groundtruth", "/mocap/base", "/odom", "/target")] == [
        True,
        True,
        True,
        False,
        False,
    ]


@pytest.mark.slow
def test_bag_info_prints_a_command_that_runs_as_printed(kitti_bag: Path, tmp_path: Path):
    """A bag given by topic names alone, the camera 1.65 m high and 1 degree down, no ipm.* override."""
    proc = subprocess.run(
        [str(BIN / "sgf-bag-info"), f"path={kitti_bag}"], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    summary = bag_summary(kitti_bag)
    assert render(summary) == out.rstrip("\n")
    assert summary["chosen"] == {
        "image_topic": "/camera/image_raw",
        "camera_info_topic": "/camera/camera_info",
        "odometry_topic": "/odom",
        "imu_topic": "/imu",
        "ground_truth_topic": "/ground_truth",
    }
    assert "  mounting:            tf (/tf_static): camera_optical_frame in base_footprint" in out
    assert summary["missing"] == [] and "needs" not in out
    command = out.rstrip("\n").splitlines()[-1].strip()
    assert f"\"dataset.path='{kitti_bag}'\"" in command  # a path with spaces: quoted for Hydra and the shell
    argv = shlex.split(command)
    mounting = ("ipm.", "dataset.camera_height", "dataset.camera_tilt", "dataset.camera_to_base", "dataset.base_frame")
    assert argv[0] == "sgf-run" and not any(a.startswith(mounting) for a in argv)
    run = subprocess.run([str(BIN / "sgf-run"), *argv[1:]], capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    (run_dir,) = (tmp_path / "outputs" / "runs").iterdir()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["dataset"]["frames"] == 6 and metrics["dataset"]["mounting"].startswith("tf (/tf_static)")
    assert metrics["ipm"]["region"]["x_min"] > 5.0  # moved to the road the camera sees
    assert metrics["ate_rmse_m"]["odometry"] == pytest.approx(0.0, abs=1e-6)  # the odometry is the ground truth
    assert len(read_tum(run_dir / "trajectory_sgf.tum")) == len(read_tum(run_dir / "trajectory_gt.tum")) == 6
