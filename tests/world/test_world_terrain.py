import math

import numpy as np
import pytest
from sgf_plugins.world.layout import Hill, RoughPatch, SpeedBump
from sgf_plugins.world.terrain import TRACK, WHEELBASE, Terrain

from sgf_pipeline.geometry import rpy_from_rotation


def _bump(height=0.1, half_length=0.3, half_width=2.0, centre=(10.0, 0.0)) -> SpeedBump:
    return SpeedBump(np.array(centre), np.array([1.0, 0.0]), half_length, half_width, height)


def test_flat_ground_gives_the_identity_attitude():
    pose = Terrain().base_pose(3.0, -2.0, 0.7)
    assert np.allclose(pose[:3, 3], [3.0, -2.0, 0.0])
    assert np.allclose(rpy_from_rotation(pose[:3, :3]), (0.0, 0.0, 0.7))


@pytest.mark.parametrize("height", [0.05, 0.08, 0.12])
def test_front_wheels_on_a_speed_bump_pitch_the_robot_nose_up(height):
    terrain = Terrain(bumps=[_bump(height)])
    # base centre half a wheelbase behind the crest: the front wheels sit on top, the rear ones on flat ground
    pose = terrain.base_pose(10.0 - WHEELBASE / 2, 0.0, 0.0)
    roll, pitch, yaw = rpy_from_rotation(pose[:3, :3])
    assert pitch == pytest.approx(-math.atan(height / WHEELBASE), abs=1e-9)
    assert roll == pytest.approx(0.0, abs=1e-12) and yaw == pytest.approx(0.0, abs=1e-12)
    assert pose[2, 3] == pytest.approx(height / 2)
    # driving on: all four wheels straddle the crest symmetrically, the robot is level again
    level = terrain.base_pose(10.0, 0.0, 0.0)
    assert rpy_from_rotation(level[:3, :3])[1] == pytest.approx(0.0, abs=1e-12)
    # and rear wheels on the crest: nose down by the same angle
    rear = terrain.base_pose(10.0 + WHEELBASE / 2, 0.0, 0.0)
    assert rpy_from_rotation(rear[:3, :3])[1] == pytest.approx(math.atan(height / WHEELBASE), abs=1e-9)


def test_a_bump_under_the_left_wheels_rolls_the_robot_right_side_down():
    # a bump along the path direction (x), narrow, under the left wheel track (y = +TRACK / 2)
    bump = SpeedBump(np.array([0.0, TRACK / 2]), np.array([0.0, 1.0]), 0.1, 3.0, 0.06)
    roll, pitch, _ = rpy_from_rotation(Terrain(bumps=[bump]).base_pose(0.0, 0.0, 0.0)[:3, :3])
    assert roll == pytest.approx(math.atan(0.06 / TRACK), abs=1e-9)
    assert pitch == pytest.approx(0.0, abs=1e-12)


def test_on_an_even_slope_the_pitch_is_the_slope():
    # a huge hill: locally a plane rising along +x with slope dH/dx
    hill = Hill(np.array([500.0, 0.0]), 300.0, 3000.0, 0.0, 60.0)
    terrain = Terrain(hills=[hill])
    _, gx, gy = terrain.height_and_gradient(np.array([200.0]), np.array([0.0]))
    pitch = rpy_from_rotation(terrain.base_pose(200.0, 0.0, 0.0)[:3, :3])[1]
    assert gx[0] > 0.05 and abs(gy[0]) < 1e-9
    assert pitch == pytest.approx(-math.atan(gx[0]), abs=2e-4)
    # turning around on it: nose down
    pitch_back = rpy_from_rotation(terrain.base_pose(200.0, 0.0, math.pi)[:3, :3])[1]
    assert pitch_back == pytest.approx(math.atan(gx[0]), abs=2e-4)


def test_gradient_is_the_derivative_of_the_height():
    rng = np.random.default_rng(0)
    rough = RoughPatch(np.array([5.0, 5.0]), 6.0, 0.015, rng.uniform(-15, 15, (6, 2)), rng.uniform(0, 6, 6))
    terrain = Terrain(
        hills=[Hill(np.array([0.0, 0.0]), 30.0, 20.0, 0.4, 3.0)], bumps=[_bump(0.08, centre=(4.0, 4.0))], rough=[rough]
    )
    x = rng.uniform(0.0, 10.0, 400)
    y = rng.uniform(0.0, 10.0, 400)
    h, gx, gy = terrain.height_and_gradient(x, y)
    e = 1e-6
    fx = (terrain.height(x + e, y) - terrain.height(x - e, y)) / (2 * e)
    fy = (terrain.height(x, y + e) - terrain.height(x, y - e)) / (2 * e)
    assert np.abs(fx - gx).max() < 1e-5 and np.abs(fy - gy).max() < 1e-5
    assert h.std() > 0.05


def test_campus_paths_stay_under_ten_percent_slope(delivery):
    for e in delivery.layout.edges:
        pts = np.array([e.at(s)[0] for s in np.linspace(0.0, e.length, 60)])
        assert delivery.terrain.max_slope(pts) <= 0.10 + 1e-9, (e.a, e.b)
    steepest = max(
        delivery.terrain.max_slope(np.array([e.at(s)[0] for s in np.linspace(0, e.length, 60)]))
        for e in delivery.layout.edges
    )
    assert steepest > 0.06  # there are real slopes to climb


def test_campus_bumps_are_five_to_twelve_centimetres(delivery):
    heights = [b.height for b in delivery.layout.bumps]
    assert heights and min(heights) >= 0.05 and max(heights) <= 0.12


def _values(items) -> list:
    return [tuple(np.asarray(v).round(9).tolist() for v in vars(item).values()) for item in items]


def test_more_rough_paving_leaves_the_rest_of_the_campus_as_it_is():
    from sgf_plugins.world.world import build_world

    plain = build_world("campus_reverse_slope", seed=0, scale=0.3)
    rough = build_world("campus_reverse_slope", seed=0, scale=0.3, rough_paving_per_km=50.0)
    own = len(plain.layout.rough)
    assert _values(rough.layout.rough[:own]) == _values(plain.layout.rough)  # the campus's own, then the added
    added = rough.layout.rough[own:]
    long_paths = [e for e in rough.layout.edges if e.length > 20.0]
    assert len(added) == sum(max(1, round(e.length * 50.0 / 1000.0)) for e in long_paths)
    assert all(0.008 <= p.amplitude <= 0.018 and 5.0 <= p.radius <= 12.0 for p in added)
    assert [(m.instance_id, m.design.name) for m in rough.layout.markings] == [
        (m.instance_id, m.design.name) for m in plain.layout.markings
    ]
    assert _values(rough.layout.bumps) == _values(plain.layout.bumps)
    # the robot pitches more from frame to frame on the rougher paving, over the same route
    pitch = [np.diff([rpy_from_rotation(p[:3, :3])[1] for p in w.drive.poses]) for w in (plain, rough)]
    assert len(pitch[0]) == len(pitch[1])
    shaken = [float(np.mean(np.abs(d) > math.radians(0.3))) for d in pitch]  # 0.039 and 0.244 measured
    assert shaken[0] < 0.06 and shaken[1] > 0.2, shaken
