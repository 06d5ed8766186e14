"""Synthetic robot recordings for the adapter tests: frames, and the same frames as ROS bags or a folder."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration, Distortion, Intrinsics
from sgf_pipeline.folder_format import FolderDatasetWriter
from sgf_pipeline.geometry import invert, pose_from_xyz_rpy, quaternion_from_rotation

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


# -- six real KITTI frames as a ROS 2 bag, the camera placed by /tf_static --------------------------------

KITTI_K = (718.856, 718.856, 607.1928, 185.2157)
#: The KITTI camera on the car: 1.65 m above the road, 0.27 m ahead of base_link's origin, 1 degree down.
KITTI_TILT = math.radians(1.0)


def kitti_mounting() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(footprint -> base_link, base_link -> camera_link, camera_link -> camera_optical_frame)`` poses.

    base_link sits 0.3 m above base_footprint (REP 120's frame on the road); camera_link has REP 103
    body axes (x forward, y left, z up), pitched 1 degree down; the optical frame turns them to z
    forward, x right, y down, as a URDF's camera joint does.
    """
    footprint_link = pose_from_xyz_rpy(0.0, 0.0, 0.3, 0.0, 0.0, 0.0)
    link_camera = pose_from_xyz_rpy(0.27, 0.0, 1.35, 0.0, KITTI_TILT, 0.0)
    camera_optical = pose_from_xyz_rpy(0.0, 0.0, 0.0, -math.pi / 2, 0.0, -math.pi / 2)
    return footprint_link, link_camera, camera_optical


def write_kitti_bag(path: Path, kitti: Path, image_frame: str = "camera_optical_frame", stamp_offset: int = 0) -> Path:
    """KITTI 00's first six frames as a ROS 2 bag: /camera/image_raw (mono8), /camera/camera_info, /odom,
    /imu, /ground_truth and the camera's mounting on /tf_static; nothing tells the mounting otherwise.

    The odometry and ground truth are the base_footprint poses of KITTI's ground truth (the camera
    poses moved through the mounting); ``image_frame`` is the images' ``header.frame_id``
    (``camera_optical_frame`` or the body-axes ``camera_link``).
    """
    types = typestore().types
    footprint_link, link_camera, camera_optical = kitti_mounting()
    camera_to_base = footprint_link @ link_camera @ camera_optical
    camera_poses = np.loadtxt(kitti / "poses_00_first6.txt").reshape(-1, 3, 4)
    seconds = np.loadtxt(kitti / "times_00_first6.txt")
    t0 = T0_NS + stamp_offset
    msgs: list[tuple[str, str, int, object]] = []
    statics = [
        transform_stamped(types, t0, "base_footprint", "base_link", footprint_link),
        transform_stamped(types, t0, "base_link", "camera_link", link_camera),
        transform_stamped(types, t0, "camera_link", "camera_optical_frame", camera_optical),
    ]
    msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", t0, tf_message(types, statics)))
    fx, fy, cx, cy = KITTI_K
    info = types["sensor_msgs/msg/CameraInfo"](
        header=_header(types, t0, image_frame, False),
        height=376,
        width=1241,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3).reshape(-1),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    vec = types["geometry_msgs/msg/Vector3"]
    for i, (pose34, s) in enumerate(zip(camera_poses, seconds, strict=True)):
        ns = t0 + round(float(s) * 1e9)
        camera = np.vstack([pose34, [0.0, 0.0, 0.0, 1.0]])
        base = camera_to_base @ camera @ invert(camera_to_base)
        grey = cv2.imread(str(kitti / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        image = types["sensor_msgs/msg/Image"](
            header=_header(types, ns, image_frame, False),
            height=376,
            width=1241,
            encoding="mono8",
            is_bigendian=0,
            step=1241,
            data=grey.reshape(-1),
        )
        msgs.append(("/camera/image_raw", "sensor_msgs/msg/Image", ns, image))
        if i == 0:
            msgs.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", ns, info))
        msgs.append(("/odom", "nav_msgs/msg/Odometry", ns, odometry_message(types, ns, "odom", "base_footprint", base)))
        msgs.append(("/ground_truth", "geometry_msgs/msg/PoseStamped", ns, pose_stamped(types, ns, "map", base)))
        q = quaternion_from_rotation(base[:3, :3])
        imu = types["sensor_msgs/msg/Imu"](
            header=_header(types, ns, "base_footprint", False),
            orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            orientation_covariance=np.zeros(9),
            angular_velocity=vec(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9),
        )
        msgs.append(("/imu", "sensor_msgs/msg/Imu", ns, imu))
    return write_messages(path, msgs, "ros2_mcap")
