"""dataset=euroc on a synthetic recording in the EuRoC/ASL layout."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from sgf_plugins.datasets.euroc import EurocDataset, EurocParams

from sgf_pipeline.calibration_io import read_euroc_sensor_yaml
from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import DataError
from sgf_pipeline.geometry import invert, pose_from_xyz_rpy, quaternion_from_rotation
from sgf_pipeline.imu import GRAVITY
from sgf_pipeline.undistortion import Undistorter

from .test_calibration_io import EUROC_SENSOR

T0 = 1_403_636_579_000_000_000
CAM_NS = 50_000_000  # 20 Hz


def body_pose(s: float) -> np.ndarray:
    """The body's pose at time s (seconds since T0): driving a gentle curve, rocking a little."""
    return pose_from_xyz_rpy(1.0 * s, 0.1 * s * s, 0.0, 0.03 * math.sin(2 * s), 0.02 * math.sin(3 * s), 0.1 * s)


def make_euroc(root: Path, frames: int = 20) -> Path:
    mav = root / "mav0"
    (mav / "cam0" / "data").mkdir(parents=True)
    (mav / "imu0").mkdir()
    (mav / "state_groundtruth_estimate0").mkdir()
    (mav / "cam0" / "sensor.yaml").write_text(EUROC_SENSOR)
    rng = np.random.default_rng(4)
    rows = ["#timestamp [ns],filename"]
    for i in range(frames):
        ns = T0 + i * CAM_NS
        cv2.imwrite(str(mav / "cam0" / "data" / f"{ns}.png"), rng.integers(0, 256, (240, 320), dtype=np.uint8))
        rows.append(f"{ns},{ns}.png")
    (mav / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    # ground truth at 200 Hz, starting 0.12 s after the first image (as in EuRoC, the camera starts first)
    gt = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    imu = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y,w_RS_S_z,a_RS_S_x [m s^-2],a_RS_S_y,a_RS_S_z"]
    step = 5_000_000
    for k in range(24, frames * 10 + 10):
        ns = T0 + k * step
        s = (ns - T0) / 1e9
        pose = body_pose(s)
        q = quaternion_from_rotation(pose[:3, :3])
        x, y, z = pose[:3, 3]
        gt.append(f"{ns},{x:.9f},{y:.9f},{z:.9f},{q[3]:.9f},{q[0]:.9f},{q[1]:.9f},{q[2]:.9f}")
    for k in range(0, frames * 10 + 10):
        ns = T0 + k * step
        s = (ns - T0) / 1e9
        r0, r1 = body_pose(s)[:3, :3], body_pose(s + 1e-4)[:3, :3]
        delta = r0.T @ r1
        omega = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]]) / 2e-4
        accel = r0.T @ np.array([0.0, 0.0, GRAVITY])  # centripetal terms are small here
        imu.append(f"{ns}," + ",".join(f"{v:.9f}" for v in (*omega, *accel)))
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(gt) + "\n")
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
