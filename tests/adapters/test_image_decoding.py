"""Decoding ROS image messages: raw encodings (RGB, BGR, mono, 16-bit, Bayer, YUV) and compressed JPEG/PNG."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from sgf_plugins.datasets._common import decode_image_bytes
from sgf_plugins.datasets.rosbag_messages import decode_compressed_image, decode_raw_image

from sgf_pipeline import DataError

from .recordings import calibration, make_frames, write_bag

RNG = np.random.default_rng(11)
RGB = RNG.integers(0, 256, (6, 8, 3), dtype=np.uint8)


def _msg(encoding: str, data: np.ndarray, width: int = 8, height: int = 6, step: int | None = None, big: int = 0):
    flat = np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    return SimpleNamespace(
        encoding=encoding, width=width, height=height, step=step or flat.size // height, is_bigendian=big, data=flat
    )


def test_colour_and_grey_encodings():
    decoded = decode_raw_image(_msg("rgb8", RGB), "t")
    assert np.array_equal(decoded, RGB) and decoded.flags.writeable and decoded.flags.c_contiguous
    assert np.array_equal(decode_raw_image(_msg("bgr8", RGB[:, :, ::-1]), "t"), RGB)
    rgba = np.concatenate([RGB, np.full((6, 8, 1), 255, np.uint8)], axis=2)
    assert np.array_equal(decode_raw_image(_msg("rgba8", rgba), "t"), RGB)
    assert np.array_equal(decode_raw_image(_msg("bgra8", rgba[:, :, [2, 1, 0, 3]]), "t"), RGB)
    grey = RGB[:, :, 0]
    assert np.array_equal(decode_raw_image(_msg("mono8", grey), "t"), grey)
    # rows padded to a 16-byte step
    padded = np.zeros((6, 16), np.uint8)
    padded[:, :8] = grey
    assert np.array_equal(decode_raw_image(_msg("mono8", padded, step=16), "t"), grey)


def test_sixteen_bit_in_both_byte_orders():
    values = (RGB[:, :, 0].astype(np.uint16) << 8) | 0x5A
    assert np.array_equal(decode_raw_image(_msg("mono16", values.astype("<u2")), "t"), RGB[:, :, 0])
    assert np.array_equal(decode_raw_image(_msg("mono16", values.astype(">u2"), big=1), "t"), RGB[:, :, 0])


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_patterns_give_the_right_colour(pattern: str):
    colour = np.array([200, 120, 40], np.uint8)  # a flat orange scene
    channel = {"r": 0, "g": 1, "b": 2}
    mosaic = np.zeros((8, 8), np.uint8)
    for dy in (0, 1):
        for dx in (0, 1):
            mosaic[dy::2, dx::2] = colour[channel[pattern[2 * dy + dx]]]
    image = decode_raw_image(_msg(f"bayer_{pattern}8", mosaic, width=8, height=8), "t")
    assert image.shape == (8, 8, 3)
    np.testing.assert_array_equal(image[2:6, 2:6].reshape(-1, 3), np.tile(colour, (16, 1)))


def test_yuv422_uyvy_and_yuyv():
    colour = np.array([[[30, 160, 220]]], np.uint8)
    r, g, b = (float(c) for c in colour[0, 0])
    # BT.601 video-range Y'CbCr, what YUV 4:2:2 cameras send
    y = round(16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255)
    u = round(128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255)
    v = round(128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255)
    uyvy = np.tile(np.array([u, y, v, y], np.uint8), (6, 4))  # 8 pixels per row, 2 bytes each
    yuyv = np.tile(np.array([y, u, y, v], np.uint8), (6, 4))
    for encoding, data in (("yuv422", uyvy), ("uyvy", uyvy), ("yuv422_yuy2", yuyv)):
        image = decode_raw_image(_msg(encoding, data), "t")
        assert image.shape == (6, 8, 3)
        assert np.abs(image.astype(int) - colour.astype(int)).max() <= 2, encoding


def test_compressed_jpeg_and_png_and_bad_data():
    ok, png = cv2.imencode(".png", RGB[:, :, ::-1])
    assert ok
    msg = SimpleNamespace(format="rgb8; png compressed bgr8", data=png.reshape(-1))
    assert np.array_equal(decode_compressed_image(msg, "t"), RGB)
    smooth = cv2.GaussianBlur(np.repeat(np.repeat(RGB, 8, 0), 8, 1), (9, 9), 3)
    ok, jpeg = cv2.imencode(".jpg", smooth[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    decoded = decode_compressed_image(SimpleNamespace(format="jpeg", data=jpeg.reshape(-1)), "t")
    assert np.abs(decoded.astype(int) - smooth.astype(int)).mean() < 3.0
    with pytest.raises(DataError, match=r"t: the JPEG has no end marker \(truncated\)"):
        decode_compressed_image(SimpleNamespace(format="jpeg", data=jpeg.reshape(-1)[:-200]), "t")
    with pytest.raises(DataError, match="unknown compressed image format 'compressedDepth png'"):
        decode_compressed_image(SimpleNamespace(format="compressedDepth png", data=png.reshape(-1)), "t")
    with pytest.raises(DataError, match="cannot decode the image"):
        decode_image_bytes(b"not an image at all", "t")
    with pytest.raises(DataError, match=r"truncated image: 40 bytes for 6 rows of 24 bytes"):
        decode_raw_image(_msg("rgb8", RGB.reshape(-1)[:40], step=24), "t")


def test_sgf_bag_info_lists_topics(tmp_path: Path):
    bag = write_bag(tmp_path / "drive", make_frames(5, seed=1), calibration(), "ros2_mcap")
    bin_dir = Path(sys.executable).parent
    proc = subprocess.run(
        [str(bin_dir / "sgf-bag-info"), f"path={bag}"], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "ROS 2 bag, MCAP, 0.4 s, 21 messages" in out
    lines = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.startswith("  /")}
    assert lines["/camera/image_raw"] == ["sensor_msgs/msg/Image", "5", "10.0"]
    assert lines["/odom"] == ["nav_msgs/msg/Odometry", "5", "10.0"]
    assert lines["/camera/camera_info"] == ["sensor_msgs/msg/CameraInfo", "1", "-"]
    assert "dataset.image_topic=/camera/image_raw" in out and "dataset.imu_topic=/imu/data" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive"]  # no Hydra output folder
    missing = subprocess.run(
        [str(bin_dir / "sgf-bag-info"), f"path={tmp_path / 'nope.bag'}"], capture_output=True, text=True, timeout=120
    )
    assert missing.returncode == 2 and "bag not found" in missing.stderr
