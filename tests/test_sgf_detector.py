"""The moment-based SGF detector on synthetic streams of BEV saliency maps (Sec. III-B)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from sgf_plugins.sgf.detector import HuMomentDetector, HuWindowParams
from sgf_plugins.sgf.regions import Region, border_band
from sgf_plugins.sgf.tracking import FeatureTrack, FeatureView
from sgf_synthetic import (
    DEFAULT_GRID,
    Annulus,
    ConvexPart,
    GroundShape,
    SaliencyStream,
    arrow_shape,
    fov_valid_mask,
    rectangle,
    straight_path,
    toy_calibration,
)

from sgf_pipeline import RunContext
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.types import Bev, BevGrid, Frame, SaliencyMap, SalientGroundFeature

DIAMOND = (ConvexPart(np.array([[-0.8, 0.0], [0.0, -0.4], [0.8, 0.0], [0.0, 0.4]])),)


def run(stream: SaliencyStream, params: HuWindowParams | None = None, truth: bool = True):
    """Stream through a detector; returns (detector, [(output frame, sgf)], context after finalize)."""
    detector = HuMomentDetector(params or HuWindowParams())
    context = RunContext(None)
    detector.begin(context)
    out: list[tuple[int, SalientGroundFeature]] = []
    for frame, bev, saliency in stream:
        for sgf in detector.process(frame, bev, saliency).items:
            out.append((frame.index, sgf))
    if truth:
        context.truth = stream.truth()
    detector.finalize(context)
    return detector, out, context


def out_and_back(step: float = 0.2, length: float = 12.0, lateral: float = 0.25) -> list[np.ndarray]:
    """Drive along +x, then come back along -x on a parallel line (a reverse revisit)."""
    n = int(length / step)
    out = [pose_from_xy_yaw(i * step, 0.0, 0.0) for i in range(n)]
    back = [pose_from_xy_yaw(length - i * step, lateral, math.pi) for i in range(n)]
    return out + back


@pytest.fixture(scope="module")
def diamond_passes():
    """A diamond passed twice (forward, then reverse); the truth of its passes from a first iteration."""
    shapes = [GroundShape(DIAMOND, (6.03, 0.11, 0.37), 7)]
    poses = out_and_back()
    stream = SaliencyStream(shapes, poses, supersample=2)
    for _ in stream:
        pass
    return shapes, poses, stream.truth()


def test_one_sgf_per_pass_at_the_most_salient_frame(diamond_passes):
    shapes, poses, truth = diamond_passes
    passes = [p for p in truth.passes if p.instance_id == 7]
    assert len(passes) == 2 and len(truth.revisits) == 1 and truth.revisits[0].reverse
    # The saliency network is most confident on one frame inside each pass.
    peaks = [p.start_frame + (p.end_frame - p.start_frame) // 3 for p in passes]
    gain = np.full(len(poses), 0.8)
    gain[peaks] = 1.0
    stream = SaliencyStream(shapes, poses, gain=list(gain), supersample=2)
    _, out, context = run(stream)
    assert [sgf.frame_index for _, sgf in out] == peaks
    for (emitted, sgf), p in zip(out, passes, strict=True):
        assert p.contains(sgf.frame_index)
        assert emitted > p.end_frame  # the range ends when the diamond leaves the view
        assert sgf.instance_id == 7
        assert sgf.views > p.end_frame - p.start_frame  # entering and leaving views belong to the range
        assert sgf.saliency == pytest.approx(1.0, abs=0.05)
        assert np.allclose(sgf.odometry, stream.poses[sgf.frame_index])  # odometry of its own frame
        assert sgf.hu.shape == (7,) and sgf.grid == DEFAULT_GRID
        area = 1.6 * 0.8 / 2 / 0.02**2  # the diamond's area in pixels
        assert len(sgf.pixels) == pytest.approx(area, rel=0.05)
    assert context.metrics["sgf"]["detected"] == 1
    assert context.metrics["sgf"]["total"] == 1
    assert context.metrics["sgf"]["selected"] == 2
    assert context.metrics["sgf"]["open_at_end"] == 0
    kept = context.artifacts["sgf_selected"]
    assert [(s.track_id, s.frame_index, s.instance_id) for s in kept] == [
        (s.track_id, s.frame_index, s.instance_id) for _, s in out
    ]
    assert all(s.pixels.shape == (0, 2) for s in kept)  # the run keeps them without their BEV pixels
    assert all(len(s.pixels) > 0 for _, s in out)  # the stage's outputs keep theirs


def test_an_sgf_carries_the_homography_of_its_own_view(diamond_passes):
    shapes, poses, _ = diamond_passes
    detector = HuMomentDetector(HuWindowParams())
    detector.begin(RunContext(None))
    out = []
    for frame, bev, saliency in SaliencyStream(shapes, poses, supersample=2):
        mapping = np.diag([1.0, 1.0, 1.0 + frame.index])  # a different BEV -> image mapping per frame
        bev = replace(bev, homography=mapping)
        out += detector.process(frame, bev, replace(saliency, bev=bev)).items
    assert len(out) == 2
    for sgf in out:
        assert sgf.homography is not None and sgf.homography[2, 2] == 1.0 + sgf.frame_index
        assert sgf.without_pixels().homography is None  # long-lived records drop it with the pixels


def test_selected_views_never_touch_the_border():
    """An arrow and a ring on a curved path: every SGF lies wholly inside the camera's view."""
    shapes = [
        GroundShape(arrow_shape(), (4.6, 0.4, 0.3), 1),
        GroundShape((Annulus(0.35, 0.22),), (8.1, 0.6, 0.0), 2),
    ]
    poses: list[np.ndarray] = []
    yaw_rate, step = 0.012, 0.2
    x = y = yaw = 0.0
    for _ in range(70):
        poses.append(pose_from_xy_yaw(x, y, yaw))
        x, y, yaw = x + step * math.cos(yaw), y + step * math.sin(yaw), yaw + yaw_rate
    stream = SaliencyStream(shapes, poses, supersample=2)
    _, out, context = run(stream)
    assert sorted(sgf.instance_id for _, sgf in out) == [1, 2]
    band = border_band(fov_valid_mask(DEFAULT_GRID), 1)
    for _, sgf in out:
        assert not band[sgf.pixels[:, 1], sgf.pixels[:, 0]].any()
        assert context.truth is not None and context.truth.pass_of(sgf.instance_id, sgf.frame_index) is not None


def test_a_marking_never_wholly_in_view_gives_no_sgf():
    # Longer than the BEV (5.12 m): it always touches the image border.
    long_bar = GroundShape((rectangle(7.0, 0.3),), (9.0, -1.0, 0.0), 1)
    # A camera that sees only y < 0.56 m, and a square always cut by that edge of its view.
    valid = np.zeros((DEFAULT_GRID.height, DEFAULT_GRID.width), bool)
    valid[:, 100:] = True
    beside = GroundShape((rectangle(0.6, 0.6),), (5.0, 0.56, 0.0), 2)
    path = straight_path((0.0, 0.0, 0.0), 0.25, 50)
    stream = SaliencyStream([long_bar, beside], path, valid=valid, supersample=2)
    _, out, context = run(stream)
    assert out == []
    assert context.metrics["sgf"]["tracks"] >= 2
    assert context.metrics["sgf"]["rejected_border"] >= 2
    assert context.metrics["sgf"]["detected"] == 0 and context.metrics["sgf"]["total"] == 0


def test_fast_motion_is_followed_through_odometry():
    """A 0.5 m disc moving 0.6 m per frame never overlaps its previous view: only the prediction links them."""
    disc = GroundShape((Annulus(0.25),), (7.0, 0.1, 0.0), 3)
    stream = SaliencyStream([disc], straight_path((0.0, 0.0, 0.0), 0.6, 16), supersample=2)
    detector, out, _ = run(stream)
    assert len(out) == 1 and out[0][1].instance_id == 3
    assert detector.stats["tracks"] == 1
    # With the odometry withheld (the robot "stands still"), every frame starts a new track.
    still = SaliencyStream([disc], straight_path((0.0, 0.0, 0.0), 0.6, 16), odometry=[np.eye(4)] * 16, supersample=2)
    detector, out, _ = run(still, HuWindowParams(max_centroid_distance=0.0))
    assert detector.stats["tracks"] > 3


def test_degenerate_saliency_maps_do_not_crash():
    grid, valid = DEFAULT_GRID, fov_valid_mask(DEFAULT_GRID)
    detector = HuMomentDetector(HuWindowParams(min_area=5))
    detector.begin(RunContext(None))
    calibration = toy_calibration()
    maps = [
        np.zeros((256, 256), np.float32),  # nothing salient
        np.ones((256, 256), np.float32),  # the whole view salient: one region touching every border
        np.ones((256, 256), np.float32),
        np.full((256, 256), np.nan, np.float32),  # a broken network output
        np.zeros((256, 256), np.float32),
    ]
    maps[4][120, 128] = 1.0  # a single pixel: below min_area
    maps[4][100:103, 128:130] = 1.0  # six pixels: a tiny region, kept
    total = 0
    for i, prob in enumerate(maps):
        bev = Bev(np.zeros((256, 256), np.uint8), valid, grid, i, 0.1 * i)
        frame = Frame(i, 0.1 * i, np.zeros((4, 4), np.uint8), pose_from_xy_yaw(0.1 * i, 0, 0), calibration)
        total += len(detector.process(frame, bev, SaliencyMap(prob, bev)).items)
        _, regions = detector.regions(bev, SaliencyMap(prob, bev))
        if i == 1:
            assert len(regions) == 1 and regions[0].touches_border
        if i == 4:
            assert len(regions) == 1 and len(regions[0].pixels) == 6
    assert total == 0  # the whole-view region touched the border; the others were too short
    bev = Bev(np.zeros((256, 256), np.uint8), valid, grid, 9, 0.9)
    frame = Frame(9, 0.9, np.zeros((4, 4), np.uint8), np.eye(4), calibration)
    with pytest.raises(ValueError, match="differ in size"):
        detector.process(frame, bev, SaliencyMap(np.zeros((10, 10), np.float32), bev))
    with pytest.raises(ValueError, match="BEV of frame 9 given with frame 8"):
        other = Frame(8, 0.8, np.zeros((4, 4), np.uint8), np.eye(4), calibration)
        detector.process(other, bev, SaliencyMap(np.zeros((256, 256), np.float32), bev))
    with pytest.raises(ValueError, match="finite 4x4"):
        broken = Frame(9, 0.9, np.zeros((4, 4), np.uint8), np.full((4, 4), np.nan), calibration)
        detector.process(broken, bev, SaliencyMap(np.zeros((256, 256), np.float32), bev))
    with pytest.raises(ValueError, match="float map"):
        detector.process(frame, bev, SaliencyMap(np.zeros((256, 256), np.uint8), bev))
    with pytest.raises(ValueError, match="min_area"):
        HuWindowParams(min_area=2)


def test_metrics_are_null_without_ground_truth(diamond_passes):
    shapes, poses, _ = diamond_passes
    _, out, context = run(SaliencyStream(shapes, poses[:40], supersample=2), truth=False)
    assert len(out) == 1
    assert context.metrics["sgf"]["detected"] is None and context.metrics["sgf"]["total"] is None


def test_closing_joins_fragments_of_one_marking():
    grid, valid = DEFAULT_GRID, fov_valid_mask(DEFAULT_GRID)
    prob = np.zeros((256, 256), np.float32)
    prob[100:140, 100:118] = 1.0
    prob[100:140, 121:140] = 1.0  # the same marking, cut by a 3-pixel crack in the saliency
    bev = Bev(np.zeros((256, 256), np.uint8), valid, grid, 0, 0.0)
    assert len(HuMomentDetector(HuWindowParams(merge_distance=0.0)).regions(bev, SaliencyMap(prob, bev))[1]) == 2
    closed = HuMomentDetector(HuWindowParams(closing=2, merge_distance=0.0)).regions(bev, SaliencyMap(prob, bev))[1]
    assert len(closed) == 1 and 40 * 37 + 100 < len(closed[0].pixels) <= 40 * 40


def test_merge_distance_joins_the_glyphs_of_one_sign_into_one_sgf():
    grid, valid = DEFAULT_GRID, fov_valid_mask(DEFAULT_GRID)
    prob = np.zeros((256, 256), np.float32)
    prob[100:140, 100:115] = 1.0
    prob[100:140, 122:137] = 1.0  # a second glyph 7 px = 0.14 m to the side
    prob[200:240, 100:115] = 1.0  # another marking 60 px = 1.2 m nearer
    bev = Bev(np.zeros((256, 256), np.uint8), valid, grid, 0, 0.0)
    apart = HuMomentDetector(HuWindowParams(merge_distance=0.0)).regions(bev, SaliencyMap(prob, bev))[1]
    assert sorted(len(r.pixels) for r in apart) == [600, 600, 600]
    merged = HuMomentDetector(HuWindowParams(merge_distance=0.2)).regions(bev, SaliencyMap(prob, bev))[1]
    # the two glyphs form one region of their own pixels only (the gap stays out); the far marking stays apart
    assert sorted(len(r.pixels) for r in merged) == [600, 1200]
    joined = max(merged, key=lambda r: len(r.pixels))
    assert set(np.unique(joined.pixels[:, 0])) == set(range(100, 115)) | set(range(122, 137))
    too_close = HuMomentDetector(HuWindowParams(merge_distance=0.1)).regions(bev, SaliencyMap(prob, bev))[1]
    assert len(too_close) == 3  # 0.14 m apart is more than 0.1 m


def test_border_reach_merge_treats_a_row_cut_by_the_view_as_not_fully_appeared():
    """A chevron row whose next part could lie just outside the camera's view has not fully appeared."""
    grid = DEFAULT_GRID
    valid = np.zeros((256, 256), bool)
    valid[:, 40:] = True  # the camera sees nothing left of column 40
    prob = np.zeros((256, 256), np.float32)
    for left in (45, 75, 105):  # a row of three parts, 10 px (0.2 m) apart; the first 5 px (0.1 m) from the edge
        prob[150:170, left : left + 20] = 1.0
    prob[60:80, 120:140] = 1.0  # a marking far from any edge
    prob[60:80, 200:220] = 1.0  # and one 36 px (0.72 m) from the image's right border
    bev = Bev(np.zeros((256, 256), np.uint8), valid, grid, 0, 0.0)

    def touching(reach: str, merge: float = 0.3) -> dict[int, bool]:
        params = HuWindowParams(border_reach=reach, merge_distance=merge)
        regions = HuMomentDetector(params).regions(bev, SaliencyMap(prob, bev))[1]
        return {int(r.pixels[:, 0].min()): r.touches_border for r in regions}

    # The row is one SGF (gaps 0.2 m < 0.3 m); its pixels keep 5 px from the edge, within the 8 px reach.
    assert touching("region") == {45: False, 120: False, 200: False}
    assert touching("merge") == {45: True, 120: False, 200: False}
    # Half of a 0.2 m merge distance is 5 px: the first part's 5 px gap (the margin band takes 1) is reached.
    assert touching("merge", 0.2)[45] is True
    # Without merging nothing joins a region from outside the view, so the reach is the margin alone.
    assert touching("merge", 0.0) == {45: False, 75: False, 105: False, 120: False, 200: False}


@pytest.mark.parametrize(
    ("view_choice", "margin", "pick"), [("most_salient", 0.1, 0), ("salient_near", 0.1, 1), ("salient_near", 0.01, 0)]
)
def test_salient_near_takes_the_nearest_of_the_nearly_most_salient_views(diamond_passes, view_choice, margin, pick):
    shapes, poses, truth = diamond_passes
    first = next(p for p in truth.passes if p.instance_id == 7)
    length = first.end_frame - first.start_frame
    peak, later = first.start_frame + length // 3, first.start_frame + length // 2  # later = nearer (driving at it)
    gain = np.full(40, 0.7)
    gain[peak], gain[later] = 1.0, 0.95
    stream = SaliencyStream(shapes, poses[:40], gain=list(gain), supersample=2)
    params = HuWindowParams(view_choice=view_choice, near_margin=margin)
    _, out, _ = run(stream, params)
    assert [sgf.frame_index for _, sgf in out] == [(peak, later)[pick]]


@pytest.mark.parametrize(
    ("view_choice", "margin", "pick"),
    [("most_salient", 0.1, 1), ("salient_near", 0.1, 1), ("track_near", 0.1, 3), ("track_near", 0.05, 1)],
)
def test_track_near_looks_past_groups_of_one_view(view_choice, margin, pick):
    """Where eq. 8 splits every view into its own group, only track_near still finds the nearer view."""
    grid = BevGrid(0.02, 0.5, 5.62, -2.56, 2.56)
    saliency = [0.90, 0.95, 0.80, 0.88]  # frames 0-3, driving at the feature: each view 20 rows nearer
    views = []
    for k, s in enumerate(saliency):
        rows = 40 + 20 * k
        pixels = np.array([[c, r] for r in range(rows, rows + 10) for c in range(120, 130)])
        hu = np.full(7, 0.1 * (k + 1))  # eq. 8 distances far above the threshold: groups of one
        region = Region(pixels, s, hu, touches_border=False, instance_id=None)
        views.append(FeatureView(k, 0.1 * k, pose_from_xy_yaw(0.2 * k, 0.0, 0.0), region))
    detector = HuMomentDetector(HuWindowParams(view_choice=view_choice, near_margin=margin))
    sgf = detector.select(FeatureTrack(0, views), grid)
    assert sgf is not None and sgf.frame_index == pick
    assert sgf.saliency == saliency[pick]
