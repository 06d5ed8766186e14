"""Calibration readers (KITTI calib.txt, EuRoC sensor.yaml, ROS CameraInfo) and lens undistortion."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sgf_pipeline.calibration import Calibration, Distortion, Intrinsics, camera_to_base_from_mounting
from sgf_pipeline.calibration_io import (
    calibration_from_camera_info,
    distortion_from_name,
    image_size,
    intrinsics_from_projection,
    kitti_projection,
    read_euroc_sensor_yaml,
    read_kitti_calib,
)
from sgf_pipeline.errors import DataError
from sgf_pipeline.undistortion import Undistorter

KITTI_CALIB = """P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 \
7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 \
0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 \
7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 \
0.000000000000e+00
Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27
"""

# An EuRoC camera sensor.yaml as the sequences ship it: OpenCV's YAML header first.
EUROC_SENSOR = """%YAML:1.0
# General sensor definitions.
sensor_type: camera
comment: test camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0, -1.0, 0.0, -0.02,
         1.0, 0.0, 0.0, -0.06,
         0.0, 0.0, 1.0, 0.01,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [320, 240]
camera_model: pinhole
intrinsics: [300.5, 299.5, 161.0, 119.0] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]
"""


def test_kitti_calib_p0(tmp_path: Path, shared_data: Path):
    (tmp_path / "calib.txt").write_text(KITTI_CALIB)
    matrices = read_kitti_calib(tmp_path / "calib.txt")
    assert sorted(matrices) == ["P0", "P1", "Tr"]
    width, height = image_size(shared_data / "kitti00_first6" / "image_0" / "000000.png")
    assert (width, height) == (1241, 376)
    intr = intrinsics_from_projection(kitti_projection(matrices, 0), width, height)
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (718.856, 718.856, 607.1928, 185.2157)
    assert -matrices["P1"][0, 3] / matrices["P1"][0, 0] == pytest.approx(0.5372, abs=1e-4)  # the stereo baseline
    with pytest.raises(DataError, match=r"has no projection of camera 2 \(P2\); it has: \['P0', 'P1', 'Tr'\]"):
        kitti_projection(matrices, 2)


def test_image_size_of_jpeg_without_decoding(tmp_path: Path):
    ok, data = cv2.imencode(".jpg", np.zeros((37, 53, 3), np.uint8))
    assert ok
    (tmp_path / "a.jpg").write_bytes(data.tobytes())
    assert image_size(tmp_path / "a.jpg") == (53, 37)


def test_euroc_sensor_yaml(tmp_path: Path):
    (tmp_path / "sensor.yaml").write_text(EUROC_SENSOR)
    cam = read_euroc_sensor_yaml(tmp_path / "sensor.yaml")
    assert cam.intrinsics == Intrinsics(fx=300.5, fy=299.5, cx=161.0, cy=119.0, width=320, height=240)
    assert cam.distortion == Distortion(model="radtan", coefficients=(-0.28, 0.07, 0.0002, 0.00002))
    assert cam.camera_to_body[:3, 3].tolist() == [-0.02, -0.06, 0.01]
    assert cam.rate_hz == 20.0
    (tmp_path / "fish.yaml").write_text(
        EUROC_SENSOR.replace("radial-tangential", "equidistant").replace("0.0002, 0.00002", "0.001, -0.0003")
    )
    assert read_euroc_sensor_yaml(tmp_path / "fish.yaml").distortion.model == "equidistant"
    (tmp_path / "omni.yaml").write_text(EUROC_SENSOR.replace("camera_model: pinhole", "camera_model: omni"))
    with pytest.raises(DataError, match="camera_model 'omni' is not supported"):
        read_euroc_sensor_yaml(tmp_path / "omni.yaml")


def test_camera_info_models():
    mount = camera_to_base_from_mounting(0.8, 0.2)
    k = [400.0, 0.0, 320.0, 0.0, 401.0, 240.0, 0.0, 0.0, 1.0]
    plumb = calibration_from_camera_info(640, 480, k, [-0.3, 0.1, 0.001, 0.002, -0.02], "plumb_bob", mount)
    assert plumb.intrinsics.fy == 401.0 and plumb.distortion.model == "radtan"
    assert plumb.height == pytest.approx(0.8) and plumb.tilt == pytest.approx(0.2)
    rational = calibration_from_camera_info(640, 480, k, [0.1] * 8, "rational_polynomial", mount)
    assert len(rational.distortion.coefficients) == 8
    fisheye = calibration_from_camera_info(640, 480, k, [0.1, 0.01, 0.0, 0.0], "equidistant", mount)
    assert fisheye.distortion.model == "equidistant"
    assert calibration_from_camera_info(640, 480, k, [0.0] * 5, "plumb_bob", mount).distortion.is_identity
    with pytest.raises(DataError, match=r"unknown distortion model 'double_sphere'; supported: .*plumb_bob"):
        calibration_from_camera_info(640, 480, k, [0.1], "double_sphere", mount)
    with pytest.raises(DataError, match=r"K must hold 9 finite numbers with fx, fy > 0"):
        calibration_from_camera_info(640, 480, [0.0] * 9, [], "", mount)
    with pytest.raises(DataError, match=r"equidistant .* takes 4 coefficients"):
        distortion_from_name("fisheye", [0.1, 0.2, 0.3])


def _blob_image(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A float image with a Gaussian blob (sigma 1.5 px) at each point."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    image = np.zeros((h, w))
    for u, v in points:
        image += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.5**2))
    return image


def _centroids(image: np.ndarray, points: np.ndarray, radius: int = 5) -> np.ndarray:
    out = []
    for u, v in points:
        u0, v0 = round(u), round(v)
        patch = image[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1].astype(np.float64)
        yy, xx = np.mgrid[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1]
        out.append(((patch * xx).sum() / patch.sum(), (patch * yy).sum() / patch.sum()))
    return np.asarray(out)


@pytest.mark.parametrize("model", ["radtan", "equidistant"])
def test_undistortion_puts_points_where_the_pinhole_sees_them(model: str):
    size = (320, 240)
    intr = Intrinsics(fx=220.0, fy=220.0, cx=161.0, cy=119.0, width=size[0], height=size[1])
    coeffs = (-0.3, 0.09, 0.001, -0.0008, 0.0) if model == "radtan" else (0.08, -0.02, 0.004, -0.001)
    calib = Calibration(
        intrinsics=intr,
        distortion=Distortion(model=model, coefficients=coeffs),  # type: ignore[arg-type]
        camera_to_base=camera_to_base_from_mounting(0.8, 0.2),
    )
    k, d = intr.matrix, np.asarray(coeffs)
    us, vs = np.meshgrid(np.linspace(40, 280, 7), np.linspace(35, 205, 5))
    ideal_points = np.stack([us.ravel(), vs.ravel()], axis=1)
    # Render what the distorted lens sees: each distorted pixel looks at the ideal pixel it undistorts to.
    grid = np.stack(np.meshgrid(np.arange(size[0]), np.arange(size[1])), axis=-1).reshape(-1, 1, 2).astype(np.float64)
    if model == "radtan":
        undist = cv2.undistortPointsIter(
            grid, k, d, None, k, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        )
    else:
        undist = cv2.fisheye.undistortPoints(grid, k, d.reshape(4, 1), P=k)
    maps = undist.reshape(size[1], size[0], 2).astype(np.float32)
    ideal = _blob_image(ideal_points, size)
    distorted = cv2.remap((ideal * 200).astype(np.float32), maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
    distorted_u8 = np.clip(distorted, 0, 255).astype(np.uint8)
    # the distortion is real: in the raw image the corner blobs are not at their pinhole places
    for u, v in ideal_points[[0, 6, 28, 34]].astype(int):
        assert (
            distorted_u8[v - 2 : v + 3, u - 2 : u + 3].sum() < 0.2 * (ideal[v - 2 : v + 3, u - 2 : u + 3] * 200).sum()
        )

    undistorter = Undistorter(calib)
    assert undistorter.active and undistorter.calibration.distortion.is_identity
    assert undistorter.calibration.intrinsics == intr  # K is kept
    restored = undistorter(distorted_u8)
    error = np.linalg.norm(_centroids(restored, ideal_points) - ideal_points, axis=1)
    assert error.max() < 0.25, error


def test_undistorter_passes_pinhole_images_and_refuses_other_sizes():
    intr = Intrinsics(fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100, height=80)
    plain = Undistorter(Calibration.from_mounting(intr, 1.0, 0.1))
    image = np.full((80, 100), 7, np.uint8)
    assert not plain.active and plain(image) is image
    lens = Undistorter(
        Calibration.from_mounting(intr, 1.0, 0.1, Distortion(model="radtan", coefficients=(0.1, 0, 0, 0)))
    )
    with pytest.raises(DataError, match="image of 120x80 px but the calibration is for 100x80 px"):
        lens(np.zeros((80, 120), np.uint8))
    assert lens(np.zeros((80, 100, 3), np.uint8)).shape == (80, 100, 3)
    assert math.isclose(lens.calibration.tilt, 0.1)
