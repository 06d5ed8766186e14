"""Reading speed of the dataset adapters: ROS 2 / ROS 1 bags of 640x480 images, and the folder format.

Writes each recording into a temporary folder, then times building the adapter (indexing odometry
and IMU) plus streaming every frame with its image decoded, as the runner does on keyframes.

    .venv/bin/python bench/bench_adapters.py [--frames 1000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from sgf_plugins.datasets.folder import FolderDataset, FolderParams
from sgf_plugins.datasets.rosbag import RosbagDataset, RosbagParams

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.folder_format import FolderDatasetWriter
from sgf_pipeline.geometry import pose_from_xyz_rpy, quaternion_from_rotation

W, H = 640, 480
T0 = 1_700_000_000_000_000_000
CAMERA_NS = 33_333_333  # 30 Hz


def scene(i: int) -> np.ndarray:
    """A textured 640x480 RGB ground image that moves a little every frame."""
    yy, xx = np.mgrid[0:H, 0:W]
    base = ((xx + 3 * i) // 40 + (yy + 5 * i) // 40) % 2 * 60 + 90
    image = np.stack([base, base + 20, base + 40], axis=-1).astype(np.uint8)
    cv2.putText(image, f"{i:05d}", (200, 260), cv2.FONT_HERSHEY_SIMPLEX, 3.0, (250, 250, 250), 6)
    return image


def calibration() -> Calibration:
    intr = Intrinsics(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=W, height=H)
    return Calibration.from_mounting(intr, 0.6, 0.35)


def write_bag(path: Path, frames: int, version: str, compressed: bool) -> None:
    """A bag with a 30 Hz camera, 50 Hz odometry and 100 Hz IMU."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = version == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    t = store.types

    def header(ns: int, frame_id: str):
        stamp = t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return (
            t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
            if ros1
            else t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)
        )

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer: object = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if version == "ros2_mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    writer.open()  # type: ignore[attr-defined]
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    conns = {
        "image": writer.add_connection("/camera/image", image_type, typestore=store),  # type: ignore[attr-defined]
        "odom": writer.add_connection("/odom", "geometry_msgs/msg/PoseStamped", typestore=store),  # type: ignore[attr-defined]
        "imu": writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store),  # type: ignore[attr-defined]
    }
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    duration = frames * CAMERA_NS
    events: list[tuple[int, str, int]] = [(T0 + i * CAMERA_NS, "image", i) for i in range(frames)]
    events += [(T0 - 10_000_000 + k * 20_000_000, "odom", k) for k in range(duration // 20_000_000 + 2)]
    events += [(T0 - 10_000_000 + k * 10_000_000, "imu", k) for k in range(duration // 10_000_000 + 2)]
    vec = t["geometry_msgs/msg/Vector3"]
    for ns, kind, i in sorted(events):
        if kind == "image":
            image = scene(i)
            if compressed:
                ok, data = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
                assert ok
                msg = t[image_type](header=header(ns, "camera"), format="jpeg", data=data.reshape(-1))
            else:
                msg = t[image_type](
                    header=header(ns, "camera"),
                    height=H,
                    width=W,
                    encoding="rgb8",
                    is_bigendian=0,
                    step=3 * W,
                    data=image.reshape(-1),
                )
        elif kind == "odom":
            s = (ns - T0) / 1e9
            pose = pose_from_xyz_rpy(1.2 * s, 0.3 * math.sin(s), 0.0, 0.0, 0.0, 0.1 * s)
            q = quaternion_from_rotation(pose[:3, :3])
            msg = t["geometry_msgs/msg/PoseStamped"](
                header=header(ns, "odom"),
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=0.0),
                    orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
        else:
            msg = t["sensor_msgs/msg/Imu"](
                header=header(ns, "imu"),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=vec(x=0.0, y=0.0, z=0.1),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9),
            )
        writer.write(conns[kind], ns, bytes(serialize(msg, msg.__msgtype__)))  # type: ignore[attr-defined]
    writer.close()  # type: ignore[attr-defined]


def write_folder(path: Path, frames: int, image_format: str) -> None:
    writer = FolderDatasetWriter(path, "bench", calibration(), rate_hz=30.0, image_format=image_format)
    for i in range(frames):
        s = i * CAMERA_NS / 1e9
        writer.add(T0 / 1e9 + s, scene(i), pose_from_xyz_rpy(1.2 * s, 0.0, 0.0, 0.0, 0.0, 0.1 * s), (0.0, 0.0))
    writer.close()


def read_all(make: Callable[[], object]) -> tuple[float, int]:
    """Seconds to build the adapter and stream every frame with its image decoded."""
    start = time.perf_counter()
    dataset = make()
    count = 0
    for frame in dataset.frames():  # type: ignore[attr-defined]
        image = frame.image
        assert image.shape == (H, W, 3)
        count += 1
    return time.perf_counter() - start, count


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3, help="best of this many reads")
    args = parser.parse_args()
    print(f"# bench_adapters: {args.frames} frames of {W}x{H} RGB, best of {args.repeat} reads (warm file cache)")
    print(f"# {platform.processor() or platform.machine()}, {platform.platform()}, OpenCV {cv2.__version__}")
    print(f"# {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at start (the machine is shared)")
    calib = calibration()
    cases: list[tuple[str, str, bool]] = [
        ("ROS 2 sqlite3, sensor_msgs/Image rgb8", "ros2_sqlite3", False),
        ("ROS 2 MCAP, sensor_msgs/Image rgb8", "ros2_mcap", False),
        ("ROS 1, sensor_msgs/Image rgb8", "ros1", False),
        ("ROS 2 MCAP, CompressedImage JPEG q90", "ros2_mcap", True),
        ("folder, PNG", "folder_png", False),
        ("folder, JPEG", "folder_jpg", False),
    ]
    rows = []
    with tempfile.TemporaryDirectory(prefix="sgf_bench_") as tmp:
        calibration_file = Path(tmp) / "calibration.yaml"
        import yaml

        from sgf_pipeline.folder_format import calibration_to_dict

        calibration_file.write_text(yaml.safe_dump(calibration_to_dict(calib)))
        for label, kind, compressed in cases:
            path = Path(tmp) / (kind + (".bag" if kind == "ros1" else ""))
            t0 = time.perf_counter()
            if kind.startswith("folder"):
                write_folder(path, args.frames, kind.split("_")[1])

                def make(path: Path = path, compressed: bool = False) -> object:
                    return FolderDataset(FolderParams(path=str(path)))

            else:
                write_bag(path, args.frames, kind, compressed)

                def make(path: Path = path, compressed: bool = compressed) -> object:
                    return RosbagDataset(
                        RosbagParams(
                            path=str(path),
                            image_topic="/camera/image",
                            odometry_topic="/odom",
                            imu_topic="/imu",
                            calibration_file=str(calibration_file),
                        )
                    )

            written = time.perf_counter() - t0
            best = math.inf
            for _ in range(args.repeat):
                seconds, count = read_all(make)
                assert count == args.frames, (label, count)
                best = min(best, seconds)
            rows.append((label, size_mb(path), written, best, args.frames / best))
            print(f"  {label:<40} {size_mb(path):8.0f} MB  read {best:6.2f} s  {args.frames / best:7.0f} frames/s")
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    print()
    print("| recording | size (MB) | read + decode (s) | frames/s |")
    print("|---|---|---|---|")
    for label, mb, _, seconds, fps in rows:
        print(f"| {label} | {mb:.0f} | {seconds:.2f} | {fps:.0f} |")


if __name__ == "__main__":
    main()
