"""Robots and grounds other than the campus robot's: a heading bias of either sign, and ground clutter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sgf_plugins.world import build_world
from sgf_plugins.world.drive import OdometryModel, simulate_sensors
from sgf_plugins.world.texture import TileGenerator

from sgf_pipeline.geometry import rpy_from_rotation

QUIET = {
    "odometry_yaw_random_walk_deg_per_m": 0.0,
    "odometry_yaw_noise_deg": 0.0,
    "odometry_distance_noise": 0.0,
}


def _heading_error_deg(world) -> float:  # type: ignore[no-untyped-def]
    """The odometry's heading less the truth's at the end of the drive (deg, unwrapped along it)."""
    odo = np.unwrap([rpy_from_rotation(p[:3, :3])[2] for p in world.sensors.odometry])
    gt = np.unwrap([rpy_from_rotation(p[:3, :3])[2] for p in world.drive.poses])
    return float(np.degrees(odo[-1] - gt[-1]))


@pytest.mark.parametrize("bias", [0.2, -0.2])
def test_a_heading_bias_of_either_sign_turns_the_odometry_that_way(bias: float) -> None:
    world = build_world(
        "campus_delivery",
        seed=4,
        scale=0.2,
        odometry_yaw_bias_deg_per_m=bias,
        odometry_yaw_bias_seeded_sign=False,
        **QUIET,
    )
    length = world.drive.length
    # with no random walk and no per-frame noise, the heading is off by the bias times the distance driven
    assert _heading_error_deg(world) == pytest.approx(bias * length, rel=1e-6)


def test_by_default_the_seed_picks_the_sign_and_the_rest_of_the_noise_stays_the_seeds() -> None:
    signs = set()
    for seed in range(6):
        seeded = build_world("campus_delivery", seed=seed, scale=0.2, **QUIET)
        error = _heading_error_deg(seeded) / (0.07 * seeded.drive.length)
        assert error == pytest.approx(1.0, rel=1e-6) or error == pytest.approx(-1.0, rel=1e-6)
        signs.add(round(error))
    assert signs == {-1, 1}  # both ways among six seeds (each way with probability 1/2)
    # the sign's draw is made either way: the IMU's noise (drawn after it) is the same with the sign given
    drive = build_world("campus_delivery", seed=0, scale=0.2).drive
    seeded_log = simulate_sensors(drive, OdometryModel(), seed=0)
    given_log = simulate_sensors(drive, OdometryModel(seeded_sign=False), seed=0)
    np.testing.assert_array_equal(seeded_log.imu_roll_pitch, given_log.imu_roll_pitch)


def test_negative_and_out_of_range_biases_are_checked() -> None:
    build_world("campus_delivery", seed=0, scale=0.2, odometry_yaw_bias_deg_per_m=-0.3)
    with pytest.raises(ValueError, match="odometry_yaw_bias_deg_per_m"):
        build_world("campus_delivery", seed=0, scale=0.2, odometry_yaw_bias_deg_per_m=-20.0)
    with pytest.raises(ValueError, match="clutter"):
        build_world("campus_delivery", seed=0, scale=0.2, clutter=-1.0)


def _cells(world, clutter: float):  # type: ignore[no-untyped-def]
    generator = TileGenerator(world.layout, world.sun, world.seed, clutter)
    return [generator.ground_clutter.cell_features(i, j) for i in range(-10, 10) for j in range(-10, 10)]


def test_clutter_scales_the_campus_wear_and_strews_leaves_and_post_shadows() -> None:
    world = build_world("campus_delivery", seed=0, scale=0.2)
    own, same, triple = _cells(world, 1.0), _cells(world, 1.0), _cells(world, 3.0)
    n = len(own)
    count = {
        name: [sum(len(getattr(c, name)) for c in cells) for cells in (own, triple)] for name in ("cracks", "stains")
    }
    # Poisson counts over 400 cells: 2.0 and 0.8 cracks and stains per cell, three times that with clutter 3
    for name, rate in (("cracks", 2.0), ("stains", 0.8)):
        for total, factor in zip(count[name], (1.0, 3.0), strict=True):
            expected = rate * factor * n
            assert abs(total - expected) < 5.0 * math.sqrt(expected), (name, factor, total)
    # the campus's own clutter is drawn the same way at clutter 1: no leaves, no posts
    assert all(
        len(a.cracks) == len(b.cracks) and len(a.stains) == len(b.stains) for a, b in zip(own, same, strict=True)
    )
    assert not any(c.leaves or c.posts for c in own)
    leaves = sum(len(c.leaves) for c in triple)
    posts = sum(len(c.posts) for c in triple)
    assert 8 * 2.0 * n * 0.5 < leaves < 25 * 2.0 * n * 1.5  # drifts of 8-25 leaves, 2 drifts per cell
    assert abs(posts - 1.0 * n) < 5.0 * math.sqrt(n)


def test_clutter_changes_the_image_but_not_the_markings() -> None:
    plain = build_world("campus_delivery", seed=0, scale=0.2)
    cluttered = build_world("campus_delivery", seed=0, scale=0.2, clutter=4.0)
    pose = plain.drive.poses[90]
    x, y = pose[0, 3], pose[1, 3]
    rgba, ids = plain.renderer.generator.region(x - 6.0, y + 6.0, 600, 600, 0.02)
    rgba_c, ids_c = cluttered.renderer.generator.region(x - 6.0, y + 6.0, 600, 600, 0.02)
    np.testing.assert_array_equal(ids, ids_c)  # the marking masks (saliency's truth) are the same
    changed = np.abs(rgba.astype(np.int16) - rgba_c.astype(np.int16)).max(axis=2) > 20
    assert 0.001 < changed.mean() < 0.2  # leaves, post shadows, more cracks and stains: a small part of the ground
    assert plain.truth.markings == cluttered.truth.markings
