"""An exact test scene for IPM: a flat textured ground with known markings seen by a disturbed camera.

Every camera pixel's ray is intersected with the ground plane and the known ground texture is
sampled there, so the ground truth is exact: the markings' corners and masks in the robot's
level base frame. A test tool, not a plugin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_pipeline.calibration import Calibration, Intrinsics, camera_to_base_from_mounting
from sgf_pipeline.geometry import rotation_rpy
from sgf_pipeline.types import BevGrid

ASPHALT = 95.0
PAINT = 235.0
SKY = 200.0
#: Texture raster of the world ground: x in [-2, 40] m, y in [-6, 6] m, at 1 cm.
TEXTURE_ORIGIN = (-2.0, -6.0)
TEXTURE_STEP = 0.01
TEXTURE_SIZE = (4200, 1200)


def scene_calibration(width: int = 640, height: int = 480, focal: float | None = None) -> Calibration:
    """A delivery robot's front camera: 0.8 m high, 0.35 rad down, 0.25 m ahead of the base origin."""
    f = focal if focal is not None else 500.0 * width / 640.0
    intrinsics = Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)
    return Calibration(intrinsics=intrinsics, camera_to_base=camera_to_base_from_mounting(0.8, 0.35, x=0.25))


@dataclass(frozen=True)
class Marking:
    """A painted rectangle on the ground: instance id and its four world corners (x, y)."""

    instance_id: int
    corners: np.ndarray


def _rectangle(instance_id: int, cx: float, cy: float, length: float, width: float, yaw: float) -> Marking:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=np.float64) * [length / 2, width / 2]
    return Marking(instance_id, local @ np.array([[c, s], [-s, c]]) + [cx, cy])


def default_markings(length: float = 36.0, period: float = 3.0) -> list[Marking]:
    """Markings along the route, one group every ``period`` m: stripes, a bar, a tilted plate."""
    out: list[Marking] = []
    next_id = 1
    for k, x0 in enumerate(float(x) for x in np.arange(1.0, length, period)):
        side = 1.0 if k % 2 == 0 else -1.0
        for j in range(3):  # three crosswalk stripes across the path
            out.append(_rectangle(next_id, x0 + 0.45 * j, 0.9 * side, 0.22, 1.2, 0.0))
            next_id += 1
        out.append(_rectangle(next_id, x0 + 1.2, -1.3 * side, 0.9, 0.15, 0.0))  # a lane bar along the path
        next_id += 1
        out.append(_rectangle(next_id, x0 + 2.0, 0.3 * side, 0.5, 0.35, 0.5 * side))  # a rotated plate
        next_id += 1
    return out


def _texture(seed: int = 7) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, (TEXTURE_SIZE[0] // 4, TEXTURE_SIZE[1] // 4)).astype(np.float32)
    coarse = cv2.resize(noise, (TEXTURE_SIZE[1], TEXTURE_SIZE[0]), interpolation=cv2.INTER_CUBIC)
    fine = rng.normal(0.0, 1.0, TEXTURE_SIZE).astype(np.float32)
    return (ASPHALT + 12.0 * coarse + 6.0 * cv2.GaussianBlur(fine, (0, 0), 1.0)).astype(np.float32)


class GroundScene:
    """A world ground plane (z = 0) with asphalt texture and painted markings, rasterised at 1 cm."""

    def __init__(self, markings: list[Marking] | None = None, seed: int = 7) -> None:
        self.markings = markings if markings is not None else default_markings()
        self.ids = np.zeros(TEXTURE_SIZE, dtype=np.int32)
        shift = 4  # sub-pixel vertices: 1/16 of the 1 cm raster
        for m in self.markings:
            rows = (m.corners[:, 0] - TEXTURE_ORIGIN[0]) / TEXTURE_STEP
            cols = (m.corners[:, 1] - TEXTURE_ORIGIN[1]) / TEXTURE_STEP
            polygon = np.rint(np.column_stack([cols, rows]) * (1 << shift)).astype(np.int32)
            cv2.fillConvexPoly(self.ids, polygon, int(m.instance_id), lineType=cv2.LINE_8, shift=shift)
        self.texture = np.where(self.ids > 0, np.float32(PAINT), _texture(seed)).astype(np.float32)

    def ground(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (bilinear) and marking instance id (nearest) at world ground points."""
        mx = ((np.asarray(x) - TEXTURE_ORIGIN[0]) / TEXTURE_STEP).astype(np.float32)
        my = ((np.asarray(y) - TEXTURE_ORIGIN[1]) / TEXTURE_STEP).astype(np.float32)
        value = cv2.remap(self.texture, my, mx, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        ids = cv2.remap(self.ids, my, mx, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return value, ids

    def exact_ids(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Marking instance id at world ground points, from the exact polygons."""
        ids = np.zeros(np.shape(x), dtype=np.int32)
        for m in self.markings:
            inside = np.ones(np.shape(x), dtype=bool)
            for i in range(4):
                a, b = m.corners[i], m.corners[(i + 1) % 4]
                inside &= (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) <= 0.0
            ids[inside] = m.instance_id
        return ids


def camera_pose(
    calibration: Calibration, robot_x: float, roll: float, pitch: float, pivot: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World rotation and position of the camera of a robot at ``robot_x`` with a ground-relative attitude.

    The robot body rolls and pitches (``Ry(pitch) Rx(roll)``, about the base axes) about the camera
    centre, or about ``pivot`` (a point in the base frame, e.g. a wheel contact) when given.
    """
    base = calibration.camera_to_base_matrix
    attitude = rotation_rpy(roll, pitch, 0.0)
    rotation = attitude @ base[:3, :3]
    position = base[:3, 3].copy()
    if pivot is not None:
        position = attitude @ (position - pivot) + pivot
    return rotation, position + np.array([robot_x, 0.0, 0.0])


def render(
    scene: GroundScene,
    calibration: Calibration,
    robot_x: float,
    roll: float = 0.0,
    pitch: float = 0.0,
    pivot: np.ndarray | None = None,
    supersample: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """The camera image (RGB uint8) and the marking instance id at each pixel centre."""
    intr = calibration.intrinsics
    rotation, position = camera_pose(calibration, robot_x, roll, pitch, pivot)
    k_inv = np.linalg.inv(intr.matrix)
    acc = np.zeros((intr.height, intr.width), dtype=np.float64)
    ids_centre = np.zeros((intr.height, intr.width), dtype=np.int32)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    for du in offsets:
        for dv in offsets:
            v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
            rays = np.stack([u + du, v + dv, np.ones_like(u)], axis=-1) @ k_inv.T @ rotation.T
            down = rays[..., 2] < -1e-9
            t = np.where(down, -position[2] / np.where(down, rays[..., 2], -1.0), 0.0)
            x = position[0] + t * rays[..., 0]
            y = position[1] + t * rays[..., 1]
            value, ids = scene.ground(np.where(down, x, 0.0), np.where(down, y, 0.0))
            acc += np.where(down, value, SKY)
            if du == offsets[len(offsets) // 2] and dv == offsets[len(offsets) // 2]:
                ids_centre = np.where(down, ids, 0)
    grey = np.clip(np.rint(acc / supersample**2), 0, 255).astype(np.uint8)
    if supersample % 2 == 0:  # no sample at the centre: take the instance at the centre ray itself
        _, ids_centre = render(scene, calibration, robot_x, roll, pitch, pivot, supersample=1)
    return np.repeat(grey[:, :, None], 3, axis=2), ids_centre


def project(
    calibration: Calibration, points_world: np.ndarray, robot_x: float, roll: float, pitch: float, pivot=None
) -> tuple[np.ndarray, np.ndarray]:
    """Image pixels of world ground points under the true camera pose, and whether they are in front."""
    rotation, position = camera_pose(calibration, robot_x, roll, pitch, pivot)
    p = np.column_stack([points_world, np.zeros(len(points_world))]) - position
    cam = p @ rotation  # = rotation.T @ p for each point
    uvw = cam @ calibration.intrinsics.matrix.T
    front = cam[:, 2] > 1e-6
    return uvw[:, :2] / np.where(front, uvw[:, 2], 1.0)[:, None], front


def corner_errors(
    scene: GroundScene,
    calibration: Calibration,
    grid: BevGrid,
    bev_to_image: np.ndarray,
    robot_x: float,
    roll: float,
    pitch: float,
    pivot: np.ndarray | None = None,
) -> np.ndarray:
    """Distance (m) between where each visible marking corner appears in the BEV and where it truly lies.

    The corner is imaged by the true camera, then mapped back through the IPM's BEV -> image
    homography into the BEV, whose pixel -> ground mapping (eq. 9) gives where the BEV puts it.
    """
    intr = calibration.intrinsics
    corners = np.concatenate([m.corners for m in scene.markings])
    truth = corners - [robot_x, 0.0]  # level base frame of the robot
    inside = (truth[:, 0] >= grid.x_min) & (truth[:, 0] <= grid.x_max)
    inside &= (truth[:, 1] >= grid.y_min) & (truth[:, 1] <= grid.y_max)
    pixels, front = project(calibration, corners, robot_x, roll, pitch, pivot)
    inside &= front & (pixels[:, 0] >= 0) & (pixels[:, 0] <= intr.width - 1)
    inside &= (pixels[:, 1] >= 0) & (pixels[:, 1] <= intr.height - 1)
    mapped = np.column_stack([pixels[inside], np.ones(int(inside.sum()))]) @ np.linalg.inv(bev_to_image).T
    u, v = mapped[:, 0] / mapped[:, 2], mapped[:, 1] / mapped[:, 2]
    x, y = grid.pixel_to_ground(u, v)
    return np.hypot(x - truth[inside, 0], y - truth[inside, 1])


def truth_mask(scene: GroundScene, grid: BevGrid, robot_x: float) -> np.ndarray:
    """The orthographic marking-instance layout of the BEV grid (exact, at pixel centres)."""
    v, u = np.mgrid[0 : grid.height, 0 : grid.width].astype(np.float64)
    x, y = grid.pixel_to_ground(u, v)
    return scene.exact_ids(x + robot_x, y)
