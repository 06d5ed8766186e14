"""Camera calibration readers: the folder YAML, KITTI ``calib.txt``, EuRoC ``sensor.yaml`` and ROS CameraInfo.

Each returns the project's :class:`~sgf_pipeline.calibration.Calibration` pieces: intrinsics and
distortion, and the camera's pose where the file states one (EuRoC's ``T_BS``). How the camera
sits on the robot's base (height above the ground, tilt) is never in these files except the
folder YAML; the adapters take it as a parameter.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sgf_pipeline.calibration import Calibration, Distortion, Intrinsics
from sgf_pipeline.errors import DataError
from sgf_pipeline.folder_format import read_calibration_yaml
from sgf_pipeline.io import read_text, read_yaml

__all__ = [
    "EurocCamera",
    "calibration_from_camera_info",
    "distortion_from_name",
    "euroc_matrix",
    "image_size",
    "intrinsics_from_projection",
    "read_calibration_yaml",
    "read_euroc_sensor_yaml",
    "read_kitti_calib",
]

#: Distortion model names used by ROS, Kalibr/EuRoC and OpenCV, mapped to the project's two models.
_MODEL_NAMES = {
    "": "none",
    "none": "none",
    "pinhole": "none",
    "plumb_bob": "radtan",
    "rational_polynomial": "radtan",
    "radtan": "radtan",
    "radial-tangential": "radtan",
    "radial_tangential": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
    "kannala_brandt": "equidistant",
}


def distortion_from_name(model: str, coefficients: Sequence[float], source: str = "") -> Distortion:
    """A :class:`Distortion` from any common model name (``plumb_bob``, ``radial-tangential``, ``equidistant`` ...)."""
    where = f"{source}: " if source else ""
    key = model.strip().lower()
    if key not in _MODEL_NAMES:
        known = ", ".join(sorted(k for k in _MODEL_NAMES if k))
        raise DataError(f"{where}unknown distortion model {model!r}; supported: {known}")
    if isinstance(coefficients, (str, bytes)) or not isinstance(coefficients, Sequence | np.ndarray):
        raise DataError(f"{where}distortion coefficients must be a list of numbers, got {coefficients!r:.80}")
    try:
        coeffs = tuple(float(c) for c in coefficients)
    except (TypeError, ValueError):
        raise DataError(f"{where}distortion coefficients must be numbers, got {list(coefficients)!r:.80}") from None
    if not all(math.isfinite(c) for c in coeffs):
        raise DataError(f"{where}non-finite distortion coefficient in {list(coeffs)}")
    kind = _MODEL_NAMES[key]
    if kind == "none" or not any(coeffs):
        return Distortion()
    if kind == "radtan" and len(coeffs) not in (4, 5, 8):
        # ROS pads plumb_bob to 5 and rational_polynomial to 8; trailing zeros beyond those are harmless.
        trimmed = coeffs[:8] if len(coeffs) > 8 and not any(coeffs[8:]) else coeffs
        if len(trimmed) not in (4, 5, 8):
            raise DataError(
                f"{where}{model} takes 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {len(coeffs)}"
            )
        coeffs = trimmed
    if kind == "equidistant" and len(coeffs) != 4:
        raise DataError(f"{where}the equidistant (fisheye) model takes 4 coefficients k1..k4, got {len(coeffs)}")
    try:
        return Distortion(model=kind, coefficients=coeffs)
    except ValueError as exc:
        raise DataError(f"{where}{exc}") from None


def image_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """``(width, height)`` of a PNG or JPEG file, read from its header (decodes only other formats)."""
    p = Path(path)
    try:
        size = _header_size(p)
    except OSError as exc:
        raise DataError(f"{p}: cannot be read: {exc.strerror or exc}") from None
    if size is None:
        import cv2

        image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DataError(f"{p}: not an image that can be read (corrupt, truncated or an unknown format)")
        size = int(image.shape[1]), int(image.shape[0])
    if size[0] <= 0 or size[1] <= 0:
        raise DataError(f"{p}: the image header gives a size of {size[0]}x{size[1]} px")
    return size


def _header_size(p: Path) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG or JPEG header, or None (another format, or a header cut short)."""
    with p.open("rb") as fh:
        head = fh.read(32)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
            width, height = struct.unpack(">II", head[16:24])
            return int(width), int(height)
        if head[:2] == b"\xff\xd8":
            fh.seek(2)
            while True:
                marker = fh.read(2)
                if len(marker) < 2 or marker[0] != 0xFF:
                    return None
                if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:
                    continue
                length_bytes = fh.read(2)
                if len(length_bytes) < 2:
                    return None
                (length,) = struct.unpack(">H", length_bytes)
                if marker[1] in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                    data = fh.read(5)
                    if len(data) < 5:
                        return None
                    height, width = struct.unpack(">HH", data[1:5])
                    return int(width), int(height)
                if length < 2:
                    return None
                fh.seek(length - 2, os.SEEK_CUR)
    return None


def intrinsics_from_projection(projection: np.ndarray, width: int, height: int) -> Intrinsics:
    """Pinhole intrinsics of a 3x4 (or 3x3) projection matrix ``P = K [R | t]`` of a rectified camera."""
    p = np.asarray(projection, dtype=np.float64)
    try:
        return Intrinsics(fx=p[0, 0], fy=p[1, 1], cx=p[0, 2], cy=p[1, 2], width=width, height=height)
    except ValueError as exc:
        raise DataError(f"projection matrix {p.tolist()} gives invalid intrinsics: {exc}") from None


def read_kitti_calib(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """The matrices of a KITTI ``calib.txt`` (``P0: 12 numbers`` ... ``Tr: ...``), each as 3x4.

    The left grey camera of the odometry benchmark is ``P0`` (``P_rect_00`` in the raw data's
    ``calib_cam_to_cam.txt``); its intrinsics come from :func:`intrinsics_from_projection`.
    """
    p = Path(path)
    if not p.is_file():
        raise DataError(
            f"KITTI calibration file not found: {p}. Give its path with dataset.calib=<file>, or the "
            "intrinsics with dataset.intrinsics={fx: ..., fy: ..., cx: ..., cy: ...}"
        )
    matrices: dict[str, np.ndarray] = {}
    for number, line in enumerate(read_text(p, "KITTI calibration file").split("\n"), start=1):
        if ":" not in line:
            continue
        key, _, values = line.partition(":")
        try:
            numbers = [float(v) for v in values.split()]
        except ValueError:
            continue  # calib_time: 09-Jan-2012 13:57:47 and other non-matrix lines
        if numbers and not all(math.isfinite(v) for v in numbers):
            raise DataError(f"{p}:{number}: {key.strip()} holds a non-finite number (NaN or inf)")
        if len(numbers) == 12:
            matrices[key.strip()] = np.asarray(numbers).reshape(3, 4)
        elif len(numbers) == 9:
            matrices[key.strip()] = np.hstack([np.asarray(numbers).reshape(3, 3), np.zeros((3, 1))])
        elif numbers and key.strip().startswith("P"):
            raise DataError(f"{p}:{number}: {key.strip()} has {len(numbers)} numbers, a projection matrix has 12")
    if not matrices:
        raise DataError(f"{p}: no matrices found; a KITTI calib.txt has lines like 'P0: fx 0 cx 0 0 fy cy 0 0 0 1 0'")
    return matrices


def kitti_projection(matrices: dict[str, np.ndarray], camera: int, source: str = "") -> np.ndarray:
    """The projection matrix of camera ``camera`` (``P<n>`` or ``P_rect_0<n>``) from :func:`read_kitti_calib`."""
    for key in (f"P{camera}", f"P_rect_0{camera}", f"P_rect_{camera:02d}"):
        if key in matrices:
            return matrices[key]
    raise DataError(
        f"{source or 'calib.txt'} has no projection of camera {camera} (P{camera}); it has: {sorted(matrices)}"
    )


@dataclass(frozen=True)
class EurocCamera:
    """A camera of an EuRoC/ASL ``sensor.yaml``: intrinsics, distortion, pose in the body frame, rate."""

    intrinsics: Intrinsics
    distortion: Distortion
    camera_to_body: np.ndarray
    rate_hz: float | None


def euroc_matrix(node: object, key: str, source: Path) -> np.ndarray:
    """A 4x4 matrix of an ASL ``sensor.yaml`` (``{rows, cols, data}`` or a plain nested list)."""
    usage = f"{source}: {key} must be a finite 4x4 matrix ({{rows: 4, cols: 4, data: [16 numbers]}})"
    if isinstance(node, dict):
        if "data" not in node or node.get("rows", 4) != 4 or node.get("cols", 4) != 4:
            raise DataError(f"{usage}, got {node!r:.120}")
        node = node["data"]
    try:
        matrix = np.asarray(node, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{usage}, got {node!r:.120}") from None
    if not np.all(np.isfinite(matrix)):
        raise DataError(f"{usage}; it holds NaN or inf")
    return matrix


def _numbers(value: object, count: int, kind: type, key: str, source: Path, meaning: str) -> list[float]:
    """``count`` numbers of one YAML key, converted by ``kind`` (float or int), with a clear error."""
    if isinstance(value, (str, bytes, dict)) or not isinstance(value, Sequence) or len(value) != count:
        raise DataError(f"{source}: {key} must be a list of {count} numbers ({meaning}), got {value!r:.80}")
    try:
        out = [kind(v) for v in value]
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{source}: {key} must be a list of {count} numbers ({meaning}), got {value!r:.80}") from None
    if kind is int and any(isinstance(v, float) and not float(v).is_integer() for v in value):
        raise DataError(f"{source}: {key} must hold whole numbers ({meaning}), got {value!r:.80}")
    return out


def read_euroc_sensor_yaml(path: str | os.PathLike[str]) -> EurocCamera:
    """Read an EuRoC/ASL camera ``sensor.yaml`` (pinhole intrinsics, radtan/equidistant distortion, ``T_BS``)."""
    p = Path(path)
    if not p.is_file():
        raise DataError(f"camera sensor file not found: {p}")
    data = read_yaml(p, "camera sensor file")
    if not isinstance(data, dict):
        raise DataError(f"{p}: expected a mapping with intrinsics, resolution, distortion_model and T_BS")
    missing = [k for k in ("intrinsics", "resolution") if k not in data]
    if missing:
        raise DataError(f"{p}: missing {', '.join(missing)}; keys present: {', '.join(map(str, data))}")
    model = str(data.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise DataError(f"{p}: camera_model {model!r} is not supported; only the pinhole projection is")
    fx, fy, cx, cy = _numbers(data["intrinsics"], 4, float, "intrinsics", p, "fu, fv, cu, cv")
    width, height = _numbers(data["resolution"], 2, int, "resolution", p, "width, height")
    try:
        intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=int(width), height=int(height))
    except ValueError as exc:
        raise DataError(f"{p}: invalid intrinsics or resolution: {_first_error(exc)}") from None
    coefficients = data.get("distortion_coefficients")
    distortion = distortion_from_name(
        str(data.get("distortion_model", "none")), [] if coefficients is None else coefficients, str(p)
    )
    camera_to_body = euroc_matrix(data.get("T_BS", np.eye(4).tolist()), "T_BS", p)
    rate = data.get("rate_hz")
    if rate is not None and (
        isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate < 0
    ):
        raise DataError(f"{p}: rate_hz must be a positive number of frames per second, got {rate!r:.40}")
    return EurocCamera(intrinsics, distortion, camera_to_body, float(rate) if rate else None)


def _first_error(exc: ValueError) -> str:
    """The first line of a pydantic validation error, or the message of another ValueError."""
    errors = getattr(exc, "errors", None)
    if callable(errors):
        items = errors()
        if items:
            message = str(items[0]["msg"]).removeprefix("Value error, ")
            if not items[0]["loc"]:  # a check of the whole model
                return message
            loc = ".".join(str(x) for x in items[0]["loc"])
            return f"{loc}: {message} (got {items[0].get('input')!r:.40})"
    return str(exc)


def calibration_from_camera_info(
    width: int,
    height: int,
    k: Sequence[float],
    d: Sequence[float],
    distortion_model: str,
    camera_to_base: np.ndarray,
    source: str = "CameraInfo",
) -> Calibration:
    """A calibration from the fields of a ROS ``sensor_msgs/CameraInfo`` and the camera's pose on the base."""
    try:
        kk = np.asarray(k, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise DataError(f"{source}: K must hold 9 numbers, got {k!r:.80}") from None
    if kk.size != 9 or not np.all(np.isfinite(kk)) or kk[0] <= 0 or kk[4] <= 0:
        raise DataError(
            f"{source}: K must hold 9 finite numbers with fx, fy > 0 (is the camera calibrated?), got {kk.tolist()}"
        )
    if width <= 0 or height <= 0:
        raise DataError(f"{source}: the image size is {width}x{height}; the camera driver left it unset")
    intrinsics = Intrinsics(fx=kk[0], fy=kk[4], cx=kk[2], cy=kk[5], width=int(width), height=int(height))
    distortion = distortion_from_name(distortion_model, list(d), source)
    try:
        return Calibration(intrinsics=intrinsics, distortion=distortion, camera_to_base=camera_to_base)
    except ValueError as exc:
        raise DataError(f"{source}: {_first_error(exc)}") from None
