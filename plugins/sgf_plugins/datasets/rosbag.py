"""``dataset=rosbag``: ROS 1 bags and ROS 2 bags (sqlite3 or MCAP), read with ``rosbags`` (no ROS install).

Topics are chosen in the config. The camera topic drives the frames (``sensor_msgs/Image`` or
``CompressedImage``); at each image's timestamp the other streams are sampled (see
:mod:`sgf_pipeline.timesync`): odometry (``nav_msgs/Odometry``, ``PoseStamped``,
``PoseWithCovarianceStamped`` or ``TransformStamped``: the pose of the robot's base), IMU roll and
pitch (``sensor_msgs/Imu``: from its orientation, or from gyro and accelerometer by a
complementary filter when the driver publishes no orientation), and ground truth (any of the
pose types). Camera frames before the first or after the last odometry message are left out and
counted as ``trimmed``. Intrinsics and distortion come from a ``CameraInfo`` topic or from a
folder-format ``calibration.yaml``. The camera's mounting on the base comes from the config
(``camera_to_base`` or ``camera_height``) or else from the bag's tf (``/tf_static``, ``/tf``): the
pose of the images' ``header.frame_id`` in the base frame (``base_frame``, or ``base_footprint``,
else ``base_link``), see :func:`~sgf_plugins.datasets.rosbag_messages.camera_mounting`.

Timestamps are the messages' ``header.stamp`` (the sensor's time) unless ``stamps: bag``
chooses the time the recorder received them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from sgf_pipeline import DataError, RunContext, StageRegistry, hookimpl
from sgf_pipeline.bags import (
    POSE_TYPES,
    TF_TYPES,
    TransformTree,
    describe_topics,
    find_topic,
    open_bag,
    pose_of_message,
    stamp_ns,
    topic_rows,
)
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.calibration_io import calibration_from_camera_info
from sgf_pipeline.folder_format import read_calibration_yaml
from sgf_pipeline.imu import roll_pitch_from_inertial, roll_pitch_of_base
from sgf_pipeline.timesync import PoseSeries, ValueSeries
from sgf_pipeline.trajectory import seconds_from_ns
from sgf_pipeline.types import Frame
from sgf_plugins.datasets._common import MountingParams, RecordedDataset, finite_pose, mounting_matrix
from sgf_plugins.datasets.rosbag_messages import (
    CAMERA_INFO_TYPES,
    IMAGE_TYPES,
    IMU_TYPES,
    SUPPORTED_ENCODINGS,
    camera_mounting,
    decode_compressed_image,
    decode_raw_image,
    image_frame_id,
    quaternion_is_unit,
    tf_topic_names,
)

log = logging.getLogger("sgf_pipeline.datasets")


class RosbagParams(MountingParams):
    """Options of the ROS bag reader (topics, association, calibration)."""

    image_topic: str = Field("", description="camera topic (sensor_msgs/Image or CompressedImage); required")
    odometry_topic: str = Field("", description="odometry topic (Odometry, PoseStamped, TransformStamped); required")
    imu_topic: str = Field("", description="sensor_msgs/Imu topic for roll and pitch (empty: none)")
    ground_truth_topic: str = Field("", description="ground-truth pose topic (empty: none)")
    camera_info_topic: str = Field("", description="sensor_msgs/CameraInfo topic (intrinsics, distortion)")
    calibration_file: str = Field(
        "", description="folder-format calibration.yaml used instead of camera_info_topic and the mounting"
    )
    base_frame: str = Field(
        "", description="tf frame of the robot's base for the camera's mounting (empty: base_footprint, base_link)"
    )
    imu_to_base: list[list[float]] | None = Field(
        None, description="3x3 or 4x4 pose of the IMU frame in the base frame"
    )
    imu_orientation: Literal["auto", "message", "filter"] = Field(
        "auto", description="roll/pitch from the Imu orientation, from gyro+accel (filter), or auto"
    )
    imu_gain: float = Field(1.0, ge=0.0, description="complementary filter gain (1/s) when imu_orientation=filter")
    max_time_diff: float = Field(0.02, gt=0.0, description="s; furthest odometry/IMU/ground-truth sample from an image")
    interpolate: bool = Field(True, description="interpolate poses between samples (else take the nearest)")
    stamps: Literal["header", "bag"] = Field("header", description="use header.stamp or the recorder's receive time")
    typestore: str = Field("ros2_humble", description="message definitions for bags that carry none (old ROS 2)")
    sequence: str = Field("", description="sequence name in reports (default: the bag's name)")


# -- the adapter ------------------------------------------------------------------------------


class _PoseCollector:
    """Poses of one topic, checked for finite values and increasing stamps as they arrive."""

    def __init__(self, topic: str, what: str) -> None:
        self.topic = topic
        self.what = what
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []

    def add(self, dataset: RosbagDataset, ns: int, msg: Any, msgtype: str) -> None:
        """Take one message (bad ones are reported through the dataset's skip log)."""
        pose = pose_of_message(msg, msgtype)
        if not finite_pose(pose):
            dataset.skips.problem(
                "bad pose", f"{self.topic}: {self.what} pose at t={ns / 1e9:.6f} s is not finite (NaN or inf)"
            )
            return
        if dataset.check_order(self.topic, ns, self.stamps[-1] if self.stamps else None):
            self.stamps.append(ns)
            self.poses.append(pose)

    def series(self) -> PoseSeries:
        """The collected poses."""
        ts = seconds_from_ns(np.asarray(self.stamps, dtype=np.int64))
        return PoseSeries(ts, np.asarray(self.poses).reshape(-1, 4, 4), self.what)


@dataclass
class _ImuSamples:
    """IMU messages of one topic: orientation when published, angular velocity, specific force."""

    ns: list[int] = field(default_factory=list)
    orientation: list[np.ndarray] = field(default_factory=list)
    has_orientation: list[bool] = field(default_factory=list)
    gyro: list[np.ndarray] = field(default_factory=list)
    accel: list[np.ndarray] = field(default_factory=list)

    def add(self, dataset: RosbagDataset, ns: int, msg: Any) -> None:
        """Take one message (bad ones are reported through the dataset's skip log)."""
        topic = dataset.params.imu_topic
        q = np.array([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w])
        gyro = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
        accel = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
        has_q = float(msg.orientation_covariance[0]) != -1.0 and quaternion_is_unit(q)
        if not (has_q or (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel)))):
            dataset.skips.problem("bad imu", f"{topic}: IMU message at t={ns / 1e9:.6f} s is not finite")
            return
        if not dataset.check_order(topic, ns, self.ns[-1] if self.ns else None):
            return
        self.ns.append(ns)
        self.orientation.append(q)
        self.has_orientation.append(has_q)
        self.gyro.append(gyro)
        self.accel.append(accel)


class RosbagDataset(RecordedDataset):
    """A ROS 1 or ROS 2 (sqlite3, MCAP) bag: camera, odometry, IMU and ground-truth topics."""

    name = "rosbag"
    Params = RosbagParams
    params: RosbagParams

    def __init__(self, params: RosbagParams) -> None:
        super().__init__(params)
        if not params.path:
            raise DataError("dataset=rosbag needs the bag: dataset.path=<file.bag | ROS 2 bag folder | file.mcap>")
        self.path = Path(params.path).expanduser()
        self.trimmed = 0
        self.mounting_source = "config"
        reader = open_bag(self.path, params.typestore)
        try:
            params = self.params = self._bag_spelling(reader, params)
            self.image_type = self._topic(reader, "image_topic", IMAGE_TYPES, required=True)
            self._topic(reader, "odometry_topic", POSE_TYPES, required=True)
            imu_type = self._topic(reader, "imu_topic", IMU_TYPES, required=False)
            gt_type = self._topic(reader, "ground_truth_topic", POSE_TYPES, required=False)
            info_type = self._topic(reader, "camera_info_topic", CAMERA_INFO_TYPES, required=False)
            self.image_count = int(reader.topics[params.image_topic].msgcount)
            # One pass over the small topics (a second pass would read an MCAP file's chunks again).
            odometry = _PoseCollector(params.odometry_topic, "odometry")
            ground_truth = _PoseCollector(params.ground_truth_topic, "ground truth") if gt_type else None
            imu = _ImuSamples() if imu_type else None
            info: Any = None
            topics = {params.odometry_topic, params.ground_truth_topic, params.imu_topic, params.camera_info_topic}
            # The mounting the config gives wins; else the tf tree's (read in the same pass).
            tree = TransformTree()
            tf_topics = set() if self._configured_mounting() else set(tf_topic_names(reader))
            for topic, _, ns, msg, msgtype in self._messages(reader, (topics | tf_topics) - {""}):
                if topic in tf_topics:
                    tree.add_message(msg, topic, static=topic.endswith("tf_static"))
                    continue
                if topic == params.odometry_topic:
                    odometry.add(self, ns, msg, msgtype)
                if ground_truth is not None and topic == params.ground_truth_topic:
                    ground_truth.add(self, ns, msg, msgtype)
                if imu is not None and topic == params.imu_topic:
                    imu.add(self, ns, msg)
                if info is None and info_type is not None and topic == params.camera_info_topic:
                    info = msg
            self.odometry = odometry.series()
            if len(self.odometry) == 0:
                raise DataError(f"{self.path}: topic {params.odometry_topic} has no usable odometry message")
            self.ground_truth = ground_truth.series() if ground_truth is not None else None
            self.attitude = self._attitude(imu) if imu is not None else None
            calibration = self._calibration(reader, info_type is not None, info, tree)
        finally:
            reader.close()
        self.calibration = self.prepare_calibration(calibration)

    def _configured_mounting(self) -> bool:
        """Whether the config (or the calibration file) says how the camera sits on the base."""
        p = self.params
        return bool(p.calibration_file) or p.camera_to_base is not None or p.camera_height is not None

    # -- setup ------------------------------------------------------------------------------

    def _bag_spelling(self, reader: Any, params: RosbagParams) -> RosbagParams:
        """The params with each topic spelled as the bag does (``groundtruth`` for ``/groundtruth``)."""
        keys = ("image_topic", "odometry_topic", "imu_topic", "ground_truth_topic", "camera_info_topic")
        spelled = {}
        for key in keys:
            given = getattr(params, key)
            found = find_topic(reader.topics, given, self.path) if given else None
            if found is not None and found != given:
                spelled[key] = found
        return params.model_copy(update=spelled) if spelled else params

    def _topic(self, reader: Any, key: str, types: tuple[str, ...], required: bool) -> str | None:
        topic = getattr(self.params, key)
        if not topic:
            if required:
                candidates = [r.topic for r in topic_rows(reader) if r.msgtype in types]
                raise DataError(
                    f"dataset.{key} is not set; topics of type {' or '.join(t.split('/')[-1] for t in types)} in "
                    f"{self.path}: {', '.join(candidates) or 'none'} (all topics: {describe_topics(reader)})"
                )
            return None
        topics = reader.topics
        if topic not in topics:
            raise DataError(
                f"dataset.{key}={topic}: no such topic in {self.path}. Topics in the bag: "
                f"{describe_topics(reader, types)}"
            )
        msgtype = topics[topic].msgtype
        if msgtype not in types:
            raise DataError(
                f"dataset.{key}={topic} carries {msgtype}, but it must be one of {', '.join(types)}. Topics of "
                f"those types: {', '.join(r.topic for r in topic_rows(reader) if r.msgtype in types) or 'none'}"
            )
        if topics[topic].msgcount == 0:
            raise DataError(f"dataset.{key}={topic}: the topic has no messages in {self.path}")
        return str(msgtype)

    def _messages(self, reader: Any, topics: set[str]) -> Iterator[tuple[str, int, int, Any, str]]:
        """``(topic, position, ns, message, type)`` of some topics in bag order; bad messages are reported."""
        connections = [c for c in reader.connections if c.topic in topics]
        positions = dict.fromkeys(topics, -1)
        stream = iter(reader.messages(connections=connections))
        while True:
            try:
                connection, bag_ns, raw = next(stream)
            except StopIteration:
                return
            except Exception as exc:  # a damaged chunk or index: the reader cannot go on past it
                read = ", ".join(f"{n + 1} on {t}" for t, n in sorted(positions.items()))
                self.skips.problem(
                    "unreadable bag",
                    f"{self.path}: the bag cannot be read past this point ({type(exc).__name__}: {exc}); messages "
                    f"read so far: {read}. It is corrupt or truncated there; `rosbag reindex` (ROS 1) or "
                    "`ros2 bag reindex` (ROS 2) may repair it",
                )
                return
            topic = connection.topic
            positions[topic] += 1
            try:
                msg = reader.deserialize(raw, connection.msgtype)
                stamped = self.params.stamps == "header" and connection.msgtype not in TF_TYPES
                ns = stamp_ns(msg) if stamped else bag_ns
            except Exception as exc:
                self.skips.problem(
                    "corrupt message",
                    f"{topic}: message {positions[topic]} (received at t={bag_ns / 1e9:.6f} s) cannot be decoded "
                    f"({type(exc).__name__}: {exc}); the bag is corrupt or truncated there",
                )
                continue
            if ns == 0 and stamped:
                raise DataError(
                    f"{topic}: message {positions[topic]} has header.stamp 0 (its publisher leaves the stamp unset); "
                    "use the recorder's receive times with dataset.stamps=bag"
                )
            yield topic, positions[topic], ns, msg, connection.msgtype

    def check_order(self, topic: str, ns: int, last: int | None) -> bool:
        """Whether a stamp comes after the previous one; reports duplicates and disorder."""
        if last is None or ns > last:
            return True
        kind = "duplicated timestamp" if ns == last else "timestamp out of order"
        self.skips.problem(
            kind,
            f"{topic}: header stamp {ns / 1e9:.9f} s is not after the previous message's {last / 1e9:.9f} s "
            "(stamps: bag uses the recorder's clock instead)",
        )
        return False

    def _attitude(self, samples: _ImuSamples) -> ValueSeries | None:
        p = self.params
        if not samples.ns:
            return None
        ts = seconds_from_ns(np.asarray(samples.ns, dtype=np.int64))
        imu_to_base = None if p.imu_to_base is None else np.asarray(p.imu_to_base, dtype=np.float64)
        if imu_to_base is not None and imu_to_base.shape not in ((3, 3), (4, 4)):
            raise DataError(f"dataset.imu_to_base must be 3x3 or 4x4, got shape {imu_to_base.shape}")
        use_message = p.imu_orientation == "message" or (p.imu_orientation == "auto" and all(samples.has_orientation))
        if use_message:
            if not all(samples.has_orientation):
                raise DataError(
                    f"{p.imu_topic}: {samples.has_orientation.count(False)} IMU messages carry no orientation "
                    "(orientation_covariance[0] = -1 or a zero quaternion); use dataset.imu_orientation=filter"
                )
            values = np.array([roll_pitch_of_base(q, imu_to_base) for q in samples.orientation])
        else:
            gyro = np.asarray(samples.gyro)
            accel = np.asarray(samples.accel)
            if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
                raise DataError(f"{p.imu_topic}: non-finite gyro or accelerometer values; the filter needs both")
            values = roll_pitch_from_inertial(ts, gyro, accel, p.imu_gain, imu_to_base)
        return ValueSeries(ts, values, "imu roll/pitch")

    def _calibration(self, reader: Any, has_info: bool, info: Any, tree: TransformTree) -> Calibration:
        p = self.params
        if p.calibration_file:
            calibration = read_calibration_yaml(Path(p.calibration_file).expanduser())
            mounting = mounting_matrix(p, self.name)
            self.mounting_source = "config" if mounting is not None else f"calibration file {p.calibration_file}"
            return calibration if mounting is None else calibration.model_copy(update={"camera_to_base": mounting})
        if not has_info:
            infos = [r.topic for r in topic_rows(reader) if r.msgtype in CAMERA_INFO_TYPES]
            raise DataError(
                "dataset=rosbag: no camera calibration. Give dataset.camera_info_topic=<topic> (CameraInfo topics "
                f"in the bag: {', '.join(infos) or 'none'}) or dataset.calibration_file=<calibration.yaml>"
            )
        if info is None:
            raise DataError(f"{p.camera_info_topic}: no readable CameraInfo message in {self.path}")
        camera_to_base = mounting_matrix(p, self.name)
        self.mounting_source = "config"
        if camera_to_base is None:
            camera_frame = image_frame_id(reader, p.image_topic)
            camera_to_base, self.mounting_source = camera_mounting(tree, camera_frame, p.base_frame, self.path)
            log.info("dataset=rosbag: camera mounting from %s", self.mounting_source)
        k = getattr(info, "k", None)
        k = getattr(info, "K", None) if k is None else k
        d = getattr(info, "d", None)
        d = getattr(info, "D", None) if d is None else d
        return calibration_from_camera_info(
            int(info.width),
            int(info.height),
            np.asarray(k, dtype=np.float64).tolist(),
            np.asarray(d, dtype=np.float64).tolist(),
            str(info.distortion_model),
            camera_to_base,
            f"{p.camera_info_topic} in {self.path}",
        )

    # -- the Dataset contract -----------------------------------------------------------------

    def __len__(self) -> int:
        """Number of image messages (frames outside the odometry's span are dropped on the way)."""
        return self.image_count

    def begin(self, context: RunContext) -> None:
        """Calibration, rate and name into the run context."""
        context.calibration = self.calibration
        context.sequence = self.params.sequence or self.path.stem
        if len(self.odometry) > 1:
            span = self.odometry.span()
            assert span is not None
            if span[1] > span[0] and self.image_count > 1:
                context.rate_hz = float((self.image_count - 1) / (span[1] - span[0]))

    def _image_loader(self, msg: Any, msgtype: str, what: str) -> Callable[[], np.ndarray]:
        if msgtype == "sensor_msgs/msg/CompressedImage":
            return lambda: decode_compressed_image(msg, "image data")
        encoding = str(msg.encoding).lower()
        if encoding not in SUPPORTED_ENCODINGS:
            # Every frame of the topic would fail the same way: an error, whatever `strict` says.
            raise DataError(
                f"dataset={self.name}: {what}: unknown image encoding {msg.encoding!r}; supported: "
                f"{', '.join(SUPPORTED_ENCODINGS)}"
            )
        return lambda: decode_raw_image(msg, "image data")

    def frames(self) -> Iterator[Frame]:
        """Image messages in time order with odometry, IMU roll/pitch and ground truth at their stamps."""
        p = self.params
        span = self.odometry.span()
        assert span is not None
        self.yielded = self.trimmed = 0
        reader = open_bag(self.path, p.typestore)
        try:
            last: int | None = None
            for _, index, ns, msg, msgtype in self._messages(reader, {p.image_topic}):
                if not self.check_order(p.image_topic, ns, last):
                    continue
                last = ns
                t = float(seconds_from_ns(np.asarray([ns], dtype=np.int64))[0])
                if t < span[0] - p.max_time_diff or t > span[1] + p.max_time_diff:
                    self.trimmed += 1
                    continue
                odometry = self.odometry.at(t, p.max_time_diff, p.interpolate)
                if odometry is None:
                    self.skips.problem(
                        "no odometry",
                        f"no {p.odometry_topic} message within {p.max_time_diff} s of image {index} (t={t:.6f} s); "
                        "raise dataset.max_time_diff if the odometry is slow",
                    )
                    continue
                what = f"{p.image_topic} message {index} (t={t:.6f} s)"
                image = self.image_source(self._image_loader(msg, msgtype, what), what)
                if image is None:
                    continue
                yield self.make_frame(index, t, image, odometry)
        finally:
            reader.close()

    def finalize(self, context: RunContext) -> None:
        """Skips, frames outside the odometry's span and where the camera's mounting came from into metrics.json."""
        super().finalize(context)
        context.metrics["dataset"]["trimmed"] = self.trimmed
        context.metrics["dataset"]["mounting"] = self.mounting_source


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the ROS bag dataset."""
    registry.add(RosbagDataset)
