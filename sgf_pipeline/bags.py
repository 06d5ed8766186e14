"""ROS 1 and ROS 2 bags (sqlite3, MCAP) read with ``rosbags``: opening, topics, pose messages and tf.

The ``rosbag`` dataset, ``sgf-bag-info`` and ``sgf-eval`` (a trajectory kept in a bag,
``reference=drive.bag:/ground_truth``) share these. A :class:`TransformTree` holds the transforms
of ``/tf_static`` and ``/tf`` (``tf2_msgs/TFMessage``): a transform's ``header.frame_id`` is the
parent, ``child_frame_id`` the child and ``transform`` the child's pose in the parent (ROS
conventions: REP 103 axes, REP 105 frames). Frame names lose a leading ``/`` (ROS 1's tf prefix).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sgf_pipeline.errors import DataError
from sgf_pipeline.geometry import invert, rotation_from_quaternion
from sgf_pipeline.io import describe_dir
from sgf_pipeline.timesync import PoseSeries
from sgf_pipeline.trajectory import Duplicates, Trajectory, TrajectoryError, checked_trajectory, seconds_from_ns

POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
)
TF_TYPES = ("tf2_msgs/msg/TFMessage",)
#: A frame's transform may change this much over the bag and still count as fixed (m, rad).
FIXED_TRANSLATION, FIXED_ROTATION = 0.005, math.radians(0.2)


def open_bag(path: str | Path, typestore: str = "ros2_humble") -> Any:
    """An opened ``rosbags`` AnyReader (close it), with clear errors for missing and broken bags."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bag = Path(path).expanduser()
    if not bag.exists():
        raise DataError(f"bag not found: {describe_dir(bag)}")
    if bag.is_dir() and not (bag / "metadata.yaml").is_file():
        files = sorted(p.name for p in bag.iterdir())
        inner = [f for f in files if f.endswith((".mcap", ".db3", ".bag"))]
        hint = f"; pass the bag file itself ({', '.join(inner)})" if inner else ""
        raise DataError(f"{bag} is a folder without metadata.yaml, so not a ROS 2 bag (it holds: {files[:10]}){hint}")
    if bag.is_file() and bag.suffix != ".bag":
        with bag.open("rb") as fh:
            if fh.read(13) == b"#ROSBAG V2.0\n":
                raise DataError(f"{bag} is a ROS 1 bag; its name must end in .bag to be read as one: rename it")
    try:
        store = get_typestore(Stores(typestore))
    except ValueError:
        raise DataError(
            f"unknown typestore {typestore!r}; choose one of {', '.join(s.value for s in Stores if s.value != 'empty')}"
        ) from None
    try:
        reader = AnyReader([bag], default_typestore=store)
        reader.open()
    except Exception as exc:
        raise DataError(
            f"cannot open bag {bag}: {type(exc).__name__}: {exc}. The file may be truncated or corrupt (an "
            "interrupted recording?); `rosbag reindex` (ROS 1) or `ros2 bag reindex` (ROS 2) may repair it"
        ) from None
    return reader


@dataclass(frozen=True)
class TopicRow:
    """One topic of a bag: name, message type, count and mean rate."""

    topic: str
    msgtype: str
    count: int
    rate_hz: float | None


def topic_rows(reader: Any) -> list[TopicRow]:
    """The topics of an opened bag, sorted by name."""
    duration = reader.duration / 1e9 if reader.message_count > 1 else 0.0
    rows = []
    for name, info in sorted(reader.topics.items()):
        count = int(info.msgcount)
        rate = (count - 1) / duration if duration > 0 and count > 1 else None
        rows.append(TopicRow(name, info.msgtype or "?", count, rate))
    return rows


def find_topic(topics: Iterable[str], name: str, bag: str | Path) -> str | None:
    """The bag's topic ``name`` names, with or without its leading ``/``; None when none does.

    A topic spelled exactly as ``name`` wins; else the one that differs only by leading slashes
    (ROS 1 bags may name topics without one: ``groundtruth``). Two such topics are a :class:`DataError`.
    """
    topics = list(topics)
    if name in topics:
        return name
    matches = sorted(t for t in topics if t.lstrip("/") == name.lstrip("/"))
    if len(matches) > 1:
        raise DataError(
            f"{bag}: {name} is ambiguous: the bag has {' and '.join(matches)}, which differ only by their "
            "leading slashes; name one exactly as the bag spells it"
        )
    return matches[0] if matches else None


def describe_topics(reader: Any, types: tuple[str, ...] = ()) -> str:
    """``/a (type, n msgs), ...``: the bag's topics, those of ``types`` first."""
    rows = topic_rows(reader)
    if types:
        rows.sort(key=lambda r: (r.msgtype not in types, r.topic))
    return ", ".join(f"{r.topic} ({r.msgtype}, {r.count} msgs)" for r in rows) or "no topics"


def stamp_ns(msg: Any) -> int:
    """A message's ``header.stamp`` in integer nanoseconds."""
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _pose_matrix(position: Any, orientation: Any) -> np.ndarray:
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=np.float64)
    pose = np.eye(4)
    norm = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else 0.0
    pose[:3, :3] = rotation_from_quaternion(q) if norm > 1e-6 else np.nan
    pose[:3, 3] = (position.x, position.y, position.z)
    return pose


def pose_of_message(msg: Any, msgtype: str) -> np.ndarray:
    """The 4x4 pose carried by an Odometry, PoseStamped, PoseWithCovarianceStamped or TransformStamped."""
    if msgtype == "nav_msgs/msg/Odometry" or msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        return _pose_matrix(msg.pose.pose.position, msg.pose.pose.orientation)
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return _pose_matrix(msg.pose.position, msg.pose.orientation)
    if msgtype == "geometry_msgs/msg/TransformStamped":
        return _pose_matrix(msg.transform.translation, msg.transform.rotation)
    raise DataError(f"{msgtype} carries no pose; use one of {', '.join(POSE_TYPES)}")


def frame_name(frame_id: Any) -> str:
    """A tf frame id without ROS 1's leading ``/``."""
    return str(frame_id).strip().lstrip("/")


def _rotation_angle(rotation: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(rotation)) - 1.0) / 2.0)))


@dataclass
class _Edge:
    """One parent -> child transform: fixed (``/tf_static``) or a stream of stamped poses (``/tf``)."""

    static: bool
    stamps: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)

    def add(self, ns: int, pose: np.ndarray) -> None:
        if self.static:
            self.stamps, self.poses = [ns], [pose]  # the latest static transform holds
        else:
            self.stamps.append(ns)
            self.poses.append(pose)

    def series(self, name: str) -> PoseSeries:
        """The edge's poses in time order, one per stamp in seconds (the last of equal stamps)."""
        order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
        seconds = seconds_from_ns(np.asarray(self.stamps, dtype=np.int64)[order])
        poses = np.asarray(self.poses)[order]
        last = np.append(seconds[1:] != seconds[:-1], True)
        return PoseSeries(seconds[last], poses[last], name)

    def fixed_pose(self) -> np.ndarray | None:
        """The edge's pose when it does not change over the bag (within a few mm and a fraction of a degree)."""
        first = self.poses[0]
        for pose in self.poses[1:]:
            delta = invert(first) @ pose
            if np.linalg.norm(delta[:3, 3]) > FIXED_TRANSLATION or _rotation_angle(delta[:3, :3]) > FIXED_ROTATION:
                return None
        return first


class TransformTree:
    """The tf transforms of a bag: static edges and stamped ones, and the poses of frames in each other."""

    def __init__(self) -> None:
        self.edges: dict[tuple[str, str], _Edge] = {}
        self.topics: set[str] = set()

    def __bool__(self) -> bool:
        return bool(self.edges)

    def add_message(self, msg: Any, topic: str, static: bool) -> int:
        """Take the transforms of one ``TFMessage``; the number of finite ones taken."""
        taken = 0
        self.topics.add(topic)
        for transform in msg.transforms:
            parent, child = frame_name(transform.header.frame_id), frame_name(transform.child_frame_id)
            pose = _pose_matrix(transform.transform.translation, transform.transform.rotation)
            if not parent or not child or parent == child or not np.all(np.isfinite(pose)):
                continue
            edge = self.edges.get((parent, child))
            if edge is None or (static and not edge.static):
                edge = self.edges[(parent, child)] = _Edge(static)
            if static or not edge.static:
                edge.add(stamp_ns(transform), pose)
                taken += 1
        return taken

    def frames(self) -> list[str]:
        """Every frame the tree names, sorted."""
        return sorted({f for pair in self.edges for f in pair})

    def describe(self) -> str:
        """``parent -> child`` of every edge (``(tf)`` when stamped), for error messages."""
        return ", ".join(f"{p} -> {c}{'' if e.static else ' (tf)'}" for (p, c), e in sorted(self.edges.items()))

    def path(self, start: str, goal: str) -> list[tuple[str, str, bool]] | None:
        """The edges from ``start`` to ``goal`` as ``(parent, child, downward)``; None when not joined."""
        links: dict[str, list[tuple[str, tuple[str, str, bool]]]] = {}
        for parent, child in self.edges:
            links.setdefault(parent, []).append((child, (parent, child, True)))
            links.setdefault(child, []).append((parent, (parent, child, False)))
        if start not in links or goal not in links:
            return None
        previous: dict[str, tuple[str, tuple[str, str, bool]] | None] = {start: None}
        queue = deque([start])
        while queue:
            frame = queue.popleft()
            if frame == goal:
                break
            for other, edge in links[frame]:
                if other not in previous:
                    previous[other] = (frame, edge)
                    queue.append(other)
        if goal not in previous:
            return None
        steps: list[tuple[str, str, bool]] = []
        frame = goal
        while (back := previous[frame]) is not None:
            frame, edge = back
            steps.append(edge)
        return steps[::-1]

    def fixed_pose(self, target: str, source: str) -> np.ndarray:
        """The pose of ``source`` in ``target`` through edges that do not change over the bag."""
        steps = self.path(target, source)
        if steps is None:
            raise DataError(self._unjoined(target, source))
        pose = np.eye(4)
        for parent, child, downward in steps:
            value = self.edges[(parent, child)].fixed_pose()
            if value is None:
                raise DataError(
                    f"the transform {parent} -> {child} between {target} and {source} changes over the bag (on "
                    f"{', '.join(sorted(self.topics))}): {source} moves on {target}, so it has no fixed pose there"
                )
            pose = pose @ (value if downward else invert(value))
        return pose

    def trajectory(self, target: str, source: str) -> tuple[np.ndarray, np.ndarray]:
        """Seconds and poses of ``source`` in ``target`` at the stamps of the stamped edge nearest ``source``.

        The other stamped edges of the path are interpolated at those stamps; stamps outside
        their span are left out.
        """
        steps = self.path(target, source)
        if steps is None:
            raise DataError(self._unjoined(target, source))
        moving = [(p, c) for p, c, _ in steps if not self.edges[(p, c)].static]
        if not moving:
            raise DataError(f"every transform from {target} to {source} is static: there is no trajectory")
        series = {pair: self.edges[pair].series(f"{pair[0]} -> {pair[1]}") for pair in moving}
        times = series[moving[-1]].timestamps
        poses = []
        kept = []
        for t in times:
            pose = np.eye(4)
            for parent, child, downward in steps:
                edge = self.edges[(parent, child)]
                if edge.static:
                    value: np.ndarray | None = edge.poses[0]
                else:
                    s = series[(parent, child)]
                    span = s.span()
                    assert span is not None
                    value = s.at(float(t), math.inf) if span[0] <= t <= span[1] else None
                if value is None:
                    break
                pose = pose @ (value if downward else invert(value))
            else:
                poses.append(pose)
                kept.append(float(t))
        return np.asarray(kept), np.asarray(poses).reshape(-1, 4, 4)

    def _unjoined(self, target: str, source: str) -> str:
        topics = ", ".join(sorted(self.topics)) or "no tf topic"
        return (
            f"the tf tree ({topics}) does not join {target} and {source}; the frames it has: "
            f"{', '.join(self.frames()) or 'none'} (transforms: {self.describe() or 'none'})"
        )


def read_transform_tree(reader: Any, topics: list[str] | None = None) -> TransformTree:
    """The tf tree of an opened bag: every ``TFMessage`` topic, or ``topics``; ``*tf_static`` topics are static."""
    names = topics if topics is not None else [r.topic for r in topic_rows(reader) if r.msgtype in TF_TYPES]
    tree = TransformTree()
    connections = [c for c in reader.connections if c.topic in names]
    for connection, _, raw in reader.messages(connections=connections):
        msg = reader.deserialize(raw, connection.msgtype)
        tree.add_message(msg, connection.topic, connection.topic.endswith("tf_static"))
    return tree


# -- trajectories kept in a bag -------------------------------------------------------------------------


def split_bag_source(source: str) -> tuple[Path, str] | None:
    """``(bag, topic)`` of ``drive.bag:/topic`` (a bag that exists), else None.

    ``drive.bag:topic`` without the slash names a topic too when ``drive.bag`` is a file or a
    ROS 2 bag folder (one with ``metadata.yaml``), not any folder: ``runs:v2.tum`` stays a file name.
    """
    if Path(source).expanduser().exists():
        return None
    start = 0
    while (i := source.find(":", start)) > 0:
        bag, topic = Path(source[:i]).expanduser(), source[i + 1 :]
        bag_like = bag.is_file() or (bag / "metadata.yaml").is_file()
        if topic and (bag.exists() if topic.startswith("/") else bag_like):
            return bag, topic
        start = i + 1
    return None


def read_bag_trajectory(
    bag: str | Path, topic: str, duplicates: Duplicates = "error", typestore: str = "ros2_humble"
) -> Trajectory:
    """The poses of one topic of a bag as a trajectory, at their ``header.stamp``.

    ``topic`` (with or without its leading ``/``, :func:`find_topic`) carries Odometry, PoseStamped,
    PoseWithCovarianceStamped or TransformStamped, or is a tf topic (``/tf``): ``/tf:map.base_link``
    is the pose of ``base_link`` in ``map`` through the tree (``/tf_static`` included), as evo names
    it; ``/tf`` alone takes the topic's one moving transform.
    """
    given, _, frames = topic.partition(":")
    reader = open_bag(bag, typestore)
    try:
        rows = {r.topic: r for r in topic_rows(reader)}
        usable = [r.topic for r in rows.values() if r.msgtype in POSE_TYPES + TF_TYPES]
        name = find_topic(rows, given, bag) or given
        if name not in rows:
            raise DataError(
                f"{bag}: no topic {name}; topics with poses (PoseStamped, Odometry, TransformStamped, tf): "
                f"{', '.join(usable) or 'none'} (all topics: {describe_topics(reader)})"
            )
        msgtype = rows[name].msgtype
        source = f"{bag}:{name}"
        if msgtype in TF_TYPES:
            tf = [r.topic for r in rows.values() if r.msgtype in TF_TYPES and r.topic.endswith("tf_static")]
            tree = read_transform_tree(reader, sorted({name, *tf}))
            target, child = _tf_frames(tree, name, frames, source)
            seconds, poses = tree.trajectory(target, child)
            numbers = list(range(1, len(seconds) + 1))
            return checked_trajectory(f"{source}:{target}.{child}", seconds, poses, numbers, duplicates)
        if msgtype not in POSE_TYPES:
            raise DataError(
                f"{source} carries {msgtype}, which holds no pose; topics with poses: {', '.join(usable) or 'none'}"
            )
        if frames:
            raise DataError(f"{source}:{frames}: frames are named only for a tf topic (/tf:<parent>.<child>)")
        stamps: list[int] = []
        poses_list: list[np.ndarray] = []
        connections = [c for c in reader.connections if c.topic == name]
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            stamps.append(stamp_ns(msg))
            poses_list.append(pose_of_message(msg, msgtype))
        if not stamps:
            raise DataError(f"{source}: the topic has no messages")
        seconds = seconds_from_ns(np.asarray(stamps, dtype=np.int64))
        numbers = list(range(1, len(stamps) + 1))
        return checked_trajectory(source, seconds, np.asarray(poses_list), numbers, duplicates)
    except TrajectoryError as exc:
        raise DataError(str(exc)) from None
    finally:
        reader.close()


def _tf_frames(tree: TransformTree, topic: str, frames: str, source: str) -> tuple[str, str]:
    """``(parent, child)`` named as ``parent.child``, or the topic's only moving transform."""
    if frames:
        parent, dot, child = frames.rpartition(".")
        if not dot or not parent or not child:
            raise DataError(f"{source}:{frames}: name the frames as <parent>.<child>, e.g. {topic}:map.base_link")
        return frame_name(parent), frame_name(child)
    moving = [pair for pair, edge in sorted(tree.edges.items()) if not edge.static]
    if len(moving) != 1:
        listed = ", ".join(f"{topic}:{p}.{c}" for p, c in moving) or "none"
        raise DataError(
            f"{source} holds {len(moving)} moving transforms; name the one to evaluate as {topic}:<parent>.<child> "
            f"(those in the bag: {listed})"
        )
    return moving[0]
