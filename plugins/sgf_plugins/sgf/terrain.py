"""Lifting SGF pixels onto the ground the robot drove over (an extension of eq. 9 for uneven ground).

The BEV puts every pixel on one plane: the plane the IPM variant assumed when the view was taken
(the robot's base plane for plain IPM, the reference attitude's plane for MC-IPM). Where the grade
ahead differs from that plane (a slope starting or ending under the marking), a point seen d
metres ahead by a camera h metres high moves by about d^2 / h times the grade difference: 0.56 m
at 4.4 m ahead for 1 degree with the world's 0.6 m camera. By the time a feature has left the
view the robot has driven up to it, so its odometry (3-D: heights and attitude from the IMU) has
measured that ground. Each pixel's camera ray (through the view's homography to the image and the
camera's pose in the odometry frame) is intersected with the driven ground: a surface made of
the base poses since the view, each the local tangent plane of the ground under the wheels,
extended ahead of the newest pose at its grade (``ground_model=base``: :func:`driven_ground` and
:func:`intersect_ground`).

``ground_model=wheels`` (:func:`wheel_ground` and :func:`march_ground`) builds the surface from
the wheels' contact tracks instead, whose points lie on the ground where the base origin, their
average, passes under a speed bump's crest, and marches each ray to its first crossing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from sgf_pipeline.calibration import Calibration

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: Ray-ground iterations: each picks every ray's nearest ground sample, then meets its tangent plane.
ITERATIONS = 5
#: Smallest cosine between a ray and a ground normal (a ray grazing the ground gives no point).
_MIN_INCIDENCE = 1e-3
#: Horizontal step (m) of the march along each ray; the crossing is interpolated within it.
MARCH_STEP = 0.04
#: Height (m) the ground's tangent planes may reach beyond the highest and lowest samples.
RASTER_MARGIN = 0.3
#: Farthest horizontal distance (m) a ray is followed.
MARCH_REACH = 15.0
#: Cell (m) of the raster of the driven ground's height the march reads.
RASTER_CELL = 0.02
#: A ray that passed within GRAZE_HEIGHT (m) of the ground at least GRAZE_LEAD (m) before its
#: crossing skimmed a crest: where it meets the ground is not known (NaN, though covered).
GRAZE_HEIGHT = 0.02
GRAZE_LEAD = 0.2
#: Shortest contact-track chord (m) that gives a slope; shorter ones (a standing robot) keep the base's.
_MIN_CHORD = 0.02


def driven_ground(poses: np.ndarray, ahead: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground samples (K, 3) and their unit normals (K, 3) from base poses (N, 4, 4), in the poses' frame.

    Each pose's base origin is a point of the ground and its z axis the ground's normal there;
    the newest pose's tangent plane is sampled every ``step`` metres up to ``ahead`` metres on.
    """
    poses = _base_poses(poses)
    ahead_points, ahead_normals = _ahead(poses[-1], 0.0, ahead, step)
    points = np.vstack([poses[:, :3, 3], ahead_points])
    normals = np.vstack([poses[:, :3, 2], ahead_normals])
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _base_poses(poses: np.ndarray) -> np.ndarray:
    """Base poses as a float (N, 4, 4) array, N >= 1, or a ValueError that says what came instead."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise ValueError(f"expected base poses of shape (N, 4, 4), got {poses.shape}")
    return poses


def _ahead(last: np.ndarray, start: float, ahead: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """The newest pose's tangent plane sampled every ``step`` m from ``start`` m ahead of its origin for ``ahead`` m."""
    if ahead <= 0.0 or step <= 0.0:
        return np.empty((0, 3)), np.empty((0, 3))
    offsets = start + np.arange(step, ahead + 0.5 * step, step)
    return last[:3, 3] + offsets[:, None] * last[:3, 0], np.repeat(last[None, :3, 2], len(offsets), axis=0)


def pixel_rays(pixels: np.ndarray, homography: np.ndarray, calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """The camera ray of each BEV pixel ``(u, v)``: origin (3,) and unit directions (M, 3) in the base frame."""
    uv1 = np.column_stack([np.asarray(pixels, dtype=np.float64).reshape(-1, 2), np.ones(len(pixels))])
    image = uv1 @ np.asarray(homography, dtype=np.float64).T  # BEV index -> image pixel (homogeneous)
    rays = image @ np.linalg.inv(calibration.intrinsics.matrix).T  # optical frame, z forward
    camera = calibration.camera_to_base_matrix
    directions = rays @ camera[:3, :3].T
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return camera[:3, 3].copy(), directions


def intersect_ground(
    origin: np.ndarray, directions: np.ndarray, points: np.ndarray, normals: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where each ray meets the driven ground: (M, 3) points and whether a ground sample lay within ``radius``.

    Rays start on the first sample's tangent plane; each iteration moves every ray to its nearest
    sample (horizontally) and intersects that sample's plane. A ray whose nearest sample stays
    farther than ``radius`` (m) is not covered by the driven ground: its point is not trusted.
    """
    hit = np.empty((len(directions), 3))
    covered = np.zeros(len(directions), dtype=bool)
    nearest = np.zeros(len(directions), dtype=np.int64)
    for _ in range(ITERATIONS):
        n = normals[nearest]
        cos = np.einsum("ij,ij->i", directions, n)
        ok = cos < -_MIN_INCIDENCE  # the ray goes down through the plane
        t = np.where(ok, np.einsum("ij,ij->i", points[nearest] - origin, n) / np.where(ok, cos, -1.0), np.nan)
        ok &= t > 0.0
        hit = origin + np.where(ok, t, np.nan)[:, None] * directions
        d2 = (hit[:, None, 0] - points[None, :, 0]) ** 2 + (hit[:, None, 1] - points[None, :, 1]) ** 2
        d2 = np.where(ok[:, None], d2, np.inf)
        moved = np.argmin(d2, axis=1)
        covered = ok & (d2[np.arange(len(moved)), moved] <= radius * radius)
        if np.array_equal(moved, nearest):
            break
        nearest = moved
    return hit, covered


def wheel_ground(
    poses: np.ndarray, ahead: float, step: float, contacts: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Ground samples (K, 3) and their unit normals (K, 3) from base poses (N, 4, 4), in the poses' frame.

    ``contacts``: where the wheels touch the ground, metres ahead of the base origin along its x
    axis (a wheelbase of 0.5 m centred on the origin: ``(0.25, -0.25)``). Each pose puts one sample
    on each contact's track: the wheels lie on the ground, where the base origin, their average,
    lies under a bump's crest. A sample's normal is that of the track's slope through its
    neighbours (the ground under the wheel, not the wheelbase's chord) and the base's y axis. The
    newest pose's tangent plane is sampled every ``step`` metres up to ``ahead`` metres past its
    foremost contact.
    """
    poses = _base_poses(poses)
    if not contacts:
        raise ValueError("contacts must name at least one wheel position (metres ahead of the base origin)")
    points, normals = [], []
    for offset in contacts:
        track = poses[:, :3, 3] + offset * poses[:, :3, 0]
        points.append(track)
        normals.append(_track_normals(track, poses))
    ahead_points, ahead_normals = _ahead(poses[-1], max(contacts), ahead, step)
    points.append(ahead_points)
    normals.append(ahead_normals)
    n = np.vstack(normals)
    return np.vstack(points), n / np.linalg.norm(n, axis=1, keepdims=True)


def _track_normals(track: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Normals of a wheel's track: its slope between neighbouring samples, across the base's y axis."""
    normals = poses[:, :3, 2].copy()
    if len(track) < 2:
        return normals
    chord = np.empty_like(track)
    chord[1:-1] = track[2:] - track[:-2]
    chord[0], chord[-1] = track[1] - track[0], track[-1] - track[-2]
    sloped = np.cross(chord, poses[:, :3, 1])
    moving = np.linalg.norm(sloped, axis=1) >= _MIN_CHORD  # along the heading, not standing or sideways
    sloped *= np.sign(np.einsum("ij,ij->i", sloped, normals))[:, None]  # the up side, as the base's z
    normals[moving] = sloped[moving]
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def march_ground(
    origin: np.ndarray, directions: np.ndarray, points: np.ndarray, normals: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where each ray first meets the driven ground: (M, 3) points and whether a ground sample lay within ``radius``.

    The ground under a horizontal position is the tangent plane of its nearest sample. Each ray is
    marched in horizontal steps of ``MARCH_STEP``, from where it comes down to the highest ground,
    until it first passes below the ground (the paint the camera sees, not a slope hidden behind a
    crest), and the crossing is interpolated within the step. A ray that never goes below it, or
    whose crossing has no sample within ``radius`` (m), is not covered: its point is not trusted.
    A ray that skimmed the ground (within ``GRAZE_HEIGHT``) well before its crossing, over a bump's
    crest, is covered but gets a NaN point: a few millimetres of ground height decide whether it
    meets the crest or the ground a metre on.
    """
    from scipy.spatial import cKDTree

    origin = np.asarray(origin, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    hit = np.full((len(directions), 3), np.nan)
    covered = np.zeros(len(directions), dtype=bool)
    across = np.hypot(directions[:, 0], directions[:, 1])
    down = (directions[:, 2] < -_MIN_INCIDENCE) & (across > 1e-9)
    if not down.any() or len(points) == 0:
        return hit, covered
    rays = np.flatnonzero(down)
    slope = directions[rays, 2] / across[rays]  # height change per horizontal metre (< 0)
    unit = directions[rays, :2] / across[rays, None]

    # The ray meets the ground between the levels of the highest and the lowest ground: first
    # bound that band by the samples (tangent planes reach a little beyond them), then by the
    # raster of the ground's height over it.
    def band(top: float, bottom: float) -> tuple[np.ndarray, np.ndarray]:
        near = np.clip((top - origin[2]) / slope, MARCH_STEP, MARCH_REACH)
        return near, np.clip((bottom - origin[2]) / slope, near, MARCH_REACH)

    near, far = band(float(points[:, 2].max()) + RASTER_MARGIN, float(points[:, 2].min()) - RASTER_MARGIN)
    tree = cKDTree(points[:, :2])
    ground = _GroundRaster(tree, points, normals, origin[:2] + near[:, None] * unit, origin[:2] + far[:, None] * unit)
    near, far = band(float(ground.heights.max()), float(ground.heights.min()))
    near = np.maximum(near - MARCH_STEP, MARCH_STEP)
    count = int(np.ceil((far - near).max() / MARCH_STEP)) + 2
    s = near[:, None] + MARCH_STEP * np.arange(count)[None, :]
    xy = origin[:2] + s[..., None] * unit[:, None, :]
    gap = origin[2] + s * slope[:, None] - ground.height(xy)  # > 0 while the ray is above the ground
    gap[s > far[:, None] + MARCH_STEP] = np.inf
    crossed = gap <= 0.0
    done = crossed.any(axis=1)
    k = np.argmax(crossed, axis=1)
    rows = np.arange(len(rays))
    below = gap[rows, k]
    above = np.where(k > 0, gap[rows, np.maximum(k - 1, 0)], np.nan)
    fraction = np.ones(len(rays))
    ok = done & (k > 0) & (above > below)
    fraction[ok] = above[ok] / (above[ok] - below[ok])
    s_hit = s[rows, k] - MARCH_STEP * (1.0 - fraction)
    points_hit = np.column_stack([origin[:2] + s_hit[:, None] * unit, origin[2] + s_hit * slope])
    distance, _ = tree.query(points_hit[:, :2])
    # A ray that skimmed the ground well before its crossing (over a crest) may as well meet it there.
    before = np.arange(count)[None, :] < (k - round(GRAZE_LEAD / MARCH_STEP))[:, None]
    skimmed = (np.where(before, gap, np.inf).min(axis=1) < GRAZE_HEIGHT) & done
    hit[rays[done]] = points_hit[done]
    hit[rays[skimmed]] = np.nan
    covered[rays[done]] = distance[done] <= radius
    return hit, covered


class _GroundRaster:
    """The driven ground's height on a square raster over the rays' reach, read by bilinear interpolation.

    Each cell takes the tangent plane of its nearest sample: one nearest-sample search per cell
    instead of one per march step. ``start`` and ``ends`` (M, 2): where the rays enter and leave it.
    """

    def __init__(self, tree: cKDTree, points: np.ndarray, normals: np.ndarray, start: np.ndarray, ends: np.ndarray):
        lo = np.minimum(start.min(axis=0), ends.min(axis=0)) - 2 * RASTER_CELL
        hi = np.maximum(start.max(axis=0), ends.max(axis=0)) + 2 * RASTER_CELL
        shape = np.ceil((hi - lo) / RASTER_CELL).astype(int) + 1
        gx, gy = np.meshgrid(lo[0] + RASTER_CELL * np.arange(shape[0]), lo[1] + RASTER_CELL * np.arange(shape[1]))
        _, idx = tree.query(np.column_stack([gx.ravel(), gy.ravel()]))
        p, n = points[idx], normals[idx]
        heights = p[:, 2] - (n[:, 0] * (gx.ravel() - p[:, 0]) + n[:, 1] * (gy.ravel() - p[:, 1])) / n[:, 2]
        self.lo = lo
        self.heights = heights.reshape(gx.shape)  # (rows: y, columns: x)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height at horizontal positions (..., 2)."""
        f = (xy - self.lo) / RASTER_CELL
        rows, cols = self.heights.shape
        i = np.clip(np.floor(f[..., 0]).astype(int), 0, cols - 2)
        j = np.clip(np.floor(f[..., 1]).astype(int), 0, rows - 2)
        a = np.clip(f[..., 0] - i, 0.0, 1.0)
        b = np.clip(f[..., 1] - j, 0.0, 1.0)
        h = self.heights
        return (1 - b) * ((1 - a) * h[j, i] + a * h[j, i + 1]) + b * ((1 - a) * h[j + 1, i] + a * h[j + 1, i + 1])
