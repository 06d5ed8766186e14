"""How a frame is rendered: day or night, the time, exposure, lights, occluders and sensor noise."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RenderConditions:
    """How a frame looks: night or day, the time (moving people), exposure, occluders and noise."""

    night: bool = False
    time: float = 0.0
    exposure: float = 1.0
    occluders: bool = True
    extra_occluders: int = 0
    sensor_noise: bool = True
    headlight: bool | None = None
    street_lamps: bool = True
    far_field: bool = True
    noise_seed: int = 0
