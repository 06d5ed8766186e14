"""Camera calibration: intrinsics, distortion, camera-to-base extrinsics, and the IPM geometry."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# Rotation from the level optical frame (x right, y down, z forward) to the base frame
# (x forward, y left, z up).
OPTICAL_TO_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class Intrinsics(BaseModel):
    """Pinhole intrinsics in pixels, with the image size they belong to."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0)
    height: int = Field(gt=0)

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


class Distortion(BaseModel):
    """Lens distortion: ``radtan`` (OpenCV k1 k2 p1 p2 [k3]) or ``equidistant`` (k1..k4)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    model: Literal["none", "radtan", "equidistant"] = "none"
    coefficients: tuple[float, ...] = ()

    @model_validator(mode="after")
    def _check_count(self) -> Distortion:
        allowed = {"none": (0,), "radtan": (4, 5, 8), "equidistant": (4,)}[self.model]
        if len(self.coefficients) not in allowed and not (self.model == "none"):
            raise ValueError(
                f"distortion model {self.model!r} takes {' or '.join(map(str, allowed))} coefficients, "
                f"got {len(self.coefficients)}"
            )
        return self

    @property
    def is_identity(self) -> bool:
        """Whether the lens has no distortion to undo."""
        return self.model == "none" or not any(self.coefficients)


def camera_to_base_from_mounting(
    height: float, tilt: float, x: float = 0.0, y: float = 0.0, roll: float = 0.0, yaw: float = 0.0
) -> np.ndarray:
    """Pose of the camera (optical frame) in the base frame for a camera tilted ``tilt`` rad down."""
    ct, st = math.cos(tilt), math.sin(tilt)
    # Tilting down is a rotation of the optical frame about its own x axis by -tilt.
    tilt_rot = np.array([[1.0, 0.0, 0.0], [0.0, ct, st], [0.0, -st, ct]])
    cr, sr = math.cos(roll), math.sin(roll)
    roll_rot = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])  # about the optical axis
    cy, sy = math.cos(yaw), math.sin(yaw)
    yaw_rot = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])  # about base z
    pose = np.eye(4)
    pose[:3, :3] = yaw_rot @ OPTICAL_TO_BASE @ tilt_rot @ roll_rot
    pose[:3, 3] = (x, y, height)
    return pose


class Calibration(BaseModel):
    """A camera's calibration: intrinsics, distortion and its pose on the robot."""

    model_config = ConfigDict(extra="forbid", frozen=True, arbitrary_types_allowed=True)

    intrinsics: Intrinsics
    distortion: Distortion = Distortion()
    camera_to_base: tuple[tuple[float, float, float, float], ...] = Field(
        description="4x4 pose of the camera optical frame in the robot base frame (row-major)"
    )

    @field_validator("camera_to_base", mode="before")
    @classmethod
    def _as_rows(cls, value: object) -> object:
        if isinstance(value, np.ndarray):
            return tuple(tuple(float(x) for x in row) for row in value)
        return value

    @model_validator(mode="after")
    def _check_pose(self) -> Calibration:
        m = np.asarray(self.camera_to_base, dtype=float)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError("camera_to_base must be a finite 4x4 matrix")
        r = m[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or not np.allclose(m[3], (0, 0, 0, 1)):
            raise ValueError("camera_to_base must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        return self

    @classmethod
    def from_mounting(
        cls, intrinsics: Intrinsics, height: float, tilt: float, distortion: Distortion | None = None
    ) -> Calibration:
        """Calibration of a forward camera ``height`` m above the ground, tilted ``tilt`` rad down."""
        return cls(
            intrinsics=intrinsics,
            distortion=distortion or Distortion(),
            camera_to_base=camera_to_base_from_mounting(height, tilt),
        )

    @property
    def camera_to_base_matrix(self) -> np.ndarray:
        """The camera pose in the base frame as a 4x4 array."""
        return np.asarray(self.camera_to_base, dtype=np.float64)

    @property
    def height(self) -> float:
        """Height of the camera centre above the ground plane (m), ``h_c`` of eq. 2."""
        return float(self.camera_to_base_matrix[2, 3])

    @property
    def tilt(self) -> float:
        """Angle between the optical axis and the ground plane (rad, positive down), ``alpha`` of eq. 2."""
        axis = self.camera_to_base_matrix[:3, 2]
        return float(math.asin(max(-1.0, min(1.0, -axis[2]))))
