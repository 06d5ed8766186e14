"""Shared machinery of the recorded-data adapters: camera mounting, strict/skip handling, image decoding."""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from sgf_pipeline import DataError, Dataset, RunContext, StageParams
from sgf_pipeline.calibration import Calibration, camera_to_base_from_mounting
from sgf_pipeline.io import describe_dir
from sgf_pipeline.types import Frame
from sgf_pipeline.undistortion import Undistorter

log = logging.getLogger("sgf_pipeline.datasets")

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"
_LOGGED_PER_REASON = 5


class RecordedParams(StageParams):
    """Options every recorded-data adapter has."""

    path: str = Field("", description="the recording (folder or file); required")
    strict: bool = Field(
        True,
        description="stop at the first bad frame or message; false skips it, logs it and counts it in metrics.json",
    )
    undistort: bool = Field(True, description="undistort images when the calibration has lens distortion")


class MountingParams(RecordedParams):
    """Recorded-data options plus how the camera sits on the robot, for recordings whose files do not say it."""

    camera_height: float | None = Field(None, gt=0.0, description="camera centre above the ground (m)")
    camera_tilt: float = Field(
        0.0, ge=-math.pi / 2, le=math.pi / 2, description="optical axis below the horizon (rad, positive down)"
    )
    camera_to_base: list[list[float]] | None = Field(
        None, description="4x4 pose of the camera optical frame in the base frame; overrides height and tilt"
    )


def mounting_matrix(params: MountingParams, dataset: str) -> np.ndarray | None:
    """The camera-to-base pose from the mounting parameters, or ``None`` when none were given."""
    if params.camera_to_base is not None:
        matrix = np.asarray(params.camera_to_base, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise DataError(f"dataset.camera_to_base must be a 4x4 matrix (4 rows of 4), got shape {matrix.shape}")
        return matrix
    if params.camera_height is not None:
        return camera_to_base_from_mounting(params.camera_height, params.camera_tilt)
    return None


class SkipLog:
    """Bad frames or messages: an error under ``strict: true``; under ``strict: false`` logged, counted, skipped."""

    def __init__(self, strict: bool, dataset: str) -> None:
        self.strict = strict
        self.dataset = dataset
        self.counts: Counter[str] = Counter()

    def problem(self, reason: str, message: str) -> None:
        """Raise (strict) or count and log one skipped item; ``reason`` is a short key for metrics."""
        if self.strict:
            raise DataError(
                f"dataset={self.dataset}: {message}. Fix the recording, or set dataset.strict=false to skip "
                "such frames and go on (they are counted in metrics.json)"
            )
        self.counts[reason] += 1
        if self.counts[reason] <= _LOGGED_PER_REASON:
            log.warning("dataset=%s: skipped (%s): %s", self.dataset, reason, message)
        elif self.counts[reason] == _LOGGED_PER_REASON + 1:
            log.warning("dataset=%s: more skips of kind %r; logging no more of them", self.dataset, reason)

    @property
    def total(self) -> int:
        """Number of skipped items."""
        return sum(self.counts.values())

    def metrics(self) -> dict[str, Any]:
        """``{"skipped": n, "skipped_by_reason": {...}}`` for metrics.json."""
        return {"skipped": self.total, "skipped_by_reason": dict(sorted(self.counts.items()))}


def _complete(data: bytes | memoryview | np.ndarray) -> str | None:
    """Why encoded image bytes are visibly incomplete, or ``None``."""
    raw = bytes(data[:8]) if not isinstance(data, np.ndarray) else data[:8].tobytes()
    size = len(data)
    tail = bytes(data[-32:]) if not isinstance(data, np.ndarray) else data[-32:].tobytes()
    if size == 0:
        return "the file is empty"
    if raw.startswith(_PNG_MAGIC) and _PNG_END not in tail:
        return "the PNG has no end chunk (truncated)"
    if raw.startswith(b"\xff\xd8") and b"\xff\xd9" not in tail:
        return "the JPEG has no end marker (truncated)"
    return None


def to_uint8_rgb_or_grey(image: np.ndarray, bgr: bool = True) -> np.ndarray:
    """An OpenCV-decoded image as uint8 RGB (H, W, 3) or grey (H, W); 16-bit values are scaled by 1/256."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise DataError(f"images must be 8- or 16-bit, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if bgr else image
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if bgr else cv2.COLOR_RGBA2RGB)
    raise DataError(f"unsupported image shape {image.shape}")


def decode_image_bytes(data: bytes | memoryview | np.ndarray, what: str) -> np.ndarray:
    """Decode PNG/JPEG (or any OpenCV format) bytes to uint8 RGB or grey; bad data gives a clear error."""
    why = _complete(data)
    if why is not None:
        raise DataError(f"{what}: {why}")
    buffer = data if isinstance(data, np.ndarray) else np.frombuffer(data, dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataError(f"{what}: cannot decode the image (corrupt data or not an image format OpenCV reads)")
    return to_uint8_rgb_or_grey(image)


def read_image_file(path: Path) -> np.ndarray:
    """Read an image file to uint8 RGB or grey; missing, truncated or corrupt files give a clear error."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise DataError(f"image {path} cannot be read: {exc}") from None
    return decode_image_bytes(data, f"image {path}")


def finite_pose(pose: np.ndarray) -> bool:
    """Whether a 4x4 pose is finite with a proper rotation."""
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        return False
    rot = pose[:3, :3]
    return bool(np.allclose(rot @ rot.T, np.eye(3), atol=1e-3))


class RecordedDataset(Dataset):
    """Base of the adapters of recorded data: skip accounting and undistortion."""

    params: Any
    calibration: Calibration

    def __init__(self, params: StageParams) -> None:
        super().__init__(params)
        self.skips = SkipLog(bool(getattr(params, "strict", True)), self.name)
        self.yielded = 0
        self.undistorter: Undistorter | None = None

    def recording_dir(self, what: str) -> Path:
        """The ``dataset.path`` folder, checked; ``what`` says what it should hold."""
        if not self.params.path:
            raise DataError(f"dataset={self.name} needs the {what}: dataset.path=<folder>")
        root = Path(self.params.path).expanduser()
        if not root.is_dir():
            raise DataError(f"dataset.path: {describe_dir(root)}")
        return root

    def make_frame(
        self, index: int, t: float, image: np.ndarray | Callable[[], np.ndarray], odometry: np.ndarray
    ) -> Frame:
        """A frame with the IMU attitude and ground truth associated at time ``t`` (counted as yielded)."""
        p = self.params
        attitude = getattr(self, "attitude", None)
        truth = getattr(self, "ground_truth", None)
        roll_pitch = None if attitude is None else attitude.at(t, p.max_time_diff, True)
        gt = None if truth is None else truth.at(t, p.max_time_diff, p.interpolate)
        self.yielded += 1
        return Frame(
            index=index,
            timestamp=t,
            image=image,
            odometry=odometry,
            calibration=self.calibration,
            imu_roll_pitch=None if roll_pitch is None else (float(roll_pitch[0]), float(roll_pitch[1])),
            ground_truth=gt,
        )

    def prepare_calibration(self, calibration: Calibration) -> Calibration:
        """The calibration the frames carry: undistorted pinhole when ``undistort`` is on."""
        if getattr(self.params, "undistort", True) and not calibration.distortion.is_identity:
            self.undistorter = Undistorter(calibration)
            return self.undistorter.calibration
        self.undistorter = None
        return calibration

    def image_source(self, load: Callable[[], np.ndarray], what: str) -> np.ndarray | Callable[[], np.ndarray] | None:
        """A lazy image (strict) or the decoded image now, ``None`` when it is bad (non-strict: skipped)."""
        undistorter = self.undistorter

        def finish() -> np.ndarray:
            image = load()
            return undistorter(image) if undistorter is not None else image

        if self.skips.strict:

            def lazy() -> np.ndarray:
                try:
                    return finish()
                except DataError as exc:
                    raise DataError(
                        f"dataset={self.name}: {what}: {exc}. Fix or remove the file, or set dataset.strict=false "
                        "to skip bad images"
                    ) from None

            return lazy
        try:
            return finish()
        except DataError as exc:
            self.skips.problem("bad image", f"{what}: {exc}")
            return None

    def finalize(self, context: RunContext) -> None:
        """Record the frames yielded and the skips in ``metrics.json`` under ``dataset``."""
        entry = dict(context.metrics.get("dataset", {}))
        entry.update({"name": self.name, "frames": self.yielded, **self.skips.metrics()})
        context.metrics["dataset"] = entry
