"""Degenerate geometry through the real stages (MC-IPM, the Hu detector, the polar descriptor, online groups).

Empty, one-pixel and whole-view saliency, a robot standing still for minutes, turning in place,
a long slope beyond MC-IPM's pitch threshold, NaN/inf attitude and odometry: the run goes on,
and what was left out is counted in metrics.json.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from sgf_plugins.sgf.association.stage import OnlineGroupsParams, OnlineSgfGroups
from sgf_plugins.sgf.descriptor import PolarContextParams, describe
from sgf_synthetic import Annulus, GroundShape, arrow_shape, render_saliency, toy_calibration

from sgf_pipeline import Dataset, Pipeline, Stage, hookimpl, load_plugins
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.trajectory import read_tum
from sgf_pipeline.types import Bev, Frame, SaliencyMap, SalientGroundFeature

CALIBRATION = toy_calibration()
IMAGE = np.full((CALIBRATION.intrinsics.height, CALIBRATION.intrinsics.width, 3), 128, np.uint8)
ARROW = GroundShape(arrow_shape(), (4.0, 0.0, 0.3), 1)


class Script:
    """What the scripted dataset yields and how the scripted saliency answers."""

    frames: ClassVar[list[Frame]] = []
    saliency: ClassVar[Callable[[Frame, Bev], np.ndarray]] = staticmethod(lambda frame, bev: np.zeros(bev.valid.shape))


class ScriptedDataset(Dataset):
    """The frames of :class:`Script`."""

    name = "scripted"

    def frames(self) -> Iterator[Frame]:
        yield from Script.frames

    def __len__(self) -> int:
        return len(Script.frames)


class ScriptedSaliency(Stage):
    """Saliency of a BEV as :class:`Script` says (a stand-in for the SOD network)."""

    kind = "saliency"
    name = "scripted"
    output = "saliency"

    def process(self, frame: Frame, bev: Bev) -> SaliencyMap:
        return SaliencyMap(np.asarray(Script.saliency(frame, bev), dtype=np.float32), bev)


class ScriptPlugin:
    """Registers the scripted dataset and saliency."""

    @hookimpl
    def sgf_register_stages(self, registry: Any) -> None:
        registry.add(ScriptedDataset)
        registry.add(ScriptedSaliency)


@pytest.fixture(scope="module")
def plugins():
    return load_plugins(extra=[("scripted", ScriptPlugin())])


def frames_along(poses: list[np.ndarray], imu: list[tuple[float, float]] | None = None) -> list[Frame]:
    """Frames at 10 Hz along ground-truth poses (odometry = truth), IMU level unless given."""
    attitude = imu or [(0.0, 0.0)] * len(poses)
    return [
        Frame(i, 0.1 * i, IMAGE, pose.copy(), CALIBRATION, attitude[i], ground_truth=pose.copy())
        for i, pose in enumerate(poses)
    ]


def straight(n: int, step: float = 0.05, start: float = 0.0) -> list[np.ndarray]:
    return [pose_from_xy_yaw(start + i * step, 0.0, 0.0) for i in range(n)]


def marking_saliency(shapes: list[GroundShape]) -> Callable[[Frame, Bev], np.ndarray]:
    """Render the markings seen from the frame's pose (odometry = truth; cached: a still robot sees one picture)."""
    cache: dict[bytes, np.ndarray] = {}

    def render(frame: Frame, bev: Bev) -> np.ndarray:
        key = np.asarray(frame.odometry).tobytes()
        if key not in cache:
            cache[key] = render_saliency(shapes, frame.odometry, bev.grid, bev.valid, supersample=1)[0]
        return cache[key]

    return render


def run(plugins, tmp_path: Path, frames: list[Frame], saliency, **stage_params: dict[str, Any]):
    """Run dataset -> enhance -> ipm(mc) -> saliency -> detector -> descriptor -> association; the metrics and stages."""
    Script.frames = frames
    Script.saliency = staticmethod(saliency)
    cfg: dict[str, Any] = {
        "pipeline": ["dataset", "enhance", "ipm", "saliency", "detector", "descriptor", "association"],
        "dataset": {"name": "scripted"},
        "enhance": {"name": "none"},
        "ipm": {"name": "mc"},
        "saliency": {"name": "scripted"},
        "detector": {"name": "hu_window"},
        "descriptor": {"name": "polar_context"},
        "association": {"name": "online_groups"},
        "run": {"progress": False, "plots": False},
    }
    for kind, params in stage_params.items():
        cfg[kind] = {**cfg.get(kind, {}), **params}
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins)
    pipeline.run()
    stages = {n.kind: n.stage for n in pipeline.order}
    return json.loads((tmp_path / "metrics.json").read_text()), stages


def empty(frame: Frame, bev: Bev) -> np.ndarray:
    return np.zeros(bev.valid.shape)


# -- saliency that is empty, tiny, or everything ------------------------------------------------


def test_empty_saliency_masks(plugins, tmp_path: Path):
    metrics, _ = run(plugins, tmp_path, frames_along(straight(60)), empty)
    assert metrics["status"] == "finished" and metrics["timing"]["frames"] == 60
    sgf = metrics["sgf"]
    assert (sgf["tracks"], sgf["selected"], sgf["regions_too_small"], sgf["groups"]) == (0, 0, 0, 0)
    assert metrics["ipm"]["frames"] == 60 and metrics["runner"]["dropped_frames"] == 0


def test_one_pixel_regions_are_counted_as_too_small(plugins, tmp_path: Path):
    def specks(frame: Frame, bev: Bev) -> np.ndarray:
        prob = np.zeros(bev.valid.shape)
        rows, cols = np.nonzero(bev.valid)
        pick = np.linspace(0, len(rows) - 1, 7).astype(int)[1:-1]  # five well separated valid pixels
        prob[rows[pick], cols[pick] + (frame.index % 2)] = 1.0
        return prob * bev.valid

    metrics, _ = run(plugins, tmp_path, frames_along(straight(40)), specks)
    assert metrics["sgf"]["regions_too_small"] == 5 * 40
    assert metrics["sgf"]["tracks"] == 0 and metrics["sgf"]["selected"] == 0


def test_a_whole_view_region_splits_its_track_and_keeps_no_old_pixels(plugins, tmp_path: Path):
    def everything(frame: Frame, bev: Bev) -> np.ndarray:
        return bev.valid.astype(np.float64)

    metrics, stages = run(plugins, tmp_path, frames_along(straight(150)), everything, detector={"max_track_views": 50})
    sgf = metrics["sgf"]
    assert sgf["tracks_split"] == (150 - 1) // 49  # a successor starts with the view that closed its predecessor
    assert sgf["selected"] == 0 and sgf["rejected_border"] == sgf["tracks_split"]  # every view touched the border
    (track,) = stages["detector"]._tracks
    assert len(track.views) == 150 - 3 * 49
    assert [len(v.region.pixels) > 0 for v in track.views].count(True) == 1  # only the newest view keeps pixels


# -- identical and empty descriptors ---------------------------------------------------------------


def _sgf(pixels: np.ndarray, frame: int = 0) -> SalientGroundFeature:
    from sgf_synthetic import DEFAULT_GRID

    return SalientGroundFeature(frame, frame, 0.1 * frame, np.eye(4), pixels, DEFAULT_GRID, 0.9, np.zeros(7), 3, None)


def test_identical_descriptors_share_one_group_at_distance_zero():
    v, u = np.mgrid[100:140, 110:125]
    descriptor = describe(_sgf(np.stack([u.ravel(), v.ravel()], axis=1)), PolarContextParams())
    assert descriptor is not None
    groups = OnlineSgfGroups(OnlineGroupsParams())
    from sgf_pipeline.context import RunContext

    groups.begin(RunContext(None))
    assignments = [groups.assign(descriptor) for _ in range(60)]
    assert [a.new_group for a in assignments] == [True] + [False] * 59
    assert all(a.distance == 0.0 and a.shift == 0 and math.isfinite(a.yaw) for a in assignments[1:])
    (group,) = groups.groups
    assert len(group.members) == 60 and np.array_equal(group.descriptor, descriptor.matrix)


def test_a_marking_wider_than_the_descriptor_is_dropped_not_described():
    ring = GroundShape((Annulus(outer=2.4, inner=2.2),), (3.0, 0.0, 0.0), 1)
    from sgf_synthetic import DEFAULT_GRID

    prob, _ = render_saliency([ring], pose_from_xy_yaw(0.0, 0.0, 0.0), DEFAULT_GRID, supersample=1)
    v, u = np.nonzero(prob >= 0.5)
    sgf = _sgf(np.stack([u, v], axis=1))
    assert len(u) > 500
    assert describe(sgf, PolarContextParams()) is None  # every point lies beyond L_max = 2 m of the centroid
    assert describe(sgf, PolarContextParams(max_radius=3.0)) is not None


# -- a robot standing still, turning in place ----------------------------------------------------


def test_standing_still_for_two_minutes_adds_no_views(plugins, tmp_path: Path):
    approach = straight(40, 0.05)  # 2 m: the arrow comes into view
    still = [approach[-1]] * 1200  # two minutes at 10 Hz
    leave = straight(80, 0.05, start=approach[-1][0, 3] + 0.05)  # drive past it
    frames = frames_along([*approach, *still, *leave])
    metrics, stages = run(plugins, tmp_path, frames, marking_saliency([ARROW]))
    sgf = metrics["sgf"]
    assert sgf["stationary_views"] == 1200
    assert sgf["selected"] == 1 and sgf["tracks"] == 1 and sgf["open_at_end"] == 0
    (selected,) = stages["detector"].selected
    assert selected.views < 100  # the moving views only: never the 1200 identical ones
    assert metrics["ipm"]["frames"] == 1320 and metrics["ipm"]["outlier_frames"] == 0
    assert len(stages["ipm"].queue) == 50
    assert metrics["timing"]["frames"] == 1320 and len(read_tum(tmp_path / "trajectory_odometry.tum")) == 1320


def test_turning_in_place_follows_the_marking_and_finds_it_again(plugins, tmp_path: Path):
    marking = GroundShape(arrow_shape(), (2.0, 0.0, 0.5), 1)
    turn = [pose_from_xy_yaw(0.0, 0.0, 0.02 * i) for i in range(int(2 * math.pi / 0.02) + 40)]
    metrics, stages = run(plugins, tmp_path, frames_along(turn), marking_saliency([marking]))
    sgf = metrics["sgf"]
    assert sgf["stationary_views"] == 0  # every frame turned 0.02 rad: a new view each time
    assert sgf["selected"] == 2 and sgf["groups"] == 1  # before and after the full turn: one marking, one group
    (group,) = stages["association"].groups
    assert len(group.members) == 2 and abs(group.members[1].sgf.frame_index - group.members[0].sgf.frame_index) > 250
    assert metrics["runner"]["dropped_frames"] == 0


# -- attitude: long slopes, NaN and inf -------------------------------------------------------------


def test_a_long_slope_beyond_the_pitch_threshold(plugins, tmp_path: Path):
    imu = [(0.0, 0.0)] * 60 + [(0.0, 0.1)] * 300 + [(0.0, 0.0)] * 60
    metrics, stages = run(plugins, tmp_path, frames_along(straight(420), imu), empty)
    ipm = metrics["ipm"]
    # Onto the slope and off it, the median needs 25 frames to cross: those frames are compensated
    # by their full pitch (outliers of their queue), and the 25th of each has no inlier at all.
    assert ipm["outlier_frames"] == 50 and ipm["reference_without_inliers"] == 2
    assert ipm["max_abs_pitch_compensation"] == pytest.approx(0.1)
    assert stages["ipm"].last_reference.pitch == 0.0 and len(stages["ipm"].queue) == 50


@pytest.mark.parametrize(("attitude", "counted"), [("auto", "attitude_from_odometry"), ("imu", "attitude_dropouts")])
def test_nan_and_inf_attitude_are_counted(plugins, tmp_path: Path, attitude: str, counted: str):
    imu = [(0.0, 0.0)] * 50
    imu[10], imu[20], imu[30] = (math.nan, 0.0), (0.0, math.inf), (-math.inf, math.nan)
    metrics, _ = run(plugins, tmp_path, frames_along(straight(50), imu), empty, ipm={"attitude": attitude})
    ipm = metrics["ipm"]
    assert ipm[counted] == 3 and ipm["frames"] == 50
    other = {"attitude_from_odometry", "attitude_dropouts"} - {counted}
    assert ipm[other.pop()] == 0


def test_nan_inf_and_non_rigid_odometry_frames_are_dropped_and_counted(plugins, tmp_path: Path):
    poses = straight(40)
    frames = frames_along(poses)
    for i in (5, 6):
        frames[i].odometry = frames[i].odometry.copy()
        frames[i].odometry[0, 3] = math.nan
    frames[12].odometry = np.full((4, 4), math.inf)
    frames[20].odometry = 2.0 * np.eye(4)  # a scaled "rotation"
    frames[20].odometry[3, 3] = 1.0
    frames[25].ground_truth = np.full((4, 4), math.nan)
    frames[26].ground_truth = np.zeros((3, 3))
    metrics, _ = run(plugins, tmp_path, frames, marking_saliency([ARROW]))
    assert metrics["runner"] == {
        "dropped_frames": 4,
        "dropped_by_reason": {"non-finite odometry": 3, "non-rigid odometry": 1},
        "ground_truth_dropped": 2,
    }
    assert metrics["timing"]["frames"] == 36 and metrics["timing"]["dataset_frames"] == 40
    assert len(read_tum(tmp_path / "trajectory_odometry.tum")) == 36
    assert len(read_tum(tmp_path / "trajectory_gt.tum")) == 34
    # A straight drive leaves the SE(3) alignment undetermined: no ATE, and metrics.json says why.
    assert metrics["ate_rmse_m"]["odometry"] is None
    assert metrics["warnings"] == [
        "ATE of odometry not computed: se3 alignment is not possible (Degenerate covariance rank, Umeyama alignment "
        "is not possible): the associated positions lie on one point or one line (a robot standing still or driving "
        "straight), which leaves the rotation undetermined; use align=none"
    ]


def test_a_robot_driver_feeding_bad_frames_gets_them_back_dropped(plugins):
    Script.frames = []
    Script.saliency = staticmethod(empty)
    pipeline = Pipeline.from_config(
        {
            "pipeline": ["dataset", "enhance", "ipm"],
            "dataset": {"name": "scripted"},
            "enhance": {"name": "none"},
            "ipm": {"name": "mc"},
            "run": {"progress": False},
        },
        plugins=plugins,
    )
    good = frames_along(straight(3))
    assert pipeline.process(good[0]).dropped is None and pipeline.process(good[2]).dropped is None
    late = pipeline.process(good[1])  # older than the last processed frame
    assert (late.dropped, late.outputs, late.pose) == ("timestamp not increasing", {}, None)
    timeless = Frame(9, math.nan, IMAGE, np.eye(4), CALIBRATION)
    assert pipeline.process(timeless).dropped == "non-finite timestamp"
    flat = Frame(10, 5.0, IMAGE, np.eye(3), CALIBRATION)
    assert pipeline.process(flat).dropped == "malformed odometry"
    metrics = pipeline.finish()
    assert metrics["runner"]["dropped_by_reason"] == {
        "malformed odometry": 1,
        "non-finite timestamp": 1,
        "timestamp not increasing": 1,
    }
    assert metrics["timing"]["frames"] == 2


def test_a_run_never_reports_the_ate_of_an_earlier_run(plugins, tmp_path: Path):
    """The metrics skeleton was shared between runs: a run without ATE reported the previous run's."""
    curve = [pose_from_xy_yaw(3.0 * math.sin(0.1 * i), 3.0 * (1 - math.cos(0.1 * i)), 0.1 * i) for i in range(30)]
    frames = frames_along(curve)
    for f in frames:
        f.odometry = f.odometry.copy()
        f.odometry[:2, 3] *= 1.05
    first, _ = run(plugins, tmp_path / "curve", frames, empty)
    assert first["ate_rmse_m"]["odometry"] > 0.01
    second, _ = run(plugins, tmp_path / "straight", frames_along(straight(30)), empty)
    assert second["ate_rmse_m"] == {"odometry": None, "sgf": None}
    from sgf_pipeline.outputs import METRIC_SKELETON

    assert METRIC_SKELETON["ate_rmse_m"] == {"odometry": None, "sgf": None}
