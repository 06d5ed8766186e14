"""Lifting SGF pixels onto the driven ground (``descriptor.ground=driven``): rays, ramps, fallback, the stage."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sgf_plugins.sgf.descriptor import PolarContext, PolarContextParams, lift, lift_driven
from sgf_plugins.sgf.terrain import driven_ground, intersect_ground, march_ground, pixel_rays, wheel_ground
from sgf_plugins.shared.bev_homography import bev_to_image_homography
from sgf_plugins.world.layout import SpeedBump
from sgf_plugins.world.terrain import Terrain
from sgf_synthetic import DEFAULT_GRID, toy_calibration

from sgf_pipeline import RunContext
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.imu import steadied_roll_pitch
from sgf_pipeline.types import Frame, SalientGroundFeature, SgfDetections

CALIBRATION = toy_calibration()  # 0.5 m high, 30 degrees down
HOMOGRAPHY = bev_to_image_homography(CALIBRATION, DEFAULT_GRID)  # plain IPM


def patch(x0: float, x1: float, y0: float = -0.3, y1: float = 0.3) -> np.ndarray:
    """BEV pixels (u, v) of a ground rectangle [x0, x1] x [y0, y1] on the BEV's plane."""
    u, v = np.meshgrid(np.arange(DEFAULT_GRID.width), np.arange(DEFAULT_GRID.height))
    x, y = DEFAULT_GRID.pixel_to_ground(u.ravel(), v.ravel())
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return np.stack([u.ravel()[inside], v.ravel()[inside]], axis=1)


def sgf(pixels: np.ndarray, frame: int = 0, homography: np.ndarray | None = HOMOGRAPHY) -> SalientGroundFeature:
    return SalientGroundFeature(
        frame, frame, 0.1 * frame, np.eye(4), pixels, DEFAULT_GRID, 1.0, np.zeros(7), 3, homography=homography
    )


def pitched(x: float, z: float, grade: float) -> np.ndarray:
    """A base pose at (x, 0, z) heading +x, nose up by ``grade`` (rad): on a ramp of that grade."""
    c, s = math.cos(grade), math.sin(grade)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]
    pose[:3, 3] = (x, 0.0, z)
    return pose


def ramp(start: float, grade: float, length: float = 6.0, step: float = 0.25) -> np.ndarray:
    """Base poses every ``step`` m of path: flat ground, then a ramp of ``grade`` from ``start`` m on."""
    poses = []
    for s in np.arange(0.0, length + 1e-9, step):
        if s <= start:
            poses.append(pitched(s, 0.0, 0.0))
        else:
            poses.append(pitched(start + (s - start) * math.cos(grade), (s - start) * math.sin(grade), grade))
    return np.array(poses)


def ray_meets_ramp(x_flat: float, start: float, grade: float) -> float:
    """Where the ray to ``x_flat`` on the flat plane (the plane IPM assumes) meets a ramp starting at ``start``."""
    cam = CALIBRATION.camera_to_base_matrix[:3, 3]
    xc, h = float(cam[0]), float(cam[2])
    t = math.tan(grade)
    # ray height h (1 - (x - xc) / (x_flat - xc)) equals the ramp's (x - start) t
    return (h + h * xc / (x_flat - xc) + start * t) / (t + h / (x_flat - xc))


def test_on_flat_ground_the_driven_lift_is_eq_9():
    pixels = patch(2.0, 4.5, -1.0, 1.0)
    flat = np.array([pose_from_xy_yaw(0.25 * k, 0.02 * k, 0.01 * k) for k in range(20)])
    driven = lift_driven(sgf(pixels), CALIBRATION, flat, ahead=3.0, radius=1.5)
    assert driven is not None
    assert np.abs(driven - lift(sgf(pixels))).max() < 1e-9


def test_a_ramp_ahead_pulls_the_far_paint_in_as_the_ray_geometry_says():
    grade = math.radians(3.0)
    pixels = patch(4.0, 4.6)
    on_plane = lift(sgf(pixels))
    driven = lift_driven(sgf(pixels), CALIBRATION, ramp(2.0, grade), ahead=3.0, radius=1.5)
    assert driven is not None
    for x_flat in (4.01, 4.59):  # the patch's nearest and farthest pixel centres
        rows = np.isclose(on_plane[:, 0], x_flat)
        expected = ray_meets_ramp(x_flat, 2.0, grade)
        assert driven[rows, 0] == pytest.approx(expected, abs=0.01)  # horizontal distance on the base frame
    # The plane puts the paint half a metre too far: the error a reverse loop doubles.
    assert on_plane[:, 0].mean() - driven[:, 0].mean() > 0.45
    # Lateral positions scale with the distance along the ray.
    assert np.ptp(driven[:, 1]) < np.ptp(on_plane[:, 1]) * 0.9


def test_the_ramp_is_extrapolated_from_the_newest_pose_when_the_robot_has_not_reached_the_paint():
    grade = math.radians(3.0)
    pixels = patch(4.0, 4.6)
    full = lift_driven(sgf(pixels), CALIBRATION, ramp(2.0, grade), ahead=3.0, radius=1.5)
    short = lift_driven(sgf(pixels), CALIBRATION, ramp(2.0, grade, length=3.0), ahead=3.0, radius=1.5)
    assert full is not None and short is not None
    assert np.abs(short - full).max() < 0.005
    # Without the extension the far paint has no ground sample within 0.5 m: it stays on the plane.
    assert lift_driven(sgf(pixels), CALIBRATION, ramp(2.0, grade, length=3.0), ahead=0.0, radius=0.5) is None


def test_paint_the_robot_turned_away_from_stays_on_the_plane():
    pixels = patch(4.0, 4.6)
    away = np.array([pose_from_xy_yaw(0.0, -0.25 * k, -math.pi / 2) for k in range(20)])  # drives off to the right
    away[0] = np.eye(4)
    assert lift_driven(sgf(pixels), CALIBRATION, away, ahead=0.0, radius=1.0) is None
    assert lift_driven(sgf(pixels, homography=None), CALIBRATION, ramp(2.0, 0.05), ahead=3.0, radius=1.5) is None


def test_rays_that_never_reach_the_ground_are_not_covered():
    origin = np.array([0.0, 0.0, 0.5])
    directions = np.array([[1.0, 0.0, -0.1], [1.0, 0.0, 0.1]])  # down to the ground; up into the sky
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points, normals = driven_ground(np.array([np.eye(4)]), ahead=10.0, step=0.25)
    hit, covered = intersect_ground(origin, directions, points, normals, radius=1.0)
    assert covered.tolist() == [True, False]
    assert hit[0] == pytest.approx([5.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        driven_ground(np.eye(4), ahead=1.0, step=0.25)


def test_pixel_rays_pass_through_the_plane_point_of_each_pixel():
    pixels = patch(1.0, 5.0, -2.0, 2.0)
    origin, directions = pixel_rays(pixels, HOMOGRAPHY, CALIBRATION)
    assert origin == pytest.approx(CALIBRATION.camera_to_base_matrix[:3, 3])
    t = -origin[2] / directions[:, 2]
    ground = origin + t[:, None] * directions
    assert np.abs(ground[:, :2] - lift(sgf(pixels))).max() < 1e-9


def test_the_stage_lifts_on_the_driven_ground_and_counts_the_fallbacks():
    grade = math.radians(3.0)
    poses = ramp(2.0, grade)
    feature = sgf(patch(4.0, 4.6), frame=0)
    off_path = sgf(patch(4.0, 4.6, 2.0, 2.5), frame=0)  # 2 m beside the path
    stage = PolarContext(PolarContextParams(ground="driven", ground_radius=1.5))
    context = RunContext(None)
    stage.begin(context)
    out = None
    for k, pose in enumerate(poses[:12]):
        items = (feature, off_path) if k == 11 else ()
        out = stage.process(Frame(k, 0.1 * k, np.zeros((2, 2), np.uint8), pose, CALIBRATION), SgfDetections(items))
    assert out is not None and len(out.items) == 2
    on_ramp, beside = out.items
    expected = np.mean([ray_meets_ramp(x, 2.0, grade) for x in (4.01, 4.59)])
    assert on_ramp.centroid[0] == pytest.approx(expected, abs=0.02)
    assert beside.centroid[0] == pytest.approx(4.3, abs=0.02)  # uncovered: eq. 9 on the plane
    stage.finalize(context)
    assert context.metrics["sgf"]["lifted_on_driven_ground"] == 1
    assert context.metrics["sgf"]["lifted_on_plane"] == 1


def test_planar_odometry_with_a_tilted_imu_is_warned_about_once(caplog):
    stage = PolarContext(PolarContextParams(ground="driven"))
    stage.begin(RunContext(None))
    with caplog.at_level("WARNING", logger="sgf_pipeline.sgf"):
        for k in range(3):  # on a 5 % slope by the IMU, level by the odometry
            frame = Frame(
                k, 0.1 * k, np.zeros((2, 2), np.uint8), pose_from_xy_yaw(0.25 * k, 0.0, 0.0), CALIBRATION, (0.0, 0.05)
            )
            stage.process(frame, SgfDetections())
    warnings = [r for r in caplog.records if "descriptor.ground=plane" in r.getMessage()]
    assert len(warnings) == 1 and "pitch 0.050" in warnings[0].getMessage()
    caplog.clear()
    stage.begin(RunContext(None))
    with caplog.at_level("WARNING", logger="sgf_pipeline.sgf"):  # 3-D odometry that carries the IMU's attitude
        stage.process(
            Frame(0, 0.0, np.zeros((2, 2), np.uint8), pitched(0.0, 0.0, 0.05), CALIBRATION, (0.0, 0.05)),
            SgfDetections(),
        )
    assert not caplog.records


def bump_paint(terrain: Terrain, x0: float, x1: float) -> tuple[np.ndarray, np.ndarray]:
    """BEV pixels whose camera rays (from the base at the origin) first meet the ground in [x0, x1] x [-0.3, 0.3].

    Returns the pixels and where the rays meet the true ground (a 2 mm march against its height).
    """
    pixels = patch(x0 - 1.0, DEFAULT_GRID.x_max)
    origin, directions = pixel_rays(pixels, HOMOGRAPHY, CALIBRATION)
    across = np.hypot(directions[:, 0], directions[:, 1])
    s = np.arange(1.0, 8.0, 0.002)
    ray = origin + (s[None, :] / across[:, None])[..., None] * directions[:, None, :]
    ground = terrain.height_and_gradient(ray[..., 0], ray[..., 1], gradient=False)[0]
    k = np.argmax(ray[..., 2] <= ground, axis=1)
    truth = ray[np.arange(len(ray)), k]
    paint = (truth[:, 0] >= x0) & (truth[:, 0] <= x1) & (np.abs(truth[:, 1]) <= 0.3)
    return pixels[paint], truth[paint]


def test_paint_on_a_speed_bump_lands_where_the_wheels_measured_the_ground():
    # A 10 cm, 60 cm long cos^2 bump 4 m ahead, and the robot's base poses on its four wheels as it drives over it.
    terrain = Terrain(bumps=[SpeedBump(np.array([4.0, 0.0]), np.array([1.0, 0.0]), 0.3, 1.5, 0.1)])
    x = np.arange(0.0, 6.01, 0.1)
    poses = terrain.base_poses(x, np.zeros_like(x), np.zeros_like(x))
    pixels, truth = bump_paint(terrain, 3.7, 4.3)
    assert len(pixels) > 1000 and truth[:, 0].max() > 4.0  # the near slope and the crest are in view
    origin, directions = pixel_rays(pixels, HOMOGRAPHY, CALIBRATION)

    points, normals = wheel_ground(poses, ahead=3.0, step=0.25, contacts=(0.25, -0.25))
    wheels, covered = march_ground(origin, directions, points, normals, radius=1.5)
    assert covered.all()
    kept = np.isfinite(wheels[:, 0])
    # The wheels lie on the bump; the base origin, their average, passes under its crest.
    error = np.abs(wheels[kept, 0] - truth[kept, 0])
    assert np.median(error) < 0.005 and error.max() < 0.03
    base = lift_driven(sgf(pixels), CALIBRATION, poses, ahead=3.0, radius=1.5)  # ground_model=base
    assert base is not None and np.median(np.abs(base[:, 0] - truth[:, 0])) > 0.15
    assert np.median(np.abs(lift(sgf(pixels))[:, 0] - truth[:, 0])) > 0.3  # eq. 9 on the plane
    # Rays that skimmed the crest (the far slope hides behind it) are left out: a few, the misplaced ones.
    assert 0.95 < kept.mean() < 1.0
    driven = lift_driven(sgf(pixels), CALIBRATION, poses, ahead=3.0, radius=1.5, contacts=(0.25, -0.25))
    assert driven is not None and len(driven) == kept.sum()


def test_an_sgf_waits_until_the_robot_has_driven_past_its_paint():
    poses = [pose_from_xy_yaw(0.1 * k, 0.0, 0.0) for k in range(60)]
    feature = sgf(patch(4.0, 4.6), frame=2)  # seen at frame 2 (x = 0.2 m), selected at frame 5
    stage = PolarContext(PolarContextParams(ground="driven", ground_model="wheels", ground_past=0.5))
    stage.begin(RunContext(None))
    emitted = []
    for k, pose in enumerate(poses):
        out = stage.process(
            Frame(k, 0.1 * k, np.zeros((2, 2), np.uint8), pose, CALIBRATION),
            SgfDetections((feature,) if k == 5 else ()),
        )
        emitted += [k] * len(out.items)
    # Farthest pixel 4.6 m ahead of the view, plus 0.5 m: due at 0.2 + 5.1 = 5.3 m of travel.
    assert emitted == [53]
    context = RunContext(None)
    stage.begin(context)
    for k, pose in enumerate(poses[:30]):  # the run ends before the robot gets there
        stage.process(
            Frame(k, 0.1 * k, np.zeros((2, 2), np.uint8), pose, CALIBRATION),
            SgfDetections((feature,) if k == 5 else ()),
        )
    stage.finalize(context)
    assert context.metrics["sgf"]["waiting_for_ground_at_end"] == 1


def test_the_wheels_model_is_eq_9_on_flat_ground_and_follows_a_ramp():
    flat = np.array([pose_from_xy_yaw(0.25 * k, 0.02 * k, 0.01 * k) for k in range(20)])
    pixels = patch(2.0, 4.5, -1.0, 1.0)
    driven = lift_driven(sgf(pixels), CALIBRATION, flat, ahead=3.0, radius=1.5, contacts=(0.25, -0.25))
    assert driven is not None and len(driven) == len(pixels)
    assert np.abs(driven - lift(sgf(pixels))).max() < 1e-6
    grade = math.radians(3.0)
    pixels = patch(4.0, 4.6)
    on_ramp = lift_driven(sgf(pixels), CALIBRATION, ramp(2.0, grade), ahead=3.0, radius=1.5, contacts=(0.25, -0.25))
    assert on_ramp is not None
    on_plane = lift(sgf(pixels))
    for x_flat in (4.01, 4.59):
        rows = np.isclose(on_plane[:, 0], x_flat)
        assert on_ramp[rows, 0] == pytest.approx(ray_meets_ramp(x_flat, 2.0, grade), abs=0.01)


def test_marched_rays_that_never_reach_the_ground_are_not_covered():
    origin = np.array([0.0, 0.0, 0.5])
    directions = np.array([[1.0, 0.0, -0.1], [1.0, 0.0, 0.1]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points, normals = wheel_ground(np.array([np.eye(4)]), ahead=10.0, step=0.25, contacts=(0.25,))
    hit, covered = march_ground(origin, directions, points, normals, radius=1.0)
    assert covered.tolist() == [True, False]
    assert hit[0] == pytest.approx([5.0, 0.0, 0.0], abs=1e-9)
    with pytest.raises(ValueError, match="contacts"):
        wheel_ground(np.array([np.eye(4)]), ahead=1.0, step=0.25, contacts=())


def test_steadied_roll_pitch_drops_the_imu_noise_and_keeps_a_bump():
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 0.0026, (11, 2))  # the world's IMU: 0.15 degrees, on level ground
    noise[5] = (0.004, -0.0045)  # the frame's own reading: a large draw
    level = np.array(steadied_roll_pitch(noise, 5, 0.005))
    d = noise[5] - np.median(noise, axis=0)
    np.testing.assert_allclose(level, np.median(noise, axis=0) + d**3 / (d**2 + 0.005**2), atol=1e-12)
    assert np.all(np.abs(level) < 0.5 * np.abs(noise[5]))
    bump = noise.copy()
    bump[4:7, 1] += 0.06  # three frames on a speed bump's ramp: a real pitch, not noise
    _, pitch = steadied_roll_pitch(bump, 5, 0.005)
    assert pitch == pytest.approx(bump[5, 1], abs=0.002)
    assert steadied_roll_pitch(bump, 5, 0.0) == pytest.approx(tuple(bump[5]))  # no noise scale: the frame's own


def _lift_with_a_tilted_view(error: float, window: float) -> np.ndarray:
    """The stage's points of paint 4 to 4.6 m ahead on level ground, the view's odometry pitched by ``error``."""
    stage = PolarContext(PolarContextParams(ground="driven", attitude_window=window))
    stage.begin(RunContext(None))
    feature = sgf(patch(4.0, 4.6), frame=5)
    out = None
    for k in range(30):
        pose = pitched(0.1 * k, 0.0, error if k == 5 else 0.0)
        items = (feature,) if k == 29 else ()
        out = stage.process(Frame(k, 0.1 * k, np.zeros((2, 2), np.uint8), pose, CALIBRATION), SgfDetections(items))
    assert out is not None and len(out.items) == 1
    return np.asarray(out.items[0].points)


def test_the_view_s_imu_noise_no_longer_tilts_the_ground_under_far_paint():
    truth = _lift_with_a_tilted_view(0.0, 0.6)  # level ground, level odometry: eq. 9
    np.testing.assert_allclose(truth, _lift_with_a_tilted_view(0.0, 0.0), atol=1e-9)
    error = math.radians(0.25)  # a noisy IMU reading at the view only
    own = _lift_with_a_tilted_view(error, 0.0)
    steadied = _lift_with_a_tilted_view(error, 0.6)
    length = float(np.ptp(truth[:, 0]))
    # The view's own reading tilts the whole driven ground under the camera: paint 4.3 m ahead by 0.6 m high
    # moves by about d^2 / h * error and stretches by 2 d / h * error (about 6 %).
    shift = abs(own[:, 0].mean() - truth[:, 0].mean())
    assert shift == pytest.approx(4.3**2 / 0.5 * error, rel=0.35)
    assert np.ptp(own[:, 0]) / length - 1.0 == pytest.approx(2 * 4.3 / 0.5 * error, abs=0.02)
    # Steadied over 0.6 m either side (the median: level), the reading counts d^3 / (d^2 + sigma^2): with
    # sigma 0.005 rad, 43 % of a 0.25 degree error is left (21 % of a one-sigma reading of the world's IMU).
    kept = error**2 / (error**2 + 0.005**2)
    assert abs(steadied[:, 0].mean() - truth[:, 0].mean()) / shift == pytest.approx(kept, rel=0.1)
    stretch_own, stretch = np.ptp(own[:, 0]) / length - 1.0, np.ptp(steadied[:, 0]) / length - 1.0
    assert stretch / stretch_own == pytest.approx(kept, rel=0.15)
