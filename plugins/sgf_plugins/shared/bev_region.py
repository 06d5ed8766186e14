"""The BEV region a camera sees: the configured one, or one of its size on the nearest ground in view.

The shipped regions (``ipm.x_min`` 0.5 m ...) fit the delivery robot's camera, 0.6 m high and
tilted 25 degrees down. A car's camera, 1.65 m high and nearly level, sees the road only from
about 6 m ahead: ``region: auto`` then moves the region there (:func:`choose_region`), keeping its
size and resolution, and says so once in the log.
"""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np

from sgf_pipeline import ConfigError
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.types import BevGrid
from sgf_plugins.shared.bev_homography import MIN_DEPTH, bev_to_image_homography, visible_mask

log = logging.getLogger("sgf_pipeline.ipm")
Region = Literal["auto", "fixed"]
#: ``region: auto`` keeps the configured region when the camera sees at least this share of it.
MIN_SEEN = 0.5

#: The BEV grid of the IPM stages and of the synthetic world's visibility: 256 x 256 cells of 2 cm,
#: from 0.5 m ahead of the base, centred on it.
BEV_GRID = BevGrid(resolution=0.02, x_min=0.5, x_max=5.62, y_min=-2.56, y_max=2.56)


# -- the ground the camera sees ----------------------------------------------------------------------

#: How far out (m) the nearest visible ground is looked for.
MAX_GROUND_RANGE = 200.0


def ground_visible(calibration: Calibration, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Which base-frame ground points ``(x, y, 0)`` the camera images (in front of it, inside the image)."""
    pose = calibration.camera_to_base_matrix
    points = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64), np.zeros(np.shape(x))], axis=-1)
    camera = (points - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t), row-wise
    k = calibration.intrinsics
    depth = camera[..., 2]
    ahead = depth > MIN_DEPTH
    safe = np.where(ahead, depth, 1.0)
    u = k.fx * camera[..., 0] / safe + k.cx
    v = k.fy * camera[..., 1] / safe + k.cy
    return ahead & (u >= 0.0) & (u <= k.width - 1.0) & (v >= 0.0) & (v <= k.height - 1.0)


def seen_fraction(calibration: Calibration, grid: BevGrid) -> float:
    """The share of a BEV grid's pixels the camera sees."""
    k = calibration.intrinsics
    return float(visible_mask(bev_to_image_homography(calibration, grid), grid, k.width, k.height).mean())


def view_direction(calibration: Calibration) -> tuple[float, float]:
    """``(yaw, depression)`` of the optical axis in rad: from the base's x axis (left +), below the horizon.

    A camera looking straight down takes the image's up direction for its yaw.
    """
    rotation = calibration.camera_to_base_matrix[:3, :3]
    axis = rotation[:, 2]
    horizontal = axis[:2] if float(np.hypot(*axis[:2])) > 1e-6 else -rotation[:2, 1]
    depression = math.asin(max(-1.0, min(1.0, -float(axis[2]))))
    return math.atan2(float(horizontal[1]), float(horizontal[0])), depression


def _direction_word(yaw: float) -> str:
    degrees = math.degrees(yaw)
    if abs(degrees) <= 45.0:
        return "ahead"
    if abs(degrees) >= 135.0:
        return "behind"
    return "to the left" if degrees > 0 else "to the right"


def nearest_region(calibration: Calibration, grid: BevGrid) -> BevGrid | None:
    """A grid of ``grid``'s size and resolution on the nearest ground the camera sees, or None when it sees none.

    The camera's viewing direction (its optical axis on the ground) picks the side: ahead, behind,
    left or right of the robot. The region's near edge is the nearest ground seen along the line
    through its middle, on ``grid``'s pixel lattice; across that line it keeps ``grid``'s span
    (ahead or behind) or is centred on the camera (left or right).
    """
    yaw, _ = view_direction(calibration)
    side = _direction_word(yaw)
    r = grid.resolution
    depth_x, depth_y = grid.x_max - grid.x_min, grid.y_max - grid.y_min
    foot = calibration.camera_to_base_matrix[:2, 3]
    along_x = side in ("ahead", "behind")
    sign = 1.0 if side in ("ahead", "to the left") else -1.0
    origin, start = (grid.x_min, float(foot[0])) if along_x else (grid.y_min, float(foot[1]))
    extent = depth_x if along_x else depth_y
    # candidate near edges on the lattice origin + k r, from the camera's foot outwards
    steps = np.arange(0, round(MAX_GROUND_RANGE / r) + 1)
    if sign > 0:
        near = origin + (math.ceil((start - origin) / r - 1e-9) + steps) * r
        mid = near + 0.5 * r
    else:
        far = origin + extent + (math.floor((start - origin - extent) / r + 1e-9) - steps) * r
        near, mid = far - extent, far - 0.5 * r
    if along_x:
        centre = np.full(mid.shape, 0.5 * (grid.y_min + grid.y_max))
        seen = ground_visible(calibration, mid, centre)
    else:
        x_min = grid.x_min + round((float(foot[0]) - 0.5 * depth_x - grid.x_min) / r) * r
        seen = ground_visible(calibration, np.full(mid.shape, x_min + 0.5 * depth_x), mid)
    if not seen.any():
        return None
    low = float(near[int(np.argmax(seen))])
    if along_x:
        return BevGrid(r, round(low, 9), round(low + depth_x, 9), grid.y_min, grid.y_max)
    return BevGrid(r, round(x_min, 9), round(x_min + depth_x, 9), round(low, 9), round(low + depth_y, 9))


def describe_view(calibration: Calibration) -> str:
    """Where the camera looks and the nearest ground it sees, for messages."""
    yaw, depression = view_direction(calibration)
    side = _direction_word(yaw)
    tilt = round(math.degrees(depression), 1) + 0.0  # no "-0.0"
    level = f"{abs(tilt):.1f} deg {'below' if tilt >= 0 else 'above'} the horizon"
    words = f"{calibration.height:.2f} m high, optical axis {level}"
    if side != "ahead" or abs(yaw) > math.radians(1.0):
        words += f", turned {math.degrees(yaw):.0f} deg from the robot's forward axis (looking {side})"
    probe = nearest_region(calibration, BevGrid(0.01, -0.005, 0.005, -0.005, 0.005))
    if probe is None:
        return words + "; it sees no ground (the ground lies outside its image)"
    x, y = 0.5 * (probe.x_min + probe.x_max), 0.5 * (probe.y_min + probe.y_max)
    return words + f"; the nearest ground it sees {side} is about {math.hypot(x, y):.2f} m from the base origin"


# -- the region --------------------------------------------------------------------------------------


def _describe(grid: BevGrid) -> str:
    return f"x in [{grid.x_min:g}, {grid.x_max:g}] m, y in [{grid.y_min:g}, {grid.y_max:g}] m"


def choose_region(calibration: Calibration, grid: BevGrid, region: Region, what: str) -> BevGrid:
    """The region to resample: ``grid``, or (``auto``, the camera seeing under half of it) the nearest one in view.

    ``what`` names the config group in messages (``ipm``, ``odometry_scale``). A region the
    camera does not see at all is a :class:`ConfigError` with ``fixed``, and so is a camera that
    sees no ground.
    """
    seen = seen_fraction(calibration, grid)
    if region == "fixed" or seen >= MIN_SEEN:
        if seen > 0.0:
            return grid
        raise ConfigError(
            f"no pixel of the {what} region {_describe(grid)} is visible from the camera "
            f"({describe_view(calibration)}); set {what}.x_min/x_max/y_min/y_max to a region the camera sees, or "
            f"{what}.region=auto to take the nearest one"
        )
    moved = nearest_region(calibration, grid)
    if moved is None:
        raise ConfigError(
            f"the camera sees no ground for the {what} region ({describe_view(calibration)}): check the camera's "
            "mounting (camera_to_base, or its height and tilt)"
        )
    log.info(
        "%s: the camera sees %.0f %% of the configured region %s (%s); using %s, the nearest ground in view "
        "(%.0f %% seen)",
        what,
        100.0 * seen,
        _describe(grid),
        describe_view(calibration),
        _describe(moved),
        100.0 * seen_fraction(calibration, moved),
    )
    return moved
