"""The run directory's loop list: loops.csv, the loops on the trajectory plot, the report's loop table."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
from sgf_plugins.loop.files import REPORT_LOOP_ROWS, render_loops_csv, report_section

from sgf_pipeline.outputs import loop_segments, render_report
from sgf_pipeline.trajectory import Trajectory


def loop(frame_from: int, frame_to: int, **extra: object) -> dict[str, object]:
    entry: dict[str, object] = {
        "frame_from": frame_from,
        "frame_to": frame_to,
        "time_from": frame_from * 0.1,
        "time_to": frame_to * 0.1,
        "relative_xy_yaw": [0.5, -0.25, math.pi],
        "group_id": 3,
        "reverse": True,
        "from_map": False,
        "fitness": 0.0123,
        "inlier_ratio": 0.95,
        "instance_ids": [7, 7],
        "truth_error_m": 0.04,
        "truth_error_deg": 0.5,
        "true": True,
    }
    entry.update(extra)
    return entry


def with_loops(metrics: dict[str, object], accepted: list[dict[str, object]]) -> str:
    """report.md of a run whose loop stage accepted ``accepted``."""
    return render_report(metrics, [report_section(accepted)])


def line(n: int) -> Trajectory:
    """A straight drive along x, one metre per frame, 10 frames per second."""
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = np.arange(n, dtype=np.float64)
    return Trajectory(np.arange(n) * 0.1, poses)


def test_loops_csv_has_one_row_per_loop_with_the_pose_in_degrees_and_blanks_for_unknowns() -> None:
    text = render_loops_csv([loop(10, 90), loop(20, 95, time_from=None, from_map=True, true=None, truth_error_m=None)])
    rows = list(csv.DictReader(io.StringIO(text)))
    assert len(rows) == 2
    first, second = rows
    assert (first["frame_from"], first["frame_to"], first["reverse"], first["true"]) == ("10", "90", "True", "True")
    assert float(first["yaw_deg"]) == 180.0 and float(first["x"]) == 0.5 and float(first["y"]) == -0.25
    assert (first["instance_from"], first["instance_to"]) == ("7", "7")
    assert float(first["time_from"]) == 1.0 and float(first["truth_error_m"]) == 0.04
    assert second["time_from"] == "" and second["true"] == "" and second["truth_error_m"] == ""
    assert second["from_map"] == "True"
    assert render_loops_csv([]).strip().split(",")[:2] == ["frame_from", "frame_to"]  # the header, no rows


def test_loop_segments_join_the_two_frames_on_the_trajectory_and_skip_map_loops() -> None:
    trajectory = line(100)
    segments = loop_segments(
        [loop(10, 90), loop(20, 61, time_to=6.04, true=False), loop(5, 50, time_from=None, from_map=True)],
        trajectory,
    )
    assert len(segments) == 2
    (a0, a1, t0), (b0, b1, t1) = segments
    assert np.allclose(a0, [10, 0]) and np.allclose(a1, [90, 0]) and t0 is True
    assert np.allclose(b0, [20, 0]) and np.allclose(b1, [60, 0]) and t1 is False  # the nearest stamp, 6.0 s
    assert loop_segments([loop(1, 2)], line(0)) == []


def test_the_report_lists_the_loops_up_to_its_row_limit() -> None:
    metrics = {"sequence": "toy", "ate_rmse_m": {"odometry": 2.0, "sgf": 0.5}}
    report = with_loops(metrics, [loop(1, 80), loop(2, 81, true=False, truth_error_m=1.25, truth_error_deg=7.0)])
    assert "## Accepted loops (2; all in `loops.csv`)" in report
    assert "| 1 -> 80 | yes | no | 0.50, -0.25, 180.0 | 0.012 | 0.95 | 0.04, 0.5 | True |" in report
    assert "| 2 -> 81 | yes | no | 0.50, -0.25, 180.0 | 0.012 | 0.95 | 1.25, 7.0 | False |" in report
    round_marking = with_loops(metrics, [loop(3, 82, position_only=True, truth_error_m=0.03, truth_error_deg=0.0)])
    assert "| 3 -> 82 | yes | no | 0.50, -0.25, 180.0 (place only) | 0.012 | 0.95 | 0.03 at its marking | True |" in (
        round_marking
    )
    row = next(csv.DictReader(io.StringIO(render_loops_csv([loop(3, 82, position_only=True)]))))
    assert row["position_only"] == "True"
    many = with_loops(metrics, [loop(i, i + 50) for i in range(REPORT_LOOP_ROWS + 4)])
    assert many.count(" -> ") == REPORT_LOOP_ROWS
    assert "| ... and 4 more |" in many
    assert "None." in with_loops(metrics, [])
    assert "Accepted loops" not in render_report(metrics)  # a run without a loop stage
