import math

import numpy as np
import pytest
from sgf_plugins.world import build_world
from sgf_plugins.world.truth import marking_points, wholly_visible

from sgf_pipeline.evaluation import ate_rmse
from sgf_pipeline.geometry import rpy_from_rotation, wrap_angle
from sgf_pipeline.trajectory import Trajectory


def test_the_robot_drives_at_campus_speed_on_a_ten_hertz_clock(delivery):
    drive = delivery.drive
    assert np.allclose(np.diff(drive.timestamps), 0.1)
    step = np.linalg.norm(np.diff(drive.xy, axis=0), axis=1) / 0.1
    cruising = drive.speed[:-1] >= 0.999  # not starting, stopping or standing
    assert cruising.mean() > 0.9
    assert step[cruising].min() > 0.97 and step.max() < 1.53
    assert drive.speed.max() <= 1.5
    assert 1.0 <= np.median(step[step > 0.5]) <= 1.5 and np.percentile(step, 95) > 1.2
    # the drop-off stop: the robot stands still for six seconds
    assert (step < 1e-9).sum() >= 59
    assert 180.0 < drive.length < 400.0


def test_ground_truth_poses_stand_on_the_terrain(delivery):
    poses = delivery.drive.poses
    z = delivery.terrain.height(poses[:, 0, 3], poses[:, 1, 3])
    gap = np.abs(poses[:, 2, 3] - z)  # the base plane of the four wheel contacts, over bumps and dips
    assert gap.max() < 0.125 and np.median(gap) < 0.002
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    pitch = np.array([rpy_from_rotation(r)[1] for r in rot])
    assert np.abs(pitch).max() > math.atan(0.05 / 0.5) - 1e-3  # it crossed a speed bump


def test_odometry_starts_at_the_true_pose_and_drifts(delivery):
    odo, gt = delivery.sensors.odometry, delivery.drive.poses
    assert np.array_equal(odo[0], gt[0])
    err = np.linalg.norm(odo[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert err[10] < 0.05 and err[-1] > 1.0
    imu = delivery.sensors.imu_roll_pitch
    true_rp = np.array([rpy_from_rotation(p[:3, :3])[:2] for p in gt])
    diff = np.degrees(imu - true_rp)
    assert 0.05 < np.abs(diff).mean() < 1.0 and np.abs(diff).max() < 1.5


def test_another_odometry_seed_is_a_second_session_of_the_same_world(delivery):
    # the same drive, markings and camera images; only the wheel odometry's and the IMU's noise differ
    second = build_world("campus_delivery", seed=0, odometry_seed=1)
    assert np.array_equal(second.drive.poses, delivery.drive.poses)
    assert [(m.x, m.y, m.yaw) for m in second.layout.markings] == [(m.x, m.y, m.yaw) for m in delivery.layout.markings]
    assert np.array_equal(second.frame(100).image, delivery.frame(100).image)
    odo, first = second.sensors.odometry, delivery.sensors.odometry
    assert np.array_equal(odo[0], first[0])  # both start at the true start pose
    apart = np.linalg.norm(odo[:, :3, 3] - first[:, :3, 3], axis=1)
    assert apart[-1] > 0.5  # drifted another way
    assert not np.allclose(second.sensors.imu_roll_pitch, delivery.sensors.imu_roll_pitch)
    # the world's own seed gives the default's odometry (null stands for it)
    same = build_world("campus_delivery", seed=0, odometry_seed=0)
    assert np.array_equal(same.sensors.odometry, first)


def test_large_loop_odometry_error_is_in_the_papers_range():
    world = build_world("campus_large_loop", seed=0)
    drive = world.drive
    gt = Trajectory(drive.timestamps, drive.poses)
    odo = Trajectory(drive.timestamps, world.sensors.odometry)
    assert 2500.0 < drive.length < 2900.0
    assert 100.0 < ate_rmse(gt, odo) < 300.0


def test_passes_are_the_frames_with_the_marking_wholly_in_view(delivery):
    truth = delivery.truth
    grid = delivery.grid
    poses = delivery.drive.poses
    for p in truth.passes[:8]:
        m = next(m for m in delivery.layout.markings if m.instance_id == p.instance_id)
        pts = marking_points(m, delivery.terrain)
        inside = wholly_visible(pts, poses[p.start_frame : p.end_frame + 1], delivery.calibration, grid)
        assert inside[0] and inside[-1]
        before = wholly_visible(pts, poses[p.start_frame - 1 : p.start_frame], delivery.calibration, grid)
        after = wholly_visible(pts, poses[p.end_frame + 1 : p.end_frame + 2], delivery.calibration, grid)
        assert not before[0] and not after[0]
        # every outline point of the marking is in the BEV box and in the image in mid-pass
        mid = poses[(p.start_frame + p.end_frame) // 2]
        local = (pts - mid[:3, 3]) @ mid[:3, :3]
        assert (local[:, 0] >= grid.x_min).all() and (local[:, 0] <= grid.x_max).all()
        assert (local[:, 1] >= grid.y_min).all() and (local[:, 1] <= grid.y_max).all()
        heading = math.atan2(mid[1, 0], mid[0, 0])
        assert abs(wrap_angle(p.heading - heading)) < 0.5


def test_the_marking_of_a_pass_shows_in_the_id_image(delivery):
    truth = delivery.truth
    for p in truth.passes[:5]:
        k = (p.start_frame + p.end_frame) // 2
        ids = delivery.render_layers(delivery.drive.poses[k], delivery.conditions(occluders=False)).ids
        assert (ids == p.instance_id).sum() > 150


def test_revisit_pairs_are_consecutive_passes_with_their_direction(delivery):
    truth = delivery.truth
    by_instance = {}
    for p in truth.passes:
        by_instance.setdefault(p.instance_id, []).append(p)
    expected = sum(len(v) - 1 for v in by_instance.values())
    assert len(truth.revisits) == expected
    for r in truth.revisits:
        assert r.second.number == r.first.number + 1 and r.second.start_frame > r.first.end_frame
        assert r.reverse == (abs(wrap_angle(r.second.heading - r.first.heading)) > math.pi / 2)
    assert truth.on_path <= set(truth.markings)


@pytest.mark.parametrize(
    ("preset", "markings", "pairs", "reverse"),
    [
        ("campus_delivery", (15, 32), (1, 4), (1, 4)),
        ("campus_reverse_slope", (35, 60), (12, 32), None),
        ("campus_large_loop", (85, 120), (28, 50), (1, 6)),
    ],
)
def test_preset_loop_statistics_mirror_table_3(preset, markings, pairs, reverse):
    truth = build_world(preset, seed=0).truth
    rev = sum(r.reverse for r in truth.revisits)
    assert markings[0] <= len(truth.on_path) <= markings[1]
    assert pairs[0] <= len(truth.revisits) <= pairs[1]
    if reverse is None:  # reverse + slope: every revisit is a reverse one
        assert rev == len(truth.revisits)
    else:
        assert reverse[0] <= rev <= reverse[1]
    standard = sum(truth.markings[i].category == "standard" for i in truth.on_path)
    assert 0 < standard < len(truth.on_path)  # both kinds on the path


def test_standard_markings_repeat_along_the_route():
    truth = build_world("campus_large_loop", seed=0).truth
    designs = [truth.markings[i].design for i in truth.on_path if truth.markings[i].category == "standard"]
    counts = {d: designs.count(d) for d in set(designs)}
    assert max(counts.values()) >= 4  # the same arrow or word at several places (perceptual aliasing)


def test_scale_shrinks_the_route_but_keeps_its_revisits():
    full = build_world("campus_delivery", seed=0)
    half = build_world("campus_delivery", seed=0, scale=0.5)
    ratio = half.drive.length / full.drive.length
    assert 0.4 < ratio < 0.65
    assert half.drive.xy[0] == pytest.approx(half.drive.xy[-1], abs=0.5)  # still back home
    small = build_world("campus_reverse_slope", seed=0, scale=0.3)
    assert small.truth.revisits and all(r.reverse for r in small.truth.revisits)


def test_held_out_designs_are_left_out_or_alone():
    held = build_world("campus_delivery", seed=0, only_designs=["painted_shape", "delivery"])
    assert {m.design.family for m in held.layout.markings} <= {"painted_shape", "delivery"}
    rest = build_world("campus_delivery", seed=0, exclude_designs=["painted_shape", "delivery"])
    assert not {m.design.family for m in rest.layout.markings} & {"painted_shape", "delivery"}
    assert len(held.layout.markings) > 20 and len(rest.layout.markings) > 100
