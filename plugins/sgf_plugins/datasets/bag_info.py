"""``sgf-bag-info``: a bag's topics, message types, counts and rates, and the dataset config lines to read it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from sgf_pipeline import DataError
from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir
from sgf_plugins.datasets.rosbag import (
    CAMERA_INFO_TYPES,
    IMAGE_TYPES,
    IMU_TYPES,
    POSE_TYPES,
    open_bag,
    topic_rows,
)

_ROLES = (
    ("image_topic", IMAGE_TYPES),
    ("camera_info_topic", CAMERA_INFO_TYPES),
    ("odometry_topic", POSE_TYPES),
    ("imu_topic", IMU_TYPES),
)


def bag_summary(path: str | Path, typestore: str = "ros2_humble") -> dict[str, Any]:
    """Storage, time span and topics of a bag, plus the topics usable for each dataset role."""
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
        return {
            "path": str(bag),
            "storage": storage,
            "start": start,
            "end": end,
            "duration_s": max(0.0, end - start),
            "messages": int(reader.message_count),
            "topics": [{"topic": r.topic, "type": r.msgtype, "count": r.count, "rate_hz": r.rate_hz} for r in rows],
            "candidates": {role: [r.topic for r in rows if r.msgtype in types] for role, types in _ROLES},
        }
    finally:
        reader.close()


def render(summary: dict[str, Any]) -> str:
    """The summary as text: a topic table and suggested ``dataset=rosbag`` overrides."""
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
    overrides = [f"dataset.{role}={found[0]}" for role, found in summary["candidates"].items() if found]
    if overrides:
        lines += ["", "  sgf-run dataset=rosbag dataset.path=" + summary["path"] + " " + " ".join(overrides)]
    return "\n".join(lines)


@hydra.main(config_path=str(config_dir()), config_name="sgf_bag_info", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Print the topics of the bag given as ``path=...``."""
    if not cfg.get("path"):
        raise DataError("give the bag: sgf-bag-info path=<file.bag | ROS 2 bag folder | file.mcap>")
    summary = bag_summary(str(cfg.path), str(cfg.get("typestore") or "ros2_humble"))
    if cfg.get("format") == "json":
        print(json.dumps(summary, indent=2))
    else:
        print(render(summary))


#: The ``sgf-bag-info`` console script.
main = console(app)

if __name__ == "__main__":
    main()
