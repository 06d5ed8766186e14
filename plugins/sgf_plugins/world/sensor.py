"""The camera's sensor: vignetting of the lens and the read noise of the 8-bit output."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.conditions import RenderConditions
from sgf_plugins.world.noise import rng_for
from sgf_plugins.world.raycast import RayCaster


class Sensor:
    """Vignetting (at the samples and at every pixel) and a bank of read noise drawn once."""

    def __init__(self, caster: RayCaster, seed: int, rng: np.random.Generator) -> None:
        self.seed = seed
        intr = caster.calibration.intrinsics
        self.width, self.height = intr.width, intr.height
        uu, vv = caster.uu, caster.vv
        r = np.hypot((uu - intr.cx) / (0.5 * self.width), (vv - intr.cy) / (0.5 * self.height)) / math.sqrt(2)
        self.vignette = (1.0 - 0.22 * r**2).astype(np.float32)
        bank = 128.0 + 32.0 * rng.standard_normal((2, self.height + 32, self.width + 32, 3))
        self.noise_bank = np.clip(bank, 0, 255).astype(np.uint8)
        self.vignette_f = np.ascontiguousarray(caster.upsample(self.vignette))  # at every pixel

    def noise(self, image: np.ndarray, conditions: RenderConditions) -> np.ndarray:
        """Add the sensor's read noise (stronger at night, where the gain is high)."""
        rng = rng_for(self.seed, 421, conditions.noise_seed)
        k = int(rng.integers(len(self.noise_bank)))
        oy, ox = (int(v) for v in rng.integers(0, 32, 2))
        noise = self.noise_bank[k, oy : oy + self.height, ox : ox + self.width]
        sigma = 2.4 if conditions.night else 1.3
        # the bank holds 128 + 32 n (uint8): image + sigma n = image + sigma / 32 (bank - 128)
        out: np.ndarray = cv2.addWeighted(image, 1.0, noise, sigma / 32.0, -128.0 * sigma / 32.0)
        return out
