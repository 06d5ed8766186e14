"""A marking design rasterised in its local frame at a texel size, with worn paint."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sgf_plugins.world.canvas import RGB, Canvas
from sgf_plugins.world.designs import MarkingDesign
from sgf_plugins.world.noise import lattice_noise


@dataclass(frozen=True)
class Raster:
    """A marking rasterised in its local frame: colour, worn paint alpha and the instance mask."""

    colour: np.ndarray
    alpha: np.ndarray
    mask: np.ndarray
    res: float
    x_top: float
    y_left: float

    def local_to_pixel_matrix(self) -> np.ndarray:
        """2x3 affine map from local ``(x, y, 1)`` to pixel ``(col, row)``."""
        r = self.res
        return np.array([[0.0, -1.0 / r, self.y_left / r - 0.5], [-1.0 / r, 0.0, self.x_top / r - 0.5]])


def rasterise(
    design: MarkingDesign,
    length: float,
    width: float,
    res: float,
    colour: RGB,
    content_seed: int,
    wear: float = 0.0,
    wear_seed: int = 0,
) -> Raster:
    """Draw a design at ``res`` m/pixel; ``wear`` in [0, 1] fades and chips the paint (not the mask).

    ``content_seed`` picks the instance's content (words, numbers) and must be the same at every
    resolution so that all levels of detail show the same marking.
    """
    canvas = Canvas(length, width, res)
    design.draw(canvas, np.random.default_rng(content_seed), colour)
    rgb, alpha = canvas.compose()
    mask = alpha > 0.5
    if wear > 0.0:
        # Chips and fading fixed in the marking's own frame, so every level of detail agrees.
        x0 = -canvas.y_left
        chips = lattice_noise(wear_seed, x0, canvas.x_top, canvas.cols, canvas.rows, res, 0.08)
        blotch = lattice_noise(wear_seed + 1, x0, canvas.x_top, canvas.cols, canvas.rows, res, 0.64)
        keep = np.clip(1.0 - wear * (0.45 + 0.35 * blotch) - np.where(chips > 1.0 - 0.9 * wear, 0.8, 0.0), 0.05, 1.0)
        if design.material != "paint":
            keep = np.clip(0.6 + 0.4 * keep, 0.0, 1.0)
        alpha = alpha * keep.astype(np.float32)
    return Raster(rgb, alpha.astype(np.float32), mask, res, canvas.x_top, canvas.y_left)
