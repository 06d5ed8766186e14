"""The sun of a world: where it stands, and where the shadows it casts fall."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Sun:
    """Direction of the sun: azimuth (rad, from +x towards +y) and elevation (rad)."""

    azimuth: float
    elevation: float

    @property
    def shadow_offset(self) -> np.ndarray:
        """Ground offset (m) of a shadow cast by a point 1 m high."""
        k = 1.0 / math.tan(self.elevation)
        return -k * np.array([math.cos(self.azimuth), math.sin(self.azimuth)])

    @property
    def direction(self) -> np.ndarray:
        """Unit vector towards the sun (x, y, z)."""
        ce = math.cos(self.elevation)
        return np.array([ce * math.cos(self.azimuth), ce * math.sin(self.azimuth), math.sin(self.elevation)])
