"""The BEV region a camera sees: the configured one, or one of its size on the nearest ground in view.

The shipped regions (``ipm.x_min`` 0.5 m ...) fit the delivery robot's camera, 0.6 m high and
tilted 25 degrees down. A car's camera, 1.65 m high and nearly level, sees the road only from
about 6 m ahead: ``region: auto`` then moves the region there (:func:`choose_region`), keeping its
size and resolution, and says so once in the log.
"""

from __future__ import annotations

import logging
from typing import Literal

from sgf_pipeline import ConfigError
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.types import BevGrid
from sgf_plugins.ipm.geometry import describe_view, nearest_region, seen_fraction

log = logging.getLogger("sgf_pipeline.ipm")
Region = Literal["auto", "fixed"]
#: ``region: auto`` keeps the configured region when the camera sees at least this share of it.
MIN_SEEN = 0.5


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
