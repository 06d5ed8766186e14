import math

import numpy as np
import pytest
from sgf_plugins.world import build_world
from world_helpers import exact_ground, project

from sgf_pipeline.geometry import rpy_from_rotation


def _bilinear(field: np.ndarray, u: float, v: float) -> np.ndarray:
    u0, v0 = math.floor(u), math.floor(v)
    fu, fv = u - u0, v - v0
    a, b = field[v0, u0], field[v0, u0 + 1]
    c, d = field[v0 + 1, u0], field[v0 + 1, u0 + 1]
    return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv


def _pixel_showing(ground_xy: np.ndarray, target: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The (sub)pixel at which the rendered image shows the ground point ``target`` (Newton on the pixel map)."""
    uv = start.astype(np.float64).copy()
    for _ in range(20):
        g = _bilinear(ground_xy, *uv)
        e = 0.25
        jac = np.column_stack(
            [
                (_bilinear(ground_xy, uv[0] + e, uv[1]) - _bilinear(ground_xy, uv[0] - e, uv[1])) / (2 * e),
                (_bilinear(ground_xy, uv[0], uv[1] + e) - _bilinear(ground_xy, uv[0], uv[1] - e)) / (2 * e),
            ]
        )
        step = np.linalg.solve(jac, target - g)
        uv += step
        if np.abs(step).max() < 1e-4:
            break
    return uv


def _frames_to_check(world):
    """A frame on a slope with a marking in view, one with a speed bump ahead, one pitched on a bump."""
    poses = world.drive.poses
    pitch = np.array([rpy_from_rotation(p[:3, :3])[1] for p in poses])
    on_bump = int(np.argmax(np.abs(pitch)))
    ahead = on_bump - 25
    truth = world.truth
    sloped = max(truth.passes, key=lambda p: abs(pitch[(p.start_frame + p.end_frame) // 2]))
    return [(sloped.start_frame + sloped.end_frame) // 2, ahead, on_bump]


def test_marking_corners_land_at_their_projected_pixels(delivery):
    checked = 0
    passes = delivery.truth.passes[:4]
    for k in _frames_to_check(delivery) + [(p.start_frame + p.end_frame) // 2 for p in passes]:
        pose = delivery.drive.poses[k]
        layers = delivery.render_layers(pose, delivery.conditions(occluders=False, sensor_noise=False))
        ground = layers.ground_xy()
        for m in delivery.layout.markings:
            corners = m.footprint()
            pts = np.column_stack([corners, delivery.terrain.height(corners[:, 0], corners[:, 1])])
            local = (pts - pose[:3, 3]) @ pose[:3, :3]
            if not ((local[:, 0] > 0.7) & (local[:, 0] < 5.5) & (np.abs(local[:, 1]) < 2.5)).all():
                continue
            uvs = project(delivery, pose, pts)
            first = exact_ground(delivery, pose, uvs)
            for p, uv, hit in zip(pts, uvs, first, strict=True):
                if not (2 <= uv[0] <= 637 and 2 <= uv[1] <= 477):
                    continue
                if not np.linalg.norm(hit - p) < 0.01:
                    continue  # hidden behind the crest of a bump
                shown = _pixel_showing(ground, p[:2], uv)
                assert np.hypot(*(shown - uv)) < 0.5, (k, m.design.name, uv, shown)
                checked += 1
    assert checked >= 8


@pytest.mark.parametrize("which", [0, 1, 2])
def test_every_pixel_shows_the_first_ground_point_along_its_ray(delivery, which):
    k = _frames_to_check(delivery)[which]
    pose = delivery.drive.poses[k]
    ground = delivery.render_layers(pose, delivery.conditions(occluders=False)).ground_xy()
    vs, us = np.mgrid[130:476:23, 4:636:37]
    uv = np.column_stack([us.ravel(), vs.ravel()]).astype(np.float64)
    exact = exact_ground(delivery, pose, uv)
    worst = 0.0
    for (u, v), p in zip(uv, exact, strict=True):
        shown = _pixel_showing(ground, p[:2], np.array([u, v]))
        worst = max(worst, float(np.hypot(*(shown - (u, v)))))
    assert worst < 0.5


def test_on_flat_ground_the_render_is_the_plane_homography(flat_world):
    w = flat_world
    p = max(w.truth.passes, key=lambda q: q.end_frame - q.start_frame)
    k = (p.start_frame + p.end_frame) // 2
    pose = w.drive.poses[k]
    assert abs(pose[2, 3]) < 1e-12 and np.allclose(pose[2, :3], [0, 0, 1])
    layers = w.render_layers(pose, w.conditions())
    cam = pose @ w.calibration.camera_to_base_matrix
    world_to_cam = np.linalg.inv(cam)
    H = w.calibration.intrinsics.matrix @ np.column_stack(
        [world_to_cam[:3, 0], world_to_cam[:3, 1], world_to_cam[:3, 3]]
    )
    vs, us = np.mgrid[100:480, 0:640]
    g = layers.ground_xy()[100:480]
    q = np.stack([g[..., 0], g[..., 1], np.ones_like(g[..., 0])], axis=-1) @ H.T
    err = np.hypot(q[..., 0] / q[..., 2] - us, q[..., 1] / q[..., 2] - vs)
    assert np.nanmax(err) < 0.1
    # the id image is the ground's id layer seen through the homography
    Hinv = np.linalg.inv(H)
    r = np.stack([us, vs, np.ones_like(us)], axis=-1).astype(np.float64) @ Hinv.T
    gx, gy = r[..., 0] / r[..., 2], r[..., 1] / r[..., 2]
    expected = _ids_at(w, gx, gy)
    got = layers.ids[100:480]
    assert (expected > 0).sum() > 500
    assert np.mean(expected == got) > 0.995


def _ids_at(world, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Marking ids of the 1 cm id tiles at world points (nearest texel)."""
    from sgf_plugins.world.texture import LEVELS

    lv = LEVELS[0]
    out = np.zeros(x.shape, np.int32)
    tx = np.floor(x / lv.tile).astype(int)
    ty = np.floor(y / lv.tile).astype(int)
    for a, b in {(int(i), int(j)) for i, j in zip(tx.ravel(), ty.ravel(), strict=True)}:
        sel = (tx == a) & (ty == b)
        _, ids = world.renderer.cache.get(lv, a, b)
        col = np.clip(np.floor((x[sel] - a * lv.tile) / lv.res).astype(int), 0, lv.texels - 1)
        row = np.clip(np.floor(((b + 1) * lv.tile - y[sel]) / lv.res).astype(int), 0, lv.texels - 1)
        out[sel] = ids[row, col]
    return out


def test_an_ipm_of_the_id_image_matches_the_marking_layout(flat_world):
    w = flat_world
    grid = w.grid
    checked = marked = 0
    for p in w.truth.passes[:6]:
        k = (p.start_frame + p.end_frame) // 2
        pose = w.drive.poses[k]
        ids = w.render_layers(pose, w.conditions()).ids
        layout = w.marking_layout(pose, grid)
        assert layout.shape == (grid.height, grid.width) and layout.dtype == np.int32
        assert p.instance_id in layout
        # plain IPM of the camera's id image (exact on flat ground): BEV pixel -> ground -> image pixel
        v, u = np.mgrid[0 : grid.height, 0 : grid.width]
        gx, gy = grid.pixel_to_ground(u, v)
        pts = np.stack([gx, gy, np.zeros_like(gx), np.ones_like(gx)], axis=-1) @ pose.T
        uv = project(w, pose, pts[..., :3].reshape(-1, 3)).reshape(grid.height, grid.width, 2)
        ui, vi = np.round(uv[..., 0]).astype(int), np.round(uv[..., 1]).astype(int)
        inside = (ui >= 0) & (ui < 640) & (vi >= 0) & (vi < 480)
        bev = np.zeros_like(layout)
        bev[inside] = ids[vi[inside], ui[inside]]
        # away from marking edges (where a nearest-pixel IPM is a few cm coarse far ahead) they agree
        import cv2

        kernel = np.ones((5, 5), np.uint8)
        lay = layout.astype(np.float32)
        interior = (cv2.dilate(lay, kernel) == cv2.erode(lay, kernel)) & inside
        marked += int((interior & (layout > 0)).sum())
        assert np.mean(bev[interior] == layout[interior]) > 0.995
        checked += 1
    assert checked == 6 and marked > 1000


def test_the_same_seed_renders_the_same_frames(delivery):
    again = build_world("campus_delivery", seed=0)
    other = build_world("campus_delivery", seed=1)
    k = 400
    a = delivery.frame(k)
    b = again.frame(k)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.truth_ids(), b.truth_ids())
    assert np.array_equal(a.odometry, b.odometry) and np.array_equal(a.ground_truth, b.ground_truth)
    c = other.frame(k)
    assert not np.array_equal(a.image, c.image)


def test_image_and_ids_are_rendered_once_and_lazily(delivery, monkeypatch):
    calls = []
    original = delivery.renderer.render

    def counting(pose, conditions):
        calls.append(1)
        return original(pose, conditions)

    monkeypatch.setattr(delivery.renderer, "render", counting)
    frame = delivery.frame(1200)
    assert calls == [] and not frame.image_loaded
    image = frame.image
    ids = frame.truth_ids()
    assert len(calls) == 1
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8
    assert ids.shape == (480, 640) and ids.dtype == np.int32


def test_night_is_dark_except_where_the_headlight_shines(delivery):
    k = 900
    pose = delivery.drive.poses[k]
    common = {"time": 90.0, "noise_seed": 1, "sensor_noise": False, "occluders": False}
    day, _ = delivery.render(pose, **common)
    night, _ = delivery.render(pose, night=True, **common)
    unlit, _ = delivery.render(pose, night=True, headlight=False, **common)
    dark, _ = delivery.render(pose, night=True, headlight=False, street_lamps=False, **common)
    lum = {
        name: img.astype(float).mean(axis=2)
        for name, img in {"day": day, "night": night, "unlit": unlit, "dark": dark}.items()
    }
    assert lum["night"].mean() < 0.6 * lum["day"].mean()
    assert lum["dark"].mean() < 0.25 * lum["day"].mean()
    # the LED lights the ground 1-3 m ahead, hardly the ground 10 m ahead
    led = lum["night"] - lum["unlit"]
    assert led[330:400, 240:400].mean() > 20.0
    assert led[330:400, 240:400].mean() > 4.0 * led[90:110, 240:400].mean()


def test_people_occlude_the_markings_they_stand_on(delivery):
    p = max(delivery.truth.passes, key=lambda q: q.end_frame - q.start_frame)
    pose = delivery.drive.poses[(p.start_frame + p.end_frame) // 2]
    clear = delivery.render_layers(pose, delivery.conditions(occluders=False, sensor_noise=False))
    crowded = delivery.render_layers(
        pose, delivery.conditions(occluders=False, extra_occluders=6, noise_seed=4, sensor_noise=False)
    )
    assert crowded.occluded.sum() > 2000
    assert not crowded.ids[crowded.occluded].any()
    assert np.array_equal(crowded.ids[~crowded.occluded], clear.ids[~crowded.occluded])
    changed = np.any(crowded.image != clear.image, axis=2)
    assert changed[crowded.occluded].mean() > 0.9


def test_exposure_scales_the_image(delivery):
    pose = delivery.drive.poses[600]
    dark, _ = delivery.render(pose, exposure=0.6, sensor_noise=False, occluders=False)
    bright, _ = delivery.render(pose, exposure=1.2, sensor_noise=False, occluders=False)
    ratio = bright[300:].astype(float).mean() / dark[300:].astype(float).mean()
    assert 1.7 < ratio < 2.1


def test_random_poses_render_markings_for_training(delivery):
    rng = np.random.default_rng(7)
    seen = 0
    for _ in range(6):
        pose = delivery.random_pose(rng)
        assert np.isfinite(pose).all()
        assert pose[2, 3] == pytest.approx(delivery.terrain.height(pose[0:1, 3], pose[1:2, 3])[0], abs=0.15)
        image, ids = delivery.render(pose, far_field=False, occluders=False)
        assert image.shape == (480, 640, 3)
        seen += int(ids.any())
    assert seen >= 4


def test_bad_poses_are_refused(delivery):
    with pytest.raises(ValueError, match="4x4"):
        delivery.render(np.eye(3))
