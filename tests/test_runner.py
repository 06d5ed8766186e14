"""The runner: wiring, streaming, feedback edges, outputs and the run directory."""

from __future__ import annotations

import itertools
import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from toy_stages import CALIBRATION, ToyPlugin

from sgf_pipeline import Pipeline, StageError, load_plugins
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.runner import read_ahead
from sgf_pipeline.stage import Settlement
from sgf_pipeline.trajectory import read_tum
from sgf_pipeline.types import Frame, LoopConstraints


@pytest.fixture(scope="module")
def plugins():
    return load_plugins(extra=[("toy", ToyPlugin())])


def config(**stages):
    kinds = ["dataset", *stages]
    cfg = {"pipeline": kinds, "dataset": {"name": "figure_eight", "frames": 30}, "run": {"progress": False}}
    cfg.update(stages)
    return cfg


def test_streams_frames_in_order_with_feedback_and_optional_edges(plugins):
    cfg = config(
        enhance={"name": "none"},
        measure={"name": "brightness"},
        counter={"name": "feedback", "start": 5},
        gate={"name": "even"},
        consumer={"name": "strict"},
    )
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    assert [n.kind for n in pipeline.order][:2] == ["dataset", "enhance"]
    assert pipeline.order.index(next(n for n in pipeline.order if n.kind == "measure")) > 1
    results = [pipeline.process(f) for f in pipeline.dataset.frames()]
    assert [r.outputs["count"] for r in results] == list(range(5, 35))
    assert [r.outputs["brightness"] for r in results[:4]] == [0.0, 1.0, 2.0, 3.0]
    assert [r.outputs["consumed"] for r in results[:5]] == [0, None, 20, None, 40]
    metrics = pipeline.finish()
    assert metrics["timing"]["stages"]["consumer"]["calls"] == 15
    assert metrics["timing"]["stages"]["measure"]["calls"] == 30


def test_run_writes_the_run_directory(plugins, tmp_path: Path):
    cfg = config(enhance={"name": "clahe", "clip_limit": 3.0}, backend={"name": "trust_odometry"})
    metrics = Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins).run()
    names = {p.name for p in tmp_path.iterdir()}
    assert {
        "metrics.json",
        "config.yaml",
        "trajectory_gt.tum",
        "trajectory_odometry.tum",
        "trajectory_sgf.tum",
        "trajectory.png",
        "report.md",
    } <= names
    assert not [n for n in names if n.endswith(".part")]
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk["status"] == "finished"
    assert on_disk["stages"] == {"dataset": "figure_eight", "enhance": "clahe", "backend": "trust_odometry"}
    # Odometry is the ground truth scaled by 1.05 around the origin: after a rigid alignment the
    # error is the scale residual, far above zero but well below the 10 m extent.
    assert 0.05 < on_disk["ate_rmse_m"]["odometry"] < 1.0
    assert on_disk["ate_rmse_m"]["sgf"] == pytest.approx(on_disk["ate_rmse_m"]["odometry"], rel=1e-9)
    assert on_disk["backend"] == {"nodes": 30}
    timing = on_disk["timing"]
    assert timing["frames"] == 30 and timing["dataset_frames"] == 30
    assert timing["fps"] > 0 and timing["realtime_factor"] > 0
    assert timing["sequence_seconds"] == pytest.approx(2.9)
    assert set(timing["stages"]) == {"enhance", "backend"}
    assert on_disk["peak_rss_mb"] > 10
    for key in ("pairs_found", "closed", "false_closed"):
        assert key in on_disk["loops"] and on_disk["loops"][key] is None
    gt = read_tum(tmp_path / "trajectory_gt.tum")
    assert len(gt) == 30 and gt.timestamps[1] == pytest.approx(0.1)
    assert metrics["ate_rmse_m"] == on_disk["ate_rmse_m"]


def test_metrics_json_exists_with_timing_even_without_other_metrics(plugins, tmp_path: Path):
    cfg = config(enhance={"name": "none"})
    Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins).run()
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["timing"]["stages"]["enhance"]["calls"] == 30
    assert metrics["timing"]["stages"]["enhance"]["mean_ms"] >= 0
    assert metrics["sgf"] == {"detected": None, "total": None}


def test_keyframe_selection_by_distance(plugins):
    cfg = config(enhance={"name": "none"})
    cfg["dataset"]["frames"] = 200
    cfg["run"]["keyframe_distance"] = 1.0
    cfg["run"]["keyframe_angle"] = 10.0
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    processed = [pipeline.process(f).frame_index for f in pipeline.frames()]
    poses = {f.index: f.odometry for f in pipeline.dataset.frames()}
    gaps = [np.linalg.norm(poses[b][:3, 3] - poses[a][:3, 3]) for a, b in itertools.pairwise(processed)]
    assert processed[0] == 0
    assert min(gaps) >= 1.0
    assert 40 < len(processed) < 120  # about 97 m of path at >= 1 m spacing
    assert pipeline.info.frames_seen == 200


def test_max_frames_limits_the_stream(plugins):
    cfg = config(enhance={"name": "none"})
    cfg["run"]["max_frames"] = 7
    metrics = Pipeline.from_config(cfg, plugins=plugins).run()
    assert metrics["timing"]["dataset_frames"] == 7


def test_stage_error_names_stage_and_frame_and_keeps_the_run_dir(plugins, tmp_path: Path):
    cfg = config(explode={"name": "on_three"})
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins)
    with pytest.raises(StageError, match=r"stage explode=on_three failed on frame 3 .*RuntimeError: kaboom"):
        pipeline.run()
    failure = json.loads((tmp_path / "failure.json").read_text())
    assert failure["status"] == "failed"
    assert failure["frames_processed"] == 3
    assert not (tmp_path / "metrics.json").exists()


def test_every_stage_settles_before_any_stage_finalizes(plugins):
    """A later stage's settle is seen by an earlier stage's conclude (as the back-end's by the association's)."""
    cfg = config(enhance={"name": "none"}, measure={"name": "brightness"}, backend={"name": "trust_odometry"})
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    calls: list[str] = []
    seen: dict[str, object] = {}
    for node in pipeline.order[1:]:
        stage, kind = node.stage, node.kind

        def settle(context, settlement, kind=kind):
            calls.append(f"settle {kind}")
            return replace(settlement, group_of={**settlement.group_of, (len(calls), 0): kind})

        def conclude(context, settlement, kind=kind):
            calls.append(f"conclude {kind}")
            seen[kind] = sorted(settlement.group_of.values())
            return settlement

        def finalize(context, kind=kind, original=stage.finalize):
            calls.append(f"finalize {kind}")
            original(context)

        stage.settle, stage.conclude, stage.finalize = settle, conclude, finalize  # type: ignore[method-assign]
    for frame in pipeline.dataset.frames():
        pipeline.process(frame)
    metrics = pipeline.finish()
    kinds = [n.kind for n in pipeline.order[1:]]
    ends = [call for k in kinds for call in (f"conclude {k}", f"finalize {k}")]
    assert calls == [f"settle {k}" for k in kinds] + ends  # in DAG order
    assert sorted(kinds) == ["backend", "enhance", "measure"]
    assert seen[kinds[0]] == ["backend", "enhance", "measure"]
    assert metrics["backend"] == {"nodes": 30}


def test_the_settlement_is_handed_along_the_dag_and_a_stage_that_takes_no_part_passes_it_on(plugins):
    """The default settle and conclude hand the settlement on unchanged."""
    cfg = config(enhance={"name": "none"}, measure={"name": "brightness"}, backend={"name": "trust_odometry"})
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    first, last = pipeline.order[1].stage, pipeline.order[-1].stage
    loops = LoopConstraints(())
    assignments = ()
    first.settle = lambda context, settlement: replace(settlement, group_of={(0, 0): 1})  # type: ignore[method-assign]
    received: list[Settlement] = []
    last.conclude = lambda context, settlement: received.append(settlement) or settlement  # type: ignore[method-assign]
    middle = pipeline.order[2].stage
    middle.conclude = lambda context, settlement: replace(settlement, final_loops=loops)  # type: ignore[method-assign]
    for frame in pipeline.dataset.frames():
        pipeline.process(frame)
    pipeline.finish()
    (settlement,) = received
    assert settlement.group_of == {(0, 0): 1} and settlement.final_loops is loops
    assert settlement.groups is None and settlement.assignments == assignments


def test_process_returns_the_pose_estimate_for_embedding(plugins):
    cfg = config(backend={"name": "trust_odometry"})
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    frames = list(pipeline.dataset.frames())
    step = pipeline.process(frames[0])
    assert step.pose is not None and np.allclose(step.pose, frames[0].odometry)
    step = pipeline.process(frames[1])
    assert np.allclose(step.pose, frames[1].odometry)


def test_an_interrupted_run_records_itself_and_leaves_no_half_file(plugins, tmp_path: Path):
    from sgf_pipeline import Stage

    cfg = config(explode={"name": "on_three"})
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path, plugins=plugins)
    original = Stage.process

    def interrupt(frame):  # type: ignore[no-untyped-def]
        if frame.index == 5:
            raise KeyboardInterrupt
        return 0

    node = next(n for n in pipeline.order if n.kind == "explode")
    node.stage.process = interrupt  # type: ignore[method-assign]
    with pytest.raises(KeyboardInterrupt):
        pipeline.run()
    assert original is Stage.process
    failure = json.loads((tmp_path / "failure.json").read_text())
    assert failure["status"] == "interrupted" and failure["frames_processed"] == 5
    assert len(read_tum(tmp_path / "trajectory_odometry.partial.tum")) == 5
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]
    assert not (tmp_path / "metrics.json").exists()


def test_a_stage_with_a_read_ahead_gets_the_path_driven_after_each_keyframe(plugins):
    cfg = config(enhance={"name": "none"}, ahead={"name": "path", "distance": 2.0})
    cfg["dataset"]["frames"] = 200
    cfg["run"]["keyframe_distance"] = 1.0
    cfg["run"]["keyframe_angle"] = 10.0
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    assert pipeline.read_ahead == 2.0
    results = [pipeline.process(f) for f in pipeline.frames()]
    # the same keyframes as without the read-ahead, each once and in order
    plain = config(enhance={"name": "none"})
    plain["dataset"], plain["run"] = cfg["dataset"], cfg["run"]
    reference = Pipeline.from_config(plain, plugins=plugins)
    assert reference.read_ahead == 0.0
    assert [r.frame_index for r in results] == [reference.process(f).frame_index for f in reference.frames()]
    poses = [f.odometry for f in pipeline.dataset.frames()]
    complete = 0
    for r in results:
        path = r.outputs["path"]
        k, m = r.frame_index, len(path)
        # every frame after the keyframe, keyframe or not, in order
        np.testing.assert_array_equal(path.odometry, np.stack(poses[k + 1 : k + 1 + m]))
        chain = np.stack([poses[k], *path.odometry])[:, :3, 3]
        driven = np.cumsum(np.linalg.norm(np.diff(chain, axis=0), axis=1))
        if path.complete:  # up to the first frame 2 m on, not one more
            complete += 1
            assert driven[-1] >= 2.0 and (m == 1 or driven[-2] < 2.0)
        else:  # the sequence ended sooner: the path runs to its last frame
            assert k + m == 199 and driven[-1] < 2.0
        assert np.isnan(path.imu_roll_pitch).all()  # the figure eight has no IMU
    # only the keyframes less than 2 m from the sequence's end wait for the end
    assert 0 < len(results) - complete <= 3
    assert all(r.outputs["path"].complete for r in results[:complete])
    assert pipeline.finish()["timing"]["frames"] == len(results)


def test_without_a_read_ahead_frames_carry_no_path(plugins):
    pipeline = Pipeline.from_config(config(enhance={"name": "none"}), plugins=plugins)
    assert all(f.path_ahead is None for f in itertools.islice(pipeline.frames(), 5))


def test_a_keyframe_waits_for_its_path_only_so_long():
    # 0.1 m per frame at 10 Hz for 20 frames, 10 s standing still, then on again
    x = [0.1 * min(i, 20) + 0.1 * max(0, i - 120) for i in range(160)]
    image = np.zeros((60, 80), np.uint8)
    frames = [Frame(i, 0.1 * i, image, pose_from_xy_yaw(x[i], 0.0, 0.0), CALIBRATION) for i in range(160)]
    read: list[int] = []

    def source():
        for f in frames:
            read.append(f.index)
            yield f, f.index % 5 == 0

    out = {}
    for f in read_ahead(source(), 0.95, max_seconds=3.0):
        out[f.index] = (read[-1], f.path_ahead)
    assert sorted(out) == list(range(0, 160, 5))
    # driving: a keyframe comes once the path 0.95 m on is read, complete
    assert out[5][0] == 15 and out[5][1].complete and len(out[5][1]) == 10
    assert out[10][0] == 20 and out[10][1].complete
    # at the stop: it waits 3 s of sequence time, then goes on with the path so far
    for k in (15, 20):
        seen, path = out[k]
        assert seen == k + 30 and not path.complete and len(path) == 30
    # after the stop: complete again
    assert out[125][1].complete and not out[155][1].complete  # the last ones: the sequence ended


def test_the_run_files_are_written_from_a_read_only_view_of_the_pipeline(plugins):
    import dataclasses

    from sgf_pipeline import outputs

    pipeline = Pipeline.from_config(config(backend={"name": "trust_odometry"}), plugins=plugins)
    for frame in itertools.islice(pipeline.frames(), 4):
        pipeline.process(frame)
    view = pipeline.view()
    assert view.info is pipeline.info and view.context is pipeline.context and view.options is pipeline.config.run
    assert view.dropped == pipeline.drop_report()
    assert {name: len(t) for name, t in view.recorded.items()} == {"odometry": 4, "gt": 4}
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.run_dir = Path("elsewhere")  # type: ignore[misc]
    metrics = outputs.collect_metrics(view, dict(view.recorded))
    assert metrics["stages"] == {"dataset": "figure_eight", "backend": "trust_odometry"}
    assert metrics["ate_rmse_m"]["odometry"] is not None and metrics["runner"] == view.dropped


def _keyframes_as_read(pipeline: Pipeline) -> list[tuple[int, int, float, float, int]]:
    """Each keyframe with the run's counts as it comes: index, frames seen, last time, first pixel, drops."""
    return [
        (
            f.index,
            pipeline.info.frames_seen,
            pipeline.info.last_timestamp,
            int(f.image[0, 0]),
            sum(pipeline.drops.by_reason.values()),
        )
        for f in pipeline.frames()
    ]


def _with_a_bad_frame(frames, readers: list[str]):
    """The figure eight with frame 5's timestamp non-finite (dropped by the reader), noting who read each frame."""
    for frame in frames():
        readers.append(threading.current_thread().name)
        if frame.index == 5:
            frame.timestamp = float("nan")
        yield frame


def test_a_thread_reads_the_keyframes_ahead_and_the_run_sees_what_a_reading_in_its_own_thread_sees(plugins):
    cfg = config(enhance={"name": "none"})
    cfg["dataset"]["frames"] = 120
    cfg["run"]["keyframe_distance"] = 1.0
    seen: dict[bool, list] = {}
    readers: dict[bool, list[str]] = {True: [], False: []}
    for threaded in (True, False):
        pipeline = Pipeline.from_config(cfg, plugins=plugins)
        frames = pipeline.dataset.frames
        pipeline.dataset.frames = lambda frames=frames, r=readers[threaded]: _with_a_bad_frame(frames, r)  # type: ignore[method-assign]
        pipeline.reader.load_images = threaded  # without images loaded as read, the reading stays in this thread
        seen[threaded] = _keyframes_as_read(pipeline)
        assert pipeline.info.frames_seen == 120 and pipeline.drops.by_reason == {"non-finite timestamp": 1}
    assert seen[True] == seen[False]
    assert 40 < len(seen[True]) < 120 and seen[True][0][:2] == (0, 1)
    assert set(readers[True]) == {"sgf-reading"} and set(readers[False]) == {threading.current_thread().name}


def test_a_dataset_failing_in_the_reading_thread_fails_the_run_with_its_message(plugins):
    pipeline = Pipeline.from_config(config(enhance={"name": "none"}), plugins=plugins)
    frames = pipeline.dataset.frames

    def failing():
        for frame in frames():
            if frame.index == 7:
                raise OSError("disk gone")
            yield frame

    pipeline.dataset.frames = failing  # type: ignore[method-assign]
    with pytest.raises(StageError, match=r"failed after 7 frame\(s\): OSError: disk gone"):
        pipeline.run()
    assert not [t for t in threading.enumerate() if t.name == "sgf-reading"]


def test_stopping_early_stops_the_reading_thread(plugins):
    cfg = config(enhance={"name": "none"})
    cfg["dataset"]["frames"] = 200
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    frames = pipeline.frames()
    assert next(frames).index == 0
    assert [t.name for t in threading.enumerate()].count("sgf-reading") == 1
    frames.close()
    assert not [t for t in threading.enumerate() if t.name == "sgf-reading"]
    assert pipeline.info.frames_seen < 200  # the thread read at most its queue's depth ahead
