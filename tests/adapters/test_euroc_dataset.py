"""dataset=euroc on a synthetic recording in the EuRoC/ASL layout."""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from sgf_plugins.datasets.euroc import EurocDataset, EurocParams

from sgf_pipeline.calibration_io import read_euroc_sensor_yaml
from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import DataError
from sgf_pipeline.geometry import invert, pose_from_xyz_rpy, quaternion_from_rotation
from sgf_pipeline.imu import GRAVITY
from sgf_pipeline.trajectory import read_trajectory, write_euroc_csv, write_tum
from sgf_pipeline.undistortion import Undistorter

from .test_calibration_io import EUROC_SENSOR

T0 = 1_403_636_579_000_000_000
CAM_NS = 50_000_000  # 20 Hz


def body_pose(s: float) -> np.ndarray:
    """The body's pose at time s (seconds since T0): driving a gentle curve, rocking a little."""
    return pose_from_xyz_rpy(1.0 * s, 0.1 * s * s, 0.0, 0.03 * math.sin(2 * s), 0.02 * math.sin(3 * s), 0.1 * s)


BODY_YAML = """%YAML:1.0
# Body frame definitions.
comment: body frame, aligned with the IMU frame (imu0)
"""
IMU_SENSOR = """%YAML:1.0
#Default imu sensor yaml file
sensor_type: imu
comment: test IMU

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 200

# inertial sensor noise model parameters (static)
gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )
gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )
accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]  ( accel "white noise" )
accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )
"""
POSE_SENSOR = """%YAML:1.0
# Sensor extrinsics wrt. the body-frame.
sensor_type: {kind}
comment: {comment}
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
"""
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)


def make_euroc(root: Path, frames: int = 20) -> Path:
    """A recording in the ASL layout the EuRoC sequences ship in (``%YAML:1.0`` headers, 17-column ground truth)."""
    mav = root / "mav0"
    for folder in ("cam0/data", "cam1/data", "imu0", "vicon0", "state_groundtruth_estimate0"):
        (mav / folder).mkdir(parents=True)
    (mav / "body.yaml").write_text(BODY_YAML)
    (mav / "cam0" / "sensor.yaml").write_text(EUROC_SENSOR)
    (mav / "cam1" / "sensor.yaml").write_text(EUROC_SENSOR.replace("-0.02,", "0.09,"))
    (mav / "imu0" / "sensor.yaml").write_text(IMU_SENSOR)
    (mav / "vicon0" / "sensor.yaml").write_text(POSE_SENSOR.format(kind="pose", comment="test motion capture"))
    (mav / "state_groundtruth_estimate0" / "sensor.yaml").write_text(
        POSE_SENSOR.format(kind="visual-inertial", comment="test ground truth")
    )
    rng = np.random.default_rng(4)
    rows = ["#timestamp [ns],filename"]
    for i in range(frames):
        ns = T0 + i * CAM_NS
        for cam in ("cam0", "cam1"):
            cv2.imwrite(str(mav / cam / "data" / f"{ns}.png"), rng.integers(0, 256, (240, 320), dtype=np.uint8))
        rows.append(f"{ns},{ns}.png")
    for cam in ("cam0", "cam1"):
        (mav / cam / "data.csv").write_text("\n".join(rows) + "\n")
    # ground truth at 200 Hz, starting 0.12 s after the first image (as in EuRoC, the camera starts first)
    gt = [GT_HEADER]
    vicon = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    imu = [
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
        "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
    ]
    step = 5_000_000
    for k in range(24, frames * 10 + 10):
        ns = T0 + k * step
        s = (ns - T0) / 1e9
        pose = body_pose(s)
        q = quaternion_from_rotation(pose[:3, :3])
        x, y, z = pose[:3, 3]
        state = f"{ns},{x:.9f},{y:.9f},{z:.9f},{q[3]:.9f},{q[0]:.9f},{q[1]:.9f},{q[2]:.9f}"
        gt.append(state + ",1.0,0.2,0.0,-0.002153,0.020744,0.075806,-0.013337,0.103464,0.093086")
        vicon.append(state)
    for k in range(0, frames * 10 + 10):
        ns = T0 + k * step
        s = (ns - T0) / 1e9
        r0, r1 = body_pose(s)[:3, :3], body_pose(s + 1e-4)[:3, :3]
        delta = r0.T @ r1
        omega = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]]) / 2e-4
        accel = r0.T @ np.array([0.0, 0.0, GRAVITY])  # centripetal terms are small here
        imu.append(f"{ns}," + ",".join(f"{v:.9f}" for v in (*omega, *accel)))
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(gt) + "\n")
    (mav / "vicon0" / "data.csv").write_text("\n".join(vicon) + "\n")
    (mav / "imu0" / "data.csv").write_text("\n".join(imu) + "\n")
    return root


def test_euroc_frames_poses_attitude_and_undistortion(tmp_path: Path):
    root = make_euroc(tmp_path / "MH_synthetic")
    # the body is the base here: T_BS is the camera in the body, the body sits as the base
    params = EurocParams(path=str(root), body_to_base=np.eye(4).tolist(), imu_gain=2.0)
    dataset = EurocDataset(params)
    context = RunContext(run_dir=None)
    dataset.begin(context)
    assert context.rate_hz == 20.0 and context.sequence == "MH_synthetic"
    sensor = read_euroc_sensor_yaml(root / "mav0" / "cam0" / "sensor.yaml")
    assert context.calibration is not None and context.calibration.distortion.is_identity
    np.testing.assert_allclose(context.calibration.camera_to_base_matrix, sensor.camera_to_body, atol=1e-12)
    frames = list(dataset.frames())
    # ground truth (the odometry) starts 0.12 s in: images 0, 1 (0.0, 0.05 s) are outside it; image 2 at
    # 0.10 s is 0.02 s before the first sample, within max_time_diff
    assert [f.index for f in frames] == list(range(2, 20))
    assert dataset.trimmed == 2
    for f in frames[1:]:
        s = f.index * 0.05
        np.testing.assert_allclose(f.ground_truth, body_pose(s), atol=2e-5)
        np.testing.assert_array_equal(f.odometry, f.ground_truth)
        assert f.timestamp == pytest.approx(T0 / 1e9 + s, abs=1e-6)
        roll, pitch = 0.03 * math.sin(2 * s), 0.02 * math.sin(3 * s)
        assert f.imu_roll_pitch == pytest.approx((roll, pitch), abs=math.radians(0.3))
    raw = cv2.imread(str(root / "mav0" / "cam0" / "data" / f"{T0 + 5 * CAM_NS}.png"), cv2.IMREAD_UNCHANGED)
    expected = Undistorter(context.calibration.model_copy(update={"distortion": sensor.distortion}))(raw)
    assert np.array_equal(frames[3].image, expected) and not np.array_equal(frames[3].image, raw)
    dataset.finalize(context)
    assert context.metrics["dataset"] == {
        "name": "euroc",
        "frames": 18,
        "skipped": 0,
        "skipped_by_reason": {},
        "trimmed": 2,
    }


def test_euroc_mounting_moves_poses_to_the_base(tmp_path: Path):
    root = make_euroc(tmp_path / "seq", frames=8)
    dataset = EurocDataset(EurocParams(path=str(root / "mav0"), camera_height=0.6, camera_tilt=0.25))
    assert dataset.calibration.height == pytest.approx(0.6) and dataset.calibration.tilt == pytest.approx(0.25)
    sensor = read_euroc_sensor_yaml(root / "mav0" / "cam0" / "sensor.yaml")
    body_to_base = dataset.calibration.camera_to_base_matrix @ invert(sensor.camera_to_body)
    frame = list(dataset.frames())[-1]
    # the base's pose is the body's, moved by the fixed body-to-base transform
    np.testing.assert_allclose(frame.ground_truth @ body_to_base, body_pose(frame.index * 0.05), atol=2e-5)
    with pytest.raises(DataError, match=r"mounting on the robot is unknown\. Give dataset\.camera_height"):
        EurocDataset(EurocParams(path=str(root)))


def test_sensor_files_as_opencv_writes_them(tmp_path: Path):
    """EuRoC's sensor.yaml begins with OpenCV's %YAML:1.0, which a YAML parser refuses; the reader takes it,
    and a file OpenCV's FileStorage wrote (its !!opencv-matrix tags) too."""
    with pytest.raises(yaml.YAMLError):
        yaml.safe_load(EUROC_SENSOR)
    root = make_euroc(tmp_path / "seq", frames=4)
    for path in (root / "mav0").rglob("*.yaml"):
        assert path.read_text().startswith("%YAML:1.0\n")
    written = tmp_path / "opencv.yaml"
    camera_to_body = pose_from_xyz_rpy(0.1, -0.05, 0.02, -math.pi / 2, 0.0, -math.pi / 2)
    storage = cv2.FileStorage(str(written), cv2.FILE_STORAGE_WRITE)
    storage.write("T_BS", camera_to_body)
    storage.write("rate_hz", 20)
    for key, values in (("resolution", [320, 240]), ("intrinsics", [300.5, 299.5, 161.0, 119.0])):
        storage.startWriteStruct(key, cv2.FileNode_SEQ)
        for v in values:
            storage.write("", v)
        storage.endWriteStruct()
    storage.write("camera_model", "pinhole")
    storage.write("distortion_model", "radial-tangential")
    storage.startWriteStruct("distortion_coefficients", cv2.FileNode_SEQ)
    for v in (-0.28, 0.07, 0.0002, 0.00002):
        storage.write("", v)
    storage.endWriteStruct()
    storage.release()
    text = written.read_text()
    assert text.startswith("%YAML:1.0") and "!!opencv-matrix" in text
    camera = read_euroc_sensor_yaml(written)
    np.testing.assert_allclose(camera.camera_to_body, camera_to_body, atol=1e-12)
    assert camera.rate_hz == 20.0 and camera.intrinsics.fx == 300.5 and camera.distortion.model == "radtan"


def test_ground_truth_from_a_folder_a_tum_file_or_a_csv_file(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    root = make_euroc(tmp_path / "seq", frames=10)
    mav = root / "mav0"
    params = EurocParams(path=str(root), body_to_base=np.eye(4).tolist())
    expected = [f.ground_truth for f in EurocDataset(params).frames()]
    truth = read_trajectory(mav / "state_groundtruth_estimate0" / "data.csv")
    write_tum(tmp_path / "truth.tum", truth)
    write_euroc_csv(tmp_path / "truth.csv", truth)
    for source in (str(tmp_path / "truth.tum"), str(tmp_path / "truth.csv"), "vicon0"):
        frames = list(EurocDataset(params.model_copy(update={"groundtruth": source})).frames())
        assert len(frames) == len(expected) == 8
        for frame, pose in zip(frames, expected, strict=True):
            np.testing.assert_allclose(frame.ground_truth, pose, atol=1e-8)
    # a folder without its data.csv: named in a warning; the run has no ground truth (nor odometry from it)
    (mav / "state_groundtruth_estimate0" / "data.csv").rename(tmp_path / "moved.csv")
    caplog.set_level(logging.WARNING, logger="sgf_pipeline.datasets")
    with pytest.raises(DataError, match=r"has no ground truth \(state_groundtruth_estimate0\) to use as odometry"):
        EurocDataset(params)
    folder = str(mav / "state_groundtruth_estimate0")
    assert any(folder in r.getMessage() and "has no data.csv" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with_odometry = EurocDataset(params.model_copy(update={"odometry": str(tmp_path / "truth.tum")}))
    assert all(f.ground_truth is None for f in with_odometry.frames())
    assert any("sensor.yaml" in r.getMessage() and folder in r.getMessage() for r in caplog.records)  # what it holds
    with pytest.raises(DataError, match=r"dataset.groundtruth=leica0: no such folder under .*mav0 holds: body.yaml"):
        EurocDataset(params.model_copy(update={"groundtruth": "leica0"}))


def test_sgf_run_on_the_published_layout(tmp_path: Path):
    root = make_euroc(tmp_path / "V1_02_synthetic", frames=12)
    out = tmp_path / "run"
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "sgf-run"),
            "dataset=euroc",
            f"dataset.path={root}",
            "dataset.camera_height=0.6",
            "dataset.camera_tilt=0.4",
            "run.keyframe_distance=0",  # every frame: the drive is 0.5 m
            "run.progress=false",
            f"hydra.run.dir={out}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["dataset"]["name"] == "euroc" and metrics["dataset"]["frames"] == 10
    assert metrics["dataset"]["trimmed"] == 2 and metrics["dataset"]["skipped"] == 0
    assert metrics["ate_rmse_m"]["odometry"] == pytest.approx(0.0, abs=1e-6)  # the odometry is the ground truth
    assert len(read_trajectory(out / "trajectory_gt.tum")) == len(read_trajectory(out / "trajectory_sgf.tum")) == 10
