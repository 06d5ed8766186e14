"""The polar context and eq. 10 on real ground points: Scan Context's KITTI 00 Velodyne scans 94, 95, 198, 199.

Scans 94 and 95 are 0.48 m apart, 198 and 199 0.52 m, and 94 and 198 about 58 m: a place
descriptor must put each consecutive pair closer than the far pair. The SGF descriptor is built
from ground points only (every SGF point lies on the ground), here the scans' ground returns:

- the paper's setting (L_max = 2 m, N_r = 10, N_s = 90) around the ground point 6 m ahead of the
  sensor. Around the sensor itself there is nothing to describe: the HDL-64's lowest beam meets
  the road only about 3.7 m away. 6 m ahead lies on the first full rings of ground returns, and,
  like an SGF, the descriptor is centred on the centroid of the points within L_max of it;
- a lidar setting (L_max = 20 m, N_r = 20, N_s = 60, Scan Context's grid) around the sensor's
  ground point, where the ground seen between the cars and walls is the place's signature. Only
  this setting also separates the second pair (198/199 against 94).
"""

from __future__ import annotations

import numpy as np
import pytest
from sgf_plugins.shared.polar import polar_context, shift_to_yaw, shifted_distances, voxel_downsample

SCANS = (94, 95, 198, 199)


def ground_points(scan: np.ndarray) -> np.ndarray:
    """(N, 2) x, y of the returns within 0.15 m of the road plane (least squares, refit on its inliers)."""
    xyz = scan[:, :3].astype(np.float64)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    cand = xyz[(r > 3.0) & (r < 25.0) & (xyz[:, 2] < -1.3)]
    design = np.c_[cand[:, 0], cand[:, 1], np.ones(len(cand))]
    keep = np.ones(len(cand), bool)
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(design[keep], cand[keep, 2], rcond=None)
        keep = np.abs(cand[:, 2] - design @ coef) < 0.1
    height = xyz[:, 2] - (coef[0] * xyz[:, 0] + coef[1] * xyz[:, 1] + coef[2])
    return xyz[np.abs(height) < 0.15, :2]


@pytest.fixture(scope="module")
def ground(shared_data):
    folder = shared_data / "scancontext_kitti00" / "velodyne"
    out = {}
    for i in SCANS:
        scan = np.fromfile(folder / f"{i:06d}.bin", dtype=np.float32).reshape(-1, 4)
        assert len(scan) > 100_000
        out[i] = ground_points(scan)
    return out


def describe(points: np.ndarray, around, max_radius: float, rings: int, sectors: int, voxel: float = 0.0):
    near = points[np.hypot(*(points - np.asarray(around)).T) < max_radius]
    near = voxel_downsample(near, voxel)
    centre = near.mean(axis=0) if len(near) else np.asarray(around, dtype=np.float64)
    return polar_context(near, centre, rings, sectors, max_radius, "count"), len(near)


def distance(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    profile = shifted_distances(a, b[None])[0]
    k = int(np.argmin(profile))
    return float(profile[k]), k


def test_ground_extraction(ground):
    for points in ground.values():
        assert 40_000 < len(points) < 60_000
        r = np.hypot(points[:, 0], points[:, 1])
        assert r.min() > 2.5  # the lidar's blind circle around the car


def test_paper_setting_puts_the_neighbouring_scan_closer(ground):
    assert all(describe(g, (0.0, 0.0), 2.0, 10, 90)[1] == 0 for g in ground.values())  # blind around the sensor
    d = {}
    for i in SCANS:
        d[i], count = describe(ground[i], (6.0, 0.0), 2.0, 10, 90)
        assert count > 2000
    near_94, _ = distance(d[95], d[94])
    far_94, _ = distance(d[198], d[94])
    assert near_94 < 0.1 < 0.15 < far_94  # measured 0.076 and 0.182
    # Not asserted: 2 m of lidar ground returns mostly show the lidar's own ring pattern, and the
    # pair 198/199 is not told apart from 94 at this scale (0.214 against 0.182): see the lidar setting.


@pytest.mark.parametrize("voxel", [0.0, 0.2])
def test_lidar_setting_puts_the_neighbouring_scan_closer(ground, voxel):
    d = {i: describe(ground[i], (0.0, 0.0), 20.0, 20, 60, voxel)[0] for i in SCANS}
    near_94, shift = distance(d[95], d[94])
    far_94, _ = distance(d[198], d[94])
    near_198, _ = distance(d[199], d[198])
    far_199, _ = distance(d[199], d[94])
    # Measured without voxels 0.019 / 0.158 and 0.032 / 0.142; with 0.2 m voxels 0.049 / 0.272 and 0.084 / 0.248.
    assert near_94 < 0.5 * far_94
    assert near_198 < 0.5 * min(far_94, far_199)
    assert abs(shift_to_yaw(shift, 60)) < np.radians(12.0)  # the car drove straight on: no turn between 94 and 95
