"""A ground feature followed over its valid feature range (paper Sec. III-B, step 2): views, prediction, association."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sgf_pipeline.geometry import invert
from sgf_pipeline.types import BevGrid
from sgf_plugins.sgf.regions import Region

#: Most pixels of a view projected into the next frame to predict where its feature went.
PREDICTION_SAMPLES = 4000


@dataclass(frozen=True)
class FeatureView:
    """One view of a tracked feature: a region with the frame it was seen in."""

    frame_index: int
    timestamp: float
    odometry: np.ndarray
    region: Region
    homography: np.ndarray | None = None


@dataclass
class FeatureTrack:
    """A physical ground feature followed over its valid feature range (Sec. III-B, step 1)."""

    track_id: int
    views: list[FeatureView] = field(default_factory=list)
    missed: int = 0

    @property
    def last(self) -> FeatureView:
        """The newest view."""
        return self.views[-1]


def predict_view(view: FeatureView, odometry: np.ndarray, grid: BevGrid) -> tuple[np.ndarray, np.ndarray]:
    """Ground points of a view moved into the current base frame, and their (u, v) pixels."""
    pixels = view.region.pixels
    if len(pixels) > PREDICTION_SAMPLES:
        pixels = pixels[:: -(-len(pixels) // PREDICTION_SAMPLES)]
    x, y = grid.pixel_to_ground(pixels[:, 0], pixels[:, 1])
    delta = invert(odometry) @ view.odometry
    gx = delta[0, 0] * x + delta[0, 1] * y + delta[0, 3]
    gy = delta[1, 0] * x + delta[1, 1] * y + delta[1, 3]
    u, v = grid.ground_to_pixel(gx, gy)
    return np.stack([gx, gy], axis=1), np.stack([np.rint(u), np.rint(v)], axis=1).astype(np.int64)


def associate(
    tracks: list[FeatureTrack],
    labels: np.ndarray,
    regions: list[Region],
    valid: np.ndarray,
    odometry: np.ndarray,
    grid: BevGrid,
    min_overlap: float,
    max_centroid_distance: float,
) -> tuple[dict[int, int], set[int]]:
    """Greedy track-to-region assignment (track index -> region index) and the tracks that left the view.

    A region continues a track when ``min_overlap`` of the track's predicted pixels fall on it, or,
    without any overlap, when its centroid lies within ``max_centroid_distance`` (m) of the predicted one.
    """
    h, w = labels.shape
    centroids = [np.stack(grid.pixel_to_ground(*r.pixels.mean(axis=0)), axis=0) for r in regions]
    candidates: list[tuple[float, float, int, int]] = []
    left: set[int] = set()
    for t, track in enumerate(tracks):
        ground, uv = predict_view(track.last, odometry, grid)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        uv_in = uv[inside]
        seen = valid[uv_in[:, 1], uv_in[:, 0]] if len(uv_in) else np.zeros(0, dtype=bool)
        if not seen.any():
            left.add(t)
            continue
        hits = np.bincount(labels[uv_in[seen, 1], uv_in[seen, 0]], minlength=len(regions) + 1)[1:]
        predicted_centroid = ground.mean(axis=0)
        for r in range(len(regions)):
            share = hits[r] / float(seen.sum())
            dist = float(np.linalg.norm(centroids[r] - predicted_centroid))
            if share >= min_overlap or (hits[r] == 0 and dist <= max_centroid_distance):
                candidates.append((-share, dist, t, r))
    candidates.sort()
    matches: dict[int, int] = {}
    used: set[int] = set()
    for _, _, t, r in candidates:
        if t in matches or r in used:
            continue
        matches[t] = r
        used.add(r)
    return matches, left


def moved_enough(before: np.ndarray, now: np.ndarray, min_motion: float, min_turn: float) -> bool:
    """Whether the robot moved ``min_motion`` (m) or turned ``min_turn`` (rad) between two odometry poses."""
    if min_motion <= 0.0 and min_turn <= 0.0:
        return True
    delta = invert(before) @ now
    turned = math.acos(max(-1.0, min(1.0, (float(np.trace(delta[:3, :3])) - 1.0) / 2.0)))
    return float(np.linalg.norm(delta[:3, 3])) >= min_motion or turned >= min_turn
