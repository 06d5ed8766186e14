"""Synthetic robot recordings for the adapter tests: frames, and the same frames as ROS bags or a folder."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration, Distortion, Intrinsics
from sgf_pipeline.folder_format import FolderDatasetWriter
from sgf_pipeline.geometry import pose_from_xyz_rpy, quaternion_from_rotation

T0_NS = 1_700_000_000_000_000_000
STEP_NS = 100_000_000  # 10 Hz camera
WIDTH, HEIGHT = 160, 120
HEIGHT_M, TILT = 0.8, 0.3


@dataclass
class RecFrame:
    """One synthetic frame: stamp (ns), RGB image, odometry and ground-truth poses, IMU roll/pitch."""

    ns: int
    image: np.ndarray
    odometry: np.ndarray
    ground_truth: np.ndarray
    roll_pitch: tuple[float, float]

    @property
    def t(self) -> float:
        return (self.ns // 1_000_000_000) + (self.ns % 1_000_000_000) * 1e-9


def calibration(distorted: bool = False) -> Calibration:
    intr = Intrinsics(fx=150.0, fy=150.0, cx=80.0, cy=60.0, width=WIDTH, height=HEIGHT)
    dist = Distortion(model="radtan", coefficients=(-0.2, 0.05, 0.001, -0.001, 0.0)) if distorted else Distortion()
    return Calibration.from_mounting(intr, HEIGHT_M, TILT, dist)


def make_frames(n: int = 12, seed: int = 0, grey: bool = False) -> list[RecFrame]:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        image = rng.integers(0, 256, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)
        cv2.putText(image, str(i), (10, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255), 3)
        if grey:
            image = image[:, :, 1].copy()
        yaw = 0.05 * i
        roll, pitch = 0.01 * math.sin(i), 0.02 * math.cos(i)
        gt = pose_from_xyz_rpy(0.5 * i, 0.1 * i * i / n, 0.0, roll, pitch, yaw)
        odom = pose_from_xyz_rpy(0.52 * i, 0.1 * i * i / n + 0.01 * i, 0.0, roll, pitch, yaw * 1.05)
        frames.append(RecFrame(T0_NS + i * STEP_NS, image, odom, gt, (roll, pitch)))
    return frames


def write_folder(root: Path, frames: list[RecFrame], calib: Calibration, name: str = "synthetic") -> Path:
    writer = FolderDatasetWriter(root, name, calib, rate_hz=10.0)
    for f in frames:
        writer.add(f.t, f.image, f.odometry, imu_roll_pitch=f.roll_pitch, ground_truth=f.ground_truth)
    return writer.close()


def _stamp(types, ns: int):  # type: ignore[no-untyped-def]
    return types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(types, ns: int, frame_id: str, ros1: bool):  # type: ignore[no-untyped-def]
    header = types["std_msgs/msg/Header"]
    if ros1:
        return header(seq=0, stamp=_stamp(types, ns), frame_id=frame_id)
    return header(stamp=_stamp(types, ns), frame_id=frame_id)


def _pose_fields(types, pose: np.ndarray):  # type: ignore[no-untyped-def]
    q = quaternion_from_rotation(pose[:3, :3])
    point = types["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3])
    quat = types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
    return point, quat


def messages(types, frames: list[RecFrame], calib: Calibration, ros1: bool, image_kind: str, gt_kind: str):  # type: ignore[no-untyped-def]
    """(topic, msgtype, ns, message) for every message of the recording, in time order."""
    out = []
    intr, dist = calib.intrinsics, calib.distortion
    k = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], dtype=np.float64)
    d = np.array(dist.coefficients if dist.model != "none" else [0.0] * 5, dtype=np.float64)
    p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    info_type = types["sensor_msgs/msg/CameraInfo"]
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
    info = info_type(
        header=_header(types, frames[0].ns, "camera", ros1),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob",
        binning_x=0,
        binning_y=0,
        roi=roi,
        **dict(zip(names, (d, k, np.eye(3).reshape(-1), p), strict=True)),
    )
    out.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", frames[0].ns, info))
    cov36 = np.zeros(36)
    cov9 = np.zeros(9)
    for f in frames:
        header = _header(types, f.ns, "camera", ros1)
        if image_kind == "compressed_png":
            ok, png = cv2.imencode(".png", f.image if f.image.ndim == 2 else cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
            assert ok
            msg = types["sensor_msgs/msg/CompressedImage"](header=header, format="png", data=png.reshape(-1))
            out.append(("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", f.ns, msg))
        else:
            encoding = "mono8" if f.image.ndim == 2 else image_kind
            data = f.image if encoding in ("mono8", "rgb8") else cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR)
            channels = 1 if data.ndim == 2 else 3
            msg = types["sensor_msgs/msg/Image"](
                header=header,
                height=HEIGHT,
                width=WIDTH,
                encoding=encoding,
                is_bigendian=0,
                step=WIDTH * channels,
                data=np.ascontiguousarray(data).reshape(-1),
            )
            out.append(("/camera/image_raw", "sensor_msgs/msg/Image", f.ns, msg))
        point, quat = _pose_fields(types, f.odometry)
        pose = types["geometry_msgs/msg/Pose"](position=point, orientation=quat)
        twist = types["geometry_msgs/msg/Twist"](
            linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        )
        odom = types["nav_msgs/msg/Odometry"](
            header=_header(types, f.ns, "odom", ros1),
            child_frame_id="base_link",
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov36),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov36),
        )
        out.append(("/odom", "nav_msgs/msg/Odometry", f.ns, odom))
        imu_q = quaternion_from_rotation(pose_from_xyz_rpy(0, 0, 0, f.roll_pitch[0], f.roll_pitch[1], 0.3)[:3, :3])
        vec = types["geometry_msgs/msg/Vector3"]
        imu = types["sensor_msgs/msg/Imu"](
            header=_header(types, f.ns, "imu", ros1),
            orientation=types["geometry_msgs/msg/Quaternion"](x=imu_q[0], y=imu_q[1], z=imu_q[2], w=imu_q[3]),
            orientation_covariance=cov9,
            angular_velocity=vec(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=cov9,
            linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=cov9,
        )
        out.append(("/imu/data", "sensor_msgs/msg/Imu", f.ns, imu))
        point, quat = _pose_fields(types, f.ground_truth)
        if gt_kind == "pose":
            gt = types["geometry_msgs/msg/PoseStamped"](
                header=_header(types, f.ns, "map", ros1),
                pose=types["geometry_msgs/msg/Pose"](position=point, orientation=quat),
            )
            out.append(("/ground_truth", "geometry_msgs/msg/PoseStamped", f.ns, gt))
        else:
            gt = types["geometry_msgs/msg/TransformStamped"](
                header=_header(types, f.ns, "map", ros1),
                child_frame_id="base_link",
                transform=types["geometry_msgs/msg/Transform"](
                    translation=vec(x=point.x, y=point.y, z=point.z), rotation=quat
                ),
            )
            out.append(("/ground_truth", "geometry_msgs/msg/TransformStamped", f.ns, gt))
    return out


def write_bag(
    path: Path,
    frames: list[RecFrame],
    calib: Calibration,
    version: str = "ros2_sqlite3",
    image_kind: str = "rgb8",
    gt_kind: str = "pose",
    corrupt: dict[tuple[str, int], bytes] | None = None,
    extra: list[tuple[str, str, int, object]] | None = None,
) -> Path:
    """Write the frames as a bag: ``ros1``, ``ros2_sqlite3`` or ``ros2_mcap``.

    ``corrupt`` replaces the serialized bytes of (topic, n-th message on it); ``extra`` adds messages.
    """
    store = typestore(version)
    msgs = messages(store.types, frames, calib, version == "ros1", image_kind, gt_kind) + list(extra or [])
    return write_messages(path, msgs, version, corrupt)


def typestore(version: str = "ros2_sqlite3"):  # type: ignore[no-untyped-def]
    """The rosbags typestore of a bag version (ROS 1 Noetic or ROS 2 Humble)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if version == "ros1" else Stores.ROS2_HUMBLE)


def write_messages(
    path: Path,
    msgs: list[tuple[str, str, int, object]],
    version: str = "ros2_sqlite3",
    corrupt: dict[tuple[str, int], bytes] | None = None,
) -> Path:
    """Write ``(topic, msgtype, receive ns, message)`` in receive-time order as a bag of ``version``."""
    ros1 = version == "ros1"
    store = typestore(version)
    msgs = sorted(msgs, key=lambda m: m[2])
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer1 = Writer1(path)
        writer1.open()
        writer: object = writer1
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if version == "ros2_mcap" else StoragePlugin.SQLITE3
        writer2 = Writer2(path, version=9, storage_plugin=plugin)
        writer2.open()
        writer = writer2
    connections: dict[str, object] = {}
    counts: dict[str, int] = {}
    try:
        for topic, msgtype, ns, msg in msgs:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)  # type: ignore[attr-defined]
            raw = store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)
            n = counts.get(topic, 0)
            counts[topic] = n + 1
            if corrupt and (topic, n) in corrupt:
                raw = corrupt[(topic, n)]
            writer.write(connections[topic], ns, bytes(raw))  # type: ignore[attr-defined]
    finally:
        writer.close()  # type: ignore[attr-defined]
    return path


def pose_stamped(types, ns: int, frame_id: str, pose: np.ndarray, ros1: bool = False):  # type: ignore[no-untyped-def]
    """A geometry_msgs/PoseStamped of a 4x4 pose."""
    point, quat = _pose_fields(types, pose)
    return types["geometry_msgs/msg/PoseStamped"](
        header=_header(types, ns, frame_id, ros1),
        pose=types["geometry_msgs/msg/Pose"](position=point, orientation=quat),
    )


def odometry_message(types, ns: int, frame_id: str, child: str, pose: np.ndarray, ros1: bool = False):  # type: ignore[no-untyped-def]
    """A nav_msgs/Odometry of a 4x4 pose (zero twist and covariances)."""
    point, quat = _pose_fields(types, pose)
    vec = types["geometry_msgs/msg/Vector3"]
    twist = types["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
    return types["nav_msgs/msg/Odometry"](
        header=_header(types, ns, frame_id, ros1),
        child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](position=point, orientation=quat), covariance=np.zeros(36)
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def transform_stamped(types, ns: int, parent: str, child: str, pose: np.ndarray, ros1: bool = False):  # type: ignore[no-untyped-def]
    """A geometry_msgs/TransformStamped: ``child``'s pose in ``parent``."""
    point, quat = _pose_fields(types, pose)
    vec = types["geometry_msgs/msg/Vector3"]
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(types, ns, parent, ros1),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](translation=vec(x=point.x, y=point.y, z=point.z), rotation=quat),
    )


def tf_message(types, transforms: list[object]):  # type: ignore[no-untyped-def]
    """A tf2_msgs/TFMessage of TransformStamped messages."""
    return types["tf2_msgs/msg/TFMessage"](transforms=transforms)


def rosbag_overrides(path: Path, image_topic: str = "/camera/image_raw") -> list[str]:
    """Hydra overrides that read a bag written by :func:`write_bag`."""
    return [
        "dataset=rosbag",
        f"dataset.path={path}",
        f"dataset.image_topic={image_topic}",
        "dataset.odometry_topic=/odom",
        "dataset.imu_topic=/imu/data",
        "dataset.ground_truth_topic=/ground_truth",
        "dataset.camera_info_topic=/camera/camera_info",
        f"dataset.camera_height={HEIGHT_M}",
        f"dataset.camera_tilt={TILT}",
    ]
