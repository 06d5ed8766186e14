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
import yaml

from sgf_pipeline.calibration import Calibration, Distortion, Intrinsics
from sgf_pipeline.errors import DataError
from sgf_pipeline.folder_format import read_calibration_yaml

__all__ = [
    "EurocCamera",
    "calibration_from_camera_info",
    "distortion_from_name",
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
    coeffs = tuple(float(c) for c in coefficients)
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
    with p.open("rb") as fh:
        head = fh.read(32)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            width, height = struct.unpack(">II", head[16:24])
            return int(width), int(height)
        if head[:2] == b"\xff\xd8":
            fh.seek(2)
            while True:
                marker = fh.read(2)
                if len(marker) < 2 or marker[0] != 0xFF:
                    break
                if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:
                    continue
                length_bytes = fh.read(2)
                if len(length_bytes) < 2:
                    break
                (length,) = struct.unpack(">H", length_bytes)
                if marker[1] in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                    data = fh.read(5)
                    height, width = struct.unpack(">HH", data[1:5])
                    return int(width), int(height)
                fh.seek(length - 2, os.SEEK_CUR)
    import cv2

    image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataError(f"{p}: not an image that can be read (corrupt, truncated or an unknown format)")
    return int(image.shape[1]), int(image.shape[0])


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
    for number, line in enumerate(p.read_text().splitlines(), start=1):
        if ":" not in line:
            continue
        key, _, values = line.partition(":")
        try:
            numbers = [float(v) for v in values.split()]
        except ValueError:
            continue  # calib_time: 09-Jan-2012 13:57:47 and other non-matrix lines
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


def _euroc_matrix(node: object, key: str, source: Path) -> np.ndarray:
    if isinstance(node, dict) and "data" in node:
        data = node["data"]
        rows, cols = int(node.get("rows", 4)), int(node.get("cols", 4))
    else:
        data, rows, cols = node, 4, 4
    try:
        matrix = np.asarray(data, dtype=np.float64).reshape(rows, cols)
    except (TypeError, ValueError):
        raise DataError(f"{source}: {key} must be a 4x4 matrix ({{rows: 4, cols: 4, data: [16 numbers]}})") from None
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise DataError(f"{source}: {key} must be a finite 4x4 matrix, got shape {matrix.shape}")
    return matrix


def read_euroc_sensor_yaml(path: str | os.PathLike[str]) -> EurocCamera:
    """Read an EuRoC/ASL camera ``sensor.yaml`` (pinhole intrinsics, radtan/equidistant distortion, ``T_BS``)."""
    p = Path(path)
    if not p.is_file():
        raise DataError(f"camera sensor file not found: {p}")
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise DataError(f"{p}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise DataError(f"{p}: expected a mapping with intrinsics, resolution, distortion_model and T_BS")
    missing = [k for k in ("intrinsics", "resolution") if k not in data]
    if missing:
        raise DataError(f"{p}: missing {', '.join(missing)}; keys present: {', '.join(map(str, data))}")
    model = str(data.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise DataError(f"{p}: camera_model {model!r} is not supported; only the pinhole projection is")
    try:
        fx, fy, cx, cy = (float(v) for v in data["intrinsics"])
        width, height = (int(v) for v in data["resolution"])
        intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{p}: intrinsics must be [fu, fv, cu, cv] and resolution [width, height]: {exc}") from None
    distortion = distortion_from_name(
        str(data.get("distortion_model", "none")), data.get("distortion_coefficients") or [], str(p)
    )
    camera_to_body = _euroc_matrix(data.get("T_BS", np.eye(4).tolist()), "T_BS", p)
    rate = data.get("rate_hz")
    return EurocCamera(intrinsics, distortion, camera_to_body, float(rate) if rate else None)


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
    kk = np.asarray(k, dtype=np.float64)
    if kk.size != 9 or not np.all(np.isfinite(kk)) or kk[0] <= 0 or kk[4] <= 0:
        raise DataError(
            f"{source}: K must hold 9 finite numbers with fx, fy > 0 (is the camera calibrated?), got {kk.tolist()}"
        )
    if width <= 0 or height <= 0:
        raise DataError(f"{source}: the image size is {width}x{height}; the camera driver left it unset")
    intrinsics = Intrinsics(fx=kk[0], fy=kk[4], cx=kk[2], cy=kk[5], width=int(width), height=int(height))
    distortion = distortion_from_name(distortion_model, list(d), source)
    return Calibration(intrinsics=intrinsics, distortion=distortion, camera_to_base=camera_to_base)
