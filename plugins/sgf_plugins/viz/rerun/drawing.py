"""How the pipeline's outputs look in a Rerun recording: colours, JPEG images, SGF outlines, map coordinates."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from sgf_plugins.loop import outcomes
from sgf_plugins.viz.figures import group_colour

if TYPE_CHECKING:
    from sgf_pipeline.types import SalientGroundFeature

JPEG_QUALITY = 75
#: The colour of each loop candidate's outcome.
OUTCOME_COLOURS = {
    outcomes.ACCEPTED: (60, 200, 80),
    outcomes.GATE: (255, 150, 30),
    outcomes.ICP: (240, 220, 50),
    outcomes.CONSENSUS: (160, 110, 255),
    outcomes.AMBIGUOUS: (60, 200, 230),
    outcomes.SYMMETRIC: (150, 150, 150),
    outcomes.SEPARATION: (170, 110, 60),
    outcomes.TOO_FEW_POINTS: (250, 120, 160),
    outcomes.NOT_UNIQUE: (140, 160, 40),
    outcomes.MAP_UNCONFIRMED: (40, 160, 150),
}
#: The colour of each trajectory.
TRAJECTORY_COLOURS = {"odometry": (230, 60, 50), "ground_truth": (220, 220, 220), "estimate": (60, 140, 255)}


def outcome_colour(outcome: str) -> tuple[int, int, int]:
    """The colour of a loop candidate's outcome (an outcome without its own colour gets its name's)."""
    known = OUTCOME_COLOURS.get(outcome)
    if known is not None:
        return known
    return group_colour(sum(outcome.encode()))


def jpeg(image: np.ndarray, bgr: bool = False) -> bytes:
    """JPEG bytes of a uint8 grey or RGB image (``bgr``: already in OpenCV's channel order)."""
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 3 and not bgr:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise ValueError(f"could not encode an image of shape {image.shape} as JPEG")
    return buffer.tobytes()


def outline(sgf: SalientGroundFeature) -> list[np.ndarray]:
    """The closed outlines of an SGF's BEV pixels, in the BEV image's coordinates (pixel centres at +0.5)."""
    pixels = np.asarray(sgf.pixels)
    if pixels.size == 0:
        return []
    h, w = sgf.grid.height, sgf.grid.width
    mask = np.zeros((h, w), np.uint8)
    mask[pixels[:, 1].clip(0, h - 1), pixels[:, 0].clip(0, w - 1)] = 1
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    strips = []
    for contour in contours:
        points = contour.reshape(-1, 2).astype(np.float32) + 0.5
        strips.append(np.vstack([points, points[:1]]))
    return strips


def nanoseconds(seconds: float) -> int:
    """A time in whole nanoseconds, as the recording's ``time`` timeline holds it."""
    return round(seconds * 1e9)


def map_xy(positions: np.ndarray) -> np.ndarray:
    """Map-view coordinates of 3-D positions: x right, y up (a 2-D view's y points down)."""
    return np.column_stack([positions[:, 0], -positions[:, 1]]).astype(np.float32)
