"""The project's folder dataset format (version 1): what ``sgf-world`` writes and ``dataset=folder`` reads.

Layout of a sequence folder::

    sequence.yaml       format: sgf-folder, version: 1, name, rate_hz, frames
    calibration.yaml    intrinsics {fx, fy, cx, cy, width, height}, distortion {model, coefficients},
                        camera_to_base: 4x4 rows (camera optical frame in the robot base frame)
    images/000000.png   one image per frame (PNG or JPEG; grey or colour), sorted by name
    timestamps.txt      one timestamp in seconds per image, same order
    odometry.tum        TUM poses of the base in the odometry frame, one per image timestamp
    imu.csv             optional: header ``timestamp,roll,pitch`` (rad), one row per image
    groundtruth.tum     optional: TUM poses of the base in the world frame
    masks/000000.png    optional: uint16 PNG of marking instance ids (0 = none), per image
    truth.json          optional: marking table, passes and revisit pairs (synthetic worlds)

Rules the reader holds a folder to (docs/datasets.md has the full description):

* Frames are the images in name order; frame ``i`` is the ``i``-th image, and every per-image
  file (timestamps, odometry, IMU) has exactly one row per image, at the image's timestamp
  (to 1e-6 s). Timestamps increase strictly.
* Poses are of the robot's base (x forward, y left, z up, origin on the ground under the robot).
  ``distortion.model`` is ``none``, ``radtan`` (OpenCV k1 k2 p1 p2 [k3 [k4 k5 k6]]) or
  ``equidistant`` (k1..k4); the reader hands on undistorted images.
* ``groundtruth.tum`` may instead come at its own rate (motion capture, LiDAR SLAM): it is then
  interpolated at the image timestamps.
* A mask's file name is the image's stem with ``.png``; a frame without one has no mask.
* ``sequence.yaml`` may be left out of a hand-made folder (the name is then the folder's); when
  present its ``frames`` must equal the number of images.
* Nothing is ever written into a folder that is read.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
import yaml

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.errors import DataError
from sgf_pipeline.io import atomic_write_text, read_text, read_yaml
from sgf_pipeline.trajectory import Trajectory, write_tum
from sgf_pipeline.truth import MarkingPass, MarkingTruth, RevisitPair, SequenceTruth

FORMAT = "sgf-folder"
VERSION = 1


def calibration_to_dict(calibration: Calibration) -> dict[str, Any]:
    """Plain-data form of a calibration, as written to ``calibration.yaml``."""
    return {
        "intrinsics": calibration.intrinsics.model_dump(),
        "distortion": {
            "model": calibration.distortion.model,
            "coefficients": list(calibration.distortion.coefficients),
        },
        "camera_to_base": [list(row) for row in calibration.camera_to_base],
    }


def read_calibration_yaml(path: str | os.PathLike[str]) -> Calibration:
    """Read ``calibration.yaml``; a missing or malformed file gives a clear error."""
    p = Path(path)
    if not p.is_file():
        raise DataError(f"calibration file not found: {p}")
    data = read_yaml(p, "calibration file")
    if not isinstance(data, dict):
        raise DataError(f"{p}: expected a mapping with intrinsics, distortion and camera_to_base")
    try:
        return Calibration.model_validate(data)
    except Exception as exc:
        raise DataError(f"{p}: invalid calibration: {exc}") from None


def truth_to_dict(truth: SequenceTruth) -> dict[str, Any]:
    """Plain-data form of a sequence's ground truth, as written to ``truth.json``."""
    return {
        "markings": [asdict(m) for m in truth.markings.values()],
        "passes": [asdict(p) for p in truth.passes],
        "revisits": [
            {"instance_id": r.instance_id, "first": r.first.number, "second": r.second.number, "reverse": r.reverse}
            for r in truth.revisits
        ],
    }


class _TruthReader:
    """Checks the plain data of ``truth.json`` field by field; errors name the entry and the key."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, message: str) -> NoReturn:
        """Raise a DataError about one entry."""
        raise DataError(f"{self.source}{where}: {message}")

    def entries(self, data: dict[str, Any], key: str, fields: tuple[str, ...]) -> list[dict[str, Any]]:
        """The list under ``key``: mappings with exactly ``fields``."""
        items = data.get(key, [])
        if not isinstance(items, list):
            self.fail(f" {key}", f"must be a list, got {type(items).__name__}")
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                self.fail(f" {key}[{i}]", f"must be a mapping with {', '.join(fields)}, got {item!r:.60}")
            if set(item) != set(fields):
                missing, extra = sorted(set(fields) - set(item)), sorted(set(item) - set(fields), key=str)
                self.fail(f" {key}[{i}]", f"missing {missing}, unknown {extra}; the fields are {', '.join(fields)}")
        return items

    def integer(self, where: str, value: object, minimum: int | None = None) -> int:
        """A whole number (not a bool), at least ``minimum``."""
        if isinstance(value, bool) or not isinstance(value, int) or (minimum is not None and value < minimum):
            bound = f" >= {minimum}" if minimum is not None else ""
            self.fail(where, f"must be an integer{bound}, got {value!r:.40}")
        return int(value)

    def number(self, where: str, value: object, minimum: float | None = None) -> float:
        """A finite number (not a bool), at least ``minimum``."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(where, f"must be a finite number, got {value!r:.40}")
        if minimum is not None and value < minimum:
            self.fail(where, f"must be at least {minimum}, got {value!r:.40}")
        return float(value)

    def numbers(self, where: str, value: object, count: int, minimum: float | None = None) -> tuple[float, ...]:
        """``count`` finite numbers."""
        if not isinstance(value, list) or len(value) != count:
            self.fail(where, f"must be a list of {count} numbers, got {value!r:.60}")
        return tuple(self.number(f"{where}[{i}]", v, minimum) for i, v in enumerate(value))

    def flag(self, where: str, value: object) -> bool:
        """A JSON boolean."""
        if not isinstance(value, bool):
            self.fail(where, f"must be true or false, got {value!r:.40}")
        return value


def truth_from_dict(data: Any, source: str = "truth") -> SequenceTruth:
    """Inverse of :func:`truth_to_dict`: every field checked, every reference resolved (else a DataError)."""
    reader = _TruthReader(source)
    if not isinstance(data, dict):
        reader.fail("", f"must be a mapping with markings, passes and revisits, got {type(data).__name__}")
    unknown = sorted(set(data) - {"markings", "passes", "revisits"}, key=str)
    if unknown:
        reader.fail("", f"unknown key(s) {unknown}; the keys are markings, passes, revisits")
    markings: dict[int, MarkingTruth] = {}
    for i, m in enumerate(reader.entries(data, "markings", _MARKING_FIELDS)):
        at = f" markings[{i}]"
        instance = reader.integer(f"{at}.instance_id", m["instance_id"], 1)
        if instance in markings:
            reader.fail(f"{at}.instance_id", f"{instance} is listed twice")
        if not isinstance(m["design"], str):
            reader.fail(f"{at}.design", f"must be a name, got {m['design']!r:.40}")
        if m["category"] not in ("standard", "custom"):
            reader.fail(f"{at}.category", f"must be standard or custom, got {m['category']!r:.40}")
        pose = reader.numbers(f"{at}.pose", m["pose"], 3)
        size = reader.numbers(f"{at}.size", m["size"], 2, 0.0)
        symmetric = reader.flag(f"{at}.symmetric", m["symmetric"])
        markings[instance] = MarkingTruth(
            instance, m["design"], m["category"], symmetric, (pose[0], pose[1], pose[2]), (size[0], size[1])
        )
    passes: dict[tuple[int, int], MarkingPass] = {}
    for i, p in enumerate(reader.entries(data, "passes", _PASS_FIELDS)):
        at = f" passes[{i}]"
        instance = reader.integer(f"{at}.instance_id", p["instance_id"], 1)
        if instance not in markings:
            reader.fail(f"{at}.instance_id", f"marking {instance} is not in markings")
        number = reader.integer(f"{at}.number", p["number"], 0)
        start = reader.integer(f"{at}.start_frame", p["start_frame"], 0)
        end = reader.integer(f"{at}.end_frame", p["end_frame"], start)
        if (instance, number) in passes:
            reader.fail(at, f"pass {number} of marking {instance} is listed twice")
        passes[(instance, number)] = MarkingPass(
            instance, number, start, end, reader.number(f"{at}.heading", p["heading"])
        )
    revisits = []
    for i, r in enumerate(reader.entries(data, "revisits", _REVISIT_FIELDS)):
        at = f" revisits[{i}]"
        instance = reader.integer(f"{at}.instance_id", r["instance_id"], 1)
        ends = []
        for key in ("first", "second"):
            found = passes.get((instance, reader.integer(f"{at}.{key}", r[key], 0)))
            if found is None:
                reader.fail(f"{at}.{key}", f"marking {instance} has no pass {r[key]}")
            ends.append(found)
        revisits.append(RevisitPair(instance, ends[0], ends[1], reader.flag(f"{at}.reverse", r["reverse"])))
    return SequenceTruth(markings=markings, passes=list(passes.values()), revisits=revisits)


_MARKING_FIELDS = ("instance_id", "design", "category", "symmetric", "pose", "size")
_PASS_FIELDS = ("instance_id", "number", "start_frame", "end_frame", "heading")
_REVISIT_FIELDS = ("instance_id", "first", "second", "reverse")


def read_truth_json(path: str | os.PathLike[str]) -> SequenceTruth:
    """Read ``truth.json``; a malformed file gives a DataError that names the entry at fault."""
    p = Path(path)
    text = read_text(p, "truth file")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(f"{p}:{exc.lineno}: not valid JSON: {exc.msg}") from None
    except RecursionError:
        raise DataError(f"{p}: not valid JSON: nested too deeply") from None
    return truth_from_dict(data, str(p))


class FolderDatasetWriter:
    """Stream frames into a new sequence folder; the folder appears whole when ``close`` succeeds.

    Frames are written into ``<root>.partial`` and renamed onto ``root`` at the end, so an
    interrupted export never leaves a folder that looks complete. An existing ``root`` is
    refused unless ``overwrite`` is set.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        name: str,
        calibration: Calibration,
        rate_hz: float | None = None,
        image_format: str = "png",
        overwrite: bool = False,
    ) -> None:
        self.root = Path(root)
        if self.root.exists() and not overwrite:
            raise DataError(f"{self.root} exists already; choose another folder or allow overwriting")
        if image_format not in ("png", "jpg"):
            raise DataError(f"image_format must be png or jpg, got {image_format!r}")
        self.tmp = self.root.with_name(self.root.name + ".partial")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        (self.tmp / "images").mkdir(parents=True)
        self.name = name
        self.calibration = calibration
        self.rate_hz = rate_hz
        self.image_format = image_format
        self._timestamps: list[float] = []
        self._odometry: list[np.ndarray] = []
        self._ground_truth: list[np.ndarray] = []
        self._imu: list[tuple[float, float]] = []
        self._masks = False

    def add(
        self,
        timestamp: float,
        image: np.ndarray,
        odometry: np.ndarray,
        imu_roll_pitch: tuple[float, float] | None = None,
        ground_truth: np.ndarray | None = None,
        instance_ids: np.ndarray | None = None,
    ) -> None:
        """Append one frame (image RGB or grey uint8; instance ids written as uint16 PNG)."""
        index = len(self._timestamps)
        stem = f"{index:06d}"
        bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(self.tmp / "images" / f"{stem}.{self.image_format}"), bgr):
            raise DataError(f"could not write image {stem} into {self.tmp}")
        if instance_ids is not None:
            if instance_ids.max(initial=0) > np.iinfo(np.uint16).max:
                raise DataError("instance ids above 65535 cannot be stored in a uint16 mask")
            (self.tmp / "masks").mkdir(exist_ok=True)
            cv2.imwrite(str(self.tmp / "masks" / f"{stem}.png"), instance_ids.astype(np.uint16))
            self._masks = True
        self._timestamps.append(float(timestamp))
        self._odometry.append(np.asarray(odometry, dtype=np.float64))
        if imu_roll_pitch is not None:
            self._imu.append((float(imu_roll_pitch[0]), float(imu_roll_pitch[1])))
        if ground_truth is not None:
            self._ground_truth.append(np.asarray(ground_truth, dtype=np.float64))

    def close(self, truth: SequenceTruth | None = None) -> Path:
        """Write the metadata files and move the finished folder into place."""
        n = len(self._timestamps)
        if n == 0:
            raise DataError("no frames were added")
        ts = np.asarray(self._timestamps)
        write_tum(self.tmp / "odometry.tum", Trajectory(ts, np.stack(self._odometry)))
        if self._ground_truth:
            if len(self._ground_truth) != n:
                raise DataError(f"ground truth given for {len(self._ground_truth)} of {n} frames")
            write_tum(self.tmp / "groundtruth.tum", Trajectory(ts, np.stack(self._ground_truth)))
        if self._imu:
            if len(self._imu) != n:
                raise DataError(f"IMU attitude given for {len(self._imu)} of {n} frames")
            rows = ["timestamp,roll,pitch"] + [
                f"{t:.9f},{r:.9f},{p:.9f}" for t, (r, p) in zip(ts, self._imu, strict=True)
            ]
            atomic_write_text(self.tmp / "imu.csv", "\n".join(rows) + "\n")
        atomic_write_text(self.tmp / "timestamps.txt", "\n".join(f"{t:.9f}" for t in ts) + "\n")
        atomic_write_text(self.tmp / "calibration.yaml", yaml.safe_dump(calibration_to_dict(self.calibration)))
        meta = {"format": FORMAT, "version": VERSION, "name": self.name, "rate_hz": self.rate_hz, "frames": n}
        atomic_write_text(self.tmp / "sequence.yaml", yaml.safe_dump(meta, sort_keys=False))
        if truth is not None:
            atomic_write_text(self.tmp / "truth.json", json.dumps(truth_to_dict(truth)) + "\n")
        if self.root.exists():
            shutil.rmtree(self.root)
        os.replace(self.tmp, self.root)
        return self.root
