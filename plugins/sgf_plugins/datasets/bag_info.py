"""``sgf-bag-info``: a bag's topics, the topic for each role of ``dataset=rosbag``, and the command that reads it.

Candidates for each role are ranked by message type and name: the odometry prefers
``nav_msgs/Odometry`` over ``PoseWithCovarianceStamped``, ``PoseStamped`` and ``TransformStamped``
and leaves out topics named like ground truth; the ground truth is a pose topic named like one
(``ground_truth``, ``groundtruth``, ``gt``, ``vicon``, ``mocap``, ...). The camera's mounting is
looked up in the bag's tf as ``dataset=rosbag`` would; the printed command runs as printed when
the bag has a camera, its calibration, odometry and a mounting.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from sgf_pipeline import DataError
from sgf_pipeline.bags import POSE_TYPES, TF_TYPES, TransformTree, open_bag, read_transform_tree, topic_rows
from sgf_pipeline.cli.common import console, friendly_errors, hydra_value
from sgf_pipeline.config import config_dir
from sgf_plugins.datasets.rosbag_messages import (
    CAMERA_INFO_TYPES,
    IMAGE_TYPES,
    IMU_TYPES,
    camera_mounting,
    image_frame_id,
)

#: Words that name a ground-truth topic (as whole parts of the topic's name).
TRUTH_WORDS = frozenset({"gt", "truth", "groundtruth", "vicon", "mocap", "optitrack", "leica", "reference"})
#: Words of image topics that are no camera picture of the ground.
NOT_A_PICTURE = frozenset({"depth", "disparity", "ir", "infra", "infra1", "infra2", "thermal", "mask", "segmentation"})
#: The command line with the bag given as a path.
USAGE = "sgf-bag-info BAG [format=json]"
#: The roles of ``dataset=rosbag`` in the order the command names them.
ROLES = ("image_topic", "camera_info_topic", "odometry_topic", "imu_topic", "ground_truth_topic")


def _words(topic: str) -> list[str]:
    return [w for w in re.split(r"[/_\-.]+", topic.lower()) if w]


def looks_like_truth(topic: str) -> bool:
    """Whether a topic's name says ground truth (``/ground_truth``, ``/gt/pose``, ``/vicon/base``, ...)."""
    words = _words(topic)
    joined = "_".join(words)
    return "ground_truth" in joined or bool(TRUTH_WORDS.intersection(words))


def _namespace(topic: str) -> str:
    parts = [p for p in topic.split("/") if p and p not in ("compressed", "image_raw", "image_rect", "image")]
    return "/".join(parts[:-1] if len(parts) > 1 else parts)


def rank_candidates(rows: list[Any]) -> dict[str, list[str]]:
    """The topics usable for each role, best first."""
    by_type: dict[str, list[Any]] = {}
    for r in rows:
        if r.count > 0:
            by_type.setdefault(r.msgtype, []).append(r)

    def of(types: tuple[str, ...]) -> list[Any]:
        return [r for t in types for r in by_type.get(t, [])]

    images = sorted(
        of(IMAGE_TYPES),
        key=lambda r: (bool(NOT_A_PICTURE.intersection(_words(r.topic))), r.msgtype != IMAGE_TYPES[0], r.topic),
    )
    image_space = _namespace(images[0].topic) if images else ""
    infos = sorted(of(CAMERA_INFO_TYPES), key=lambda r: (_namespace(r.topic) != image_space, r.topic))
    poses = of(POSE_TYPES)
    odometry = sorted(
        (r for r in poses if not looks_like_truth(r.topic)),
        key=lambda r: (POSE_TYPES.index(r.msgtype), "odom" not in _words(r.topic), r.topic),
    )
    truth = sorted(
        (r for r in poses if looks_like_truth(r.topic)), key=lambda r: (POSE_TYPES.index(r.msgtype), r.topic)
    )
    imus = sorted(of(IMU_TYPES), key=lambda r: ("raw" in _words(r.topic), r.topic))
    return {
        "image_topic": [r.topic for r in images],
        "camera_info_topic": [r.topic for r in infos],
        "odometry_topic": [r.topic for r in odometry],
        "imu_topic": [r.topic for r in imus],
        "ground_truth_topic": [r.topic for r in truth],
    }


def _shell_word(arg: str) -> str:
    """One shell word: as it is when plain, in double quotes when that suffices, else single-quoted."""
    if shlex.quote(arg) == arg:
        return arg
    return f'"{arg}"' if not re.search(r'["$`\\!]', arg) else shlex.quote(arg)


def suggested_command(path: str, chosen: dict[str, str]) -> str:
    """The ``sgf-run`` command line that reads the bag with the chosen topics (shell-quoted)."""
    args = ["sgf-run", "dataset=rosbag", f"dataset.path={hydra_value(path)}"]
    args += [f"dataset.{role}={hydra_value(chosen[role])}" for role in ROLES if chosen.get(role)]
    return " ".join(_shell_word(a) for a in args)


def _mounting(reader: Any, image_topic: str, bag: Path) -> dict[str, Any]:
    """Where ``dataset=rosbag`` would find the camera's mounting: the tf tree, or nowhere."""
    tf_topics = [r.topic for r in topic_rows(reader) if r.msgtype in TF_TYPES and r.count > 0]
    tree = read_transform_tree(reader, tf_topics) if tf_topics else TransformTree()
    frame = image_frame_id(reader, image_topic) if image_topic else ""
    try:
        pose, source = camera_mounting(tree, frame, "", bag)
    except DataError as exc:
        return {"found": False, "camera_frame": frame, "source": None, "problem": str(exc)}
    return {"found": True, "camera_frame": frame, "source": source, "camera_to_base": pose.tolist()}


def bag_summary(path: str | Path, typestore: str = "ros2_humble") -> dict[str, Any]:
    """Storage, time span and topics of a bag, the ranked topics for each role, the mounting and the command."""
    bag = Path(path).expanduser()
    reader = open_bag(bag, typestore)
    try:
        rows = topic_rows(reader)
        start, end = reader.start_time / 1e9, reader.end_time / 1e9
        if not reader.is2:
            storage = "ROS 1 bag"
        else:
            suffixes = {p.suffix for p in bag.iterdir()} if bag.is_dir() else {bag.suffix}
            storage = "ROS 2 bag, " + ("MCAP" if ".mcap" in suffixes else "sqlite3")
        candidates = rank_candidates(rows)
        chosen = {role: found[0] for role, found in candidates.items() if found}
        mounting = _mounting(reader, chosen.get("image_topic", ""), bag)
        messages = int(reader.message_count)
    finally:
        reader.close()
    missing = [role for role in ("image_topic", "camera_info_topic", "odometry_topic") if role not in chosen]
    if not mounting["found"]:
        missing.append("mounting")
    return {
        "path": str(path),
        "storage": storage,
        "start": start,
        "end": end,
        "duration_s": max(0.0, end - start),
        "messages": messages,
        "topics": [{"topic": r.topic, "type": r.msgtype, "count": r.count, "rate_hz": r.rate_hz} for r in rows],
        "candidates": candidates,
        "chosen": chosen,
        "mounting": mounting,
        "command": suggested_command(str(path), chosen),
        "missing": missing,
    }


_MISSING = {
    "image_topic": "no sensor_msgs/Image or CompressedImage topic",
    "camera_info_topic": "no sensor_msgs/CameraInfo topic: add dataset.calibration_file=<calibration.yaml>",
    "odometry_topic": "no pose topic for the odometry (Odometry, PoseStamped, ...)",
    "mounting": "the camera's mounting: add dataset.camera_height=<m above the ground> and dataset.camera_tilt=<rad "
    "down>, or dataset.camera_to_base=<4x4>",
}


def render(summary: dict[str, Any]) -> str:
    """The summary as text: a topic table, the roles' topics, the mounting and the command."""
    topics = summary["topics"]
    width = max([len("topic"), *(len(t["topic"]) for t in topics)])
    type_width = max([len("type"), *(len(t["type"]) for t in topics)])
    lines = [
        f"{summary['path']}: {summary['storage']}, {summary['duration_s']:.1f} s, {summary['messages']} messages",
        "",
        f"  {'topic':<{width}}  {'type':<{type_width}}  {'count':>7}  {'rate (Hz)':>9}",
    ]
    for t in topics:
        rate = f"{t['rate_hz']:.1f}" if t["rate_hz"] else "-"
        lines.append(f"  {t['topic']:<{width}}  {t['type']:<{type_width}}  {t['count']:>7d}  {rate:>9}")
    lines.append("")
    for role in ROLES:
        found = summary["candidates"][role]
        others = f" (also: {', '.join(found[1:])})" if len(found) > 1 else ""
        lines.append(f"  {role + ':':<20} {found[0] if found else '-'}{others}")
    mounting = summary["mounting"]
    lines.append(f"  {'mounting:':<20} {mounting['source'] if mounting['found'] else 'unknown'}")
    lines.append("")
    if summary["missing"]:
        lines.append("  to run it, the command below needs: " + "; ".join(_MISSING[m] for m in summary["missing"]))
        if not mounting["found"] and mounting["problem"]:
            lines.append(f"  ({mounting['problem']})")
    lines.append("  " + summary["command"])
    return "\n".join(lines)


@hydra.main(config_path=str(config_dir()), config_name="sgf_bag_info", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Print the topics of the bag given as ``path=...``."""
    if not cfg.get("path"):
        raise DataError(
            f"give the bag: {USAGE} (or path=<bag>); a bag is a file.bag, a ROS 2 bag folder or a file.mcap"
        )
    summary = bag_summary(str(cfg.path), str(cfg.get("typestore") or "ros2_humble"))
    if cfg.get("format") == "json":
        print(json.dumps(summary, indent=2))
    else:
        print(render(summary))


#: The ``sgf-bag-info`` console script: ``sgf-bag-info BAG`` or ``sgf-bag-info path=BAG``.
main = console(app, positional=("path",), usage=USAGE)

if __name__ == "__main__":
    main()
