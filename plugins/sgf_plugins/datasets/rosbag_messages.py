"""What ``dataset=rosbag`` reads from a bag's messages: topic types, camera images, and the camera's mounting from tf.

Raw ``sensor_msgs/Image`` messages are decoded by their encoding (:data:`SUPPORTED_ENCODINGS`),
``CompressedImage`` ones as JPEG or PNG. The camera's mounting on the robot's base is the pose of
the images' ``header.frame_id`` in the base frame of the bag's tf tree (:func:`camera_mounting`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline import DataError
from sgf_pipeline.bags import TF_TYPES, TransformTree, frame_name, topic_rows
from sgf_pipeline.calibration import OPTICAL_TO_BASE
from sgf_plugins.datasets._common import decode_image_bytes

log = logging.getLogger("sgf_pipeline.datasets")

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
IMU_TYPES = ("sensor_msgs/msg/Imu",)
CAMERA_INFO_TYPES = ("sensor_msgs/msg/CameraInfo",)
#: Base frames looked for in the tf tree when ``base_frame`` is not set: REP 120's frame on the ground first.
BASE_FRAMES = ("base_footprint", "base_link")

#: Raw image encodings: channels, bytes per channel, and the OpenCV conversion to RGB (None: keep).
_ENCODINGS: dict[str, tuple[int, int, int | None]] = {
    "mono8": (1, 1, None),
    "8uc1": (1, 1, None),
    "mono16": (1, 2, None),
    "16uc1": (1, 2, None),
    "rgb8": (3, 1, None),
    "bgr8": (3, 1, cv2.COLOR_BGR2RGB),
    "8uc3": (3, 1, cv2.COLOR_BGR2RGB),
    "rgba8": (4, 1, cv2.COLOR_RGBA2RGB),
    "bgra8": (4, 1, cv2.COLOR_BGRA2RGB),
    "8uc4": (4, 1, cv2.COLOR_BGRA2RGB),
    "bayer_rggb8": (1, 1, cv2.COLOR_BayerBG2RGB),
    "bayer_bggr8": (1, 1, cv2.COLOR_BayerRG2RGB),
    "bayer_gbrg8": (1, 1, cv2.COLOR_BayerGR2RGB),
    "bayer_grbg8": (1, 1, cv2.COLOR_BayerGB2RGB),
    "yuv422": (2, 1, cv2.COLOR_YUV2RGB_UYVY),
    "uyvy": (2, 1, cv2.COLOR_YUV2RGB_UYVY),
    "yuv422_yuy2": (2, 1, cv2.COLOR_YUV2RGB_YUY2),
    "yuyv": (2, 1, cv2.COLOR_YUV2RGB_YUY2),
}
SUPPORTED_ENCODINGS = tuple(_ENCODINGS)
_COMPRESSED = ("jpeg", "jpg", "png")


def decode_raw_image(msg: Any, what: str) -> np.ndarray:
    """A ``sensor_msgs/Image`` as uint8 RGB (H, W, 3) or grey (H, W)."""
    encoding = str(msg.encoding).lower()
    if encoding not in _ENCODINGS:
        raise DataError(f"{what}: unknown image encoding {msg.encoding!r}; supported: {', '.join(SUPPORTED_ENCODINGS)}")
    channels, depth, conversion = _ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * depth
    data = np.asarray(msg.data, dtype=np.uint8)
    if height <= 0 or width <= 0 or step < row_bytes:
        raise DataError(f"{what}: inconsistent image header (height {height}, width {width}, step {step}, {encoding})")
    if data.size < step * height:
        raise DataError(f"{what}: truncated image: {data.size} bytes for {height} rows of {step} bytes")
    rows = data[: step * height].reshape(height, step)[:, :row_bytes]
    if depth == 2:
        dtype = ">u2" if msg.is_bigendian else "<u2"
        image16 = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
        return (image16 >> 8).astype(np.uint8)
    image = rows.reshape(height, width, channels) if channels > 1 else rows
    if conversion is None:
        return image.copy()  # own, writable memory rather than a view of the message buffer
    return cv2.cvtColor(np.ascontiguousarray(image), conversion)


def decode_compressed_image(msg: Any, what: str) -> np.ndarray:
    """A ``sensor_msgs/CompressedImage`` (JPEG or PNG) as uint8 RGB or grey."""
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt or (fmt and not any(k in fmt for k in _COMPRESSED)):
        raise DataError(f"{what}: unknown compressed image format {msg.format!r}; supported: JPEG and PNG")
    return decode_image_bytes(np.asarray(msg.data, dtype=np.uint8), what)


def tf_topic_names(reader: Any) -> list[str]:
    """The bag's tf topics (``tf2_msgs/TFMessage``: ``/tf_static``, ``/tf``)."""
    return [r.topic for r in topic_rows(reader) if r.msgtype in TF_TYPES and r.count > 0]


def image_frame_id(reader: Any, topic: str) -> str:
    """The ``header.frame_id`` of a topic's first message ('' when it has none)."""
    connections = [c for c in reader.connections if c.topic == topic]
    for connection, _, raw in reader.messages(connections=connections):
        try:
            return frame_name(reader.deserialize(raw, connection.msgtype).header.frame_id)
        except Exception:  # a corrupt first message: the frames' own reading reports it
            return ""
    return ""


def camera_mounting(
    tree: TransformTree, camera_frame: str, base_frame: str = "", bag: Path | str = "the bag"
) -> tuple[np.ndarray, str]:
    """The camera's optical frame in the base frame from the tf tree, and a sentence saying where it came from.

    ``base_frame`` empty: ``base_footprint`` (REP 120: on the ground under the robot), else
    ``base_link`` (its origin taken to be on the ground). A camera frame named ``*optical*`` is the
    optical frame (REP 103: z forward, x right, y down); another whose z axis points more up than
    its y axis points down is a body frame (x forward, y left, z up), turned to the optical axes.
    """
    hint = (
        "or give the mounting: dataset.camera_height=<m above the ground> (and dataset.camera_tilt=<rad down>) "
        "or dataset.camera_to_base=<4x4 pose of the optical frame in the base frame>"
    )
    if not tree:
        raise DataError(
            f"dataset=rosbag: the camera's mounting is unknown: {bag} has no tf (/tf_static, /tf) to place the "
            f"camera on the robot; {hint.removeprefix('or ')}"
        )
    frames = tree.frames()
    base = base_frame or next((f for f in BASE_FRAMES if f in frames), "")
    if not base:
        raise DataError(
            f"dataset=rosbag: the tf tree of {bag} has neither {' nor '.join(BASE_FRAMES)}; name the robot's base "
            f"frame with dataset.base_frame=<frame> (the frames it has: {', '.join(frames)}), {hint}"
        )
    if not camera_frame:
        raise DataError(
            f"dataset=rosbag: the images carry no header.frame_id, so tf cannot place the camera on {base}; {hint}"
        )
    try:
        pose = tree.fixed_pose(base, camera_frame)
    except DataError as exc:
        raise DataError(f"dataset=rosbag: no camera mounting: {exc}; {hint}") from None
    axes = "optical frame"
    if "optical" not in camera_frame and pose[2, 2] > -pose[2, 1]:
        turn = np.eye(4)
        turn[:3, :3] = OPTICAL_TO_BASE
        pose = pose @ turn
        axes = "body axes (REP 103) turned to the optical frame"
    if not base_frame and base != "base_footprint":
        log.info("dataset=rosbag: the tf tree has no base_footprint; %s's origin is taken to be on the ground", base)
    calibration_height = float(pose[2, 3])
    down = math.degrees(math.asin(max(-1.0, min(1.0, -float(pose[2, 2])))))
    source = (
        f"tf ({', '.join(sorted(tree.topics))}): {camera_frame} in {base}, {axes}: {calibration_height:.3f} m above "
        f"the ground, optical axis {down:.2f} deg below the horizon"
    )
    return pose, source


def quaternion_is_unit(q: np.ndarray) -> bool:
    """Whether ``(x, y, z, w)`` is a finite unit quaternion (to 1 %)."""
    return bool(np.all(np.isfinite(q)) and math.isclose(float(np.linalg.norm(q)), 1.0, abs_tol=1e-2))
