"""FrameLog: each processed frame's odometry, distance travelled and time in flat arrays."""

from __future__ import annotations

import numpy as np
import pytest
from sgf_plugins.shared.frame_log import FrameLog

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.types import Frame

CAL = Calibration.from_mounting(Intrinsics(fx=300, fy=300, cx=159.5, cy=119.5, width=320, height=240), 1.0, 0.3)


def _frame(index: int, x: float, y: float = 0.0, truth: bool = False) -> Frame:
    pose = np.eye(4)
    pose[:2, 3] = (x, y)
    gt = pose.copy() if truth else None
    if gt is not None:
        gt[2, 3] = 7.0
    return Frame(index, 0.1 * index, np.zeros((1, 1), np.uint8), pose, CAL, None, gt)


def test_the_log_answers_as_the_frames_were_recorded() -> None:
    log = FrameLog()
    xs = [0.0, 0.3, 0.3, 1.0, 4.0]
    indices = [0, 2, 5, 6, 40]
    for k, x in zip(indices, xs, strict=True):
        log.append(_frame(k, x, y=0.5 * x))
    assert len(log) == 5 and log.last == 40
    assert log.distance(6) == pytest.approx(np.hypot(1.0, 0.5))
    assert log.travelled == pytest.approx(np.hypot(4.0, 2.0))
    assert log.time(5) == pytest.approx(0.5)
    np.testing.assert_allclose(log.odometry(40)[:2, 3], [4.0, 2.0])
    assert 5 in log and 3 not in log and 41 not in log and "5" not in log
    assert log.get_distance(3) is None and log.get_odometry(3) is None and log.get_time(41) is None
    with pytest.raises(KeyError):
        log.distance(3)
    assert log.ground_truth(5) is None and not log.has_truth()
    # the returned pose is a copy: changing it changes nothing in the log
    log.odometry(2)[0, 3] = 99.0
    assert log.odometry(2)[0, 3] == pytest.approx(0.3)
    # the poses from a frame on (from the next remembered one when it is not remembered)
    np.testing.assert_allclose(log.odometry_since(5)[:, 0, 3], [0.3, 1.0, 4.0])
    np.testing.assert_allclose(log.odometry_since(3)[:, 0, 3], [0.3, 1.0, 4.0])
    assert log.odometry_since(41).shape == (0, 4, 4)
    log.odometry_since(40)[0, 0, 3] = 99.0
    assert log.odometry(40)[0, 3] == pytest.approx(4.0)


def test_frames_must_come_in_order_and_the_same_index_replaces_the_last() -> None:
    log = FrameLog()
    log.append(_frame(0, 0.0))
    log.append(_frame(1, 1.0))
    log.append(_frame(1, 2.0))
    assert len(log) == 2 and log.distance(1) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="increasing index order"):
        log.append(_frame(0, 3.0))


def test_a_bounded_log_keeps_at_least_the_newest_frames_and_stays_small() -> None:
    log = FrameLog(keep=100)
    for k in range(1000):
        log.append(_frame(3 * k, 0.5 * k))
    assert 100 <= len(log) <= 200
    assert 3 * 899 in log and 3 * 999 in log and 0 not in log
    assert log.distance(3 * 999) == pytest.approx(0.5 * 999)  # the distance counts the forgotten frames too
    assert log._rows.shape[0] == 200  # never more than 2 * keep rows
    with pytest.raises(ValueError, match="at least 1"):
        FrameLog(keep=0)


def test_ground_truth_is_kept_from_the_first_frame_that_has_one() -> None:
    log = FrameLog(truth=True)
    for k in range(70):  # past the first growth of the arrays
        frame = _frame(k, 0.1 * k, truth=k >= 3)
        if k == 40:
            frame.ground_truth = np.zeros((3, 3))  # malformed: left out, as the runner does
        if k == 41:
            frame.ground_truth = np.full((4, 4), np.nan)
        log.append(frame)
    assert log.has_truth() and log.ground_truth(2) is None
    assert log.ground_truth(40) is None and log.ground_truth(41) is None and log.ground_truth(42) is not None
    without = FrameLog()
    without.append(_frame(0, 0.0, truth=True))
    assert without.ground_truth(0) is None and not without.has_truth()
    truth = log.ground_truth(65)
    assert truth is not None and truth[2, 3] == pytest.approx(7.0) and truth[0, 3] == pytest.approx(6.5)


def test_around_gives_the_frames_within_the_metres_driven_and_the_frame_s_row() -> None:
    log = FrameLog()
    xs = [0.0, 0.1, 0.2, 0.2, 0.3, 0.5, 0.9]  # frames 2 and 3 stand at the same place
    for k, x in enumerate(xs):
        log.append(_frame(k, x))
    poses, row = log.around(3, 0.15)
    np.testing.assert_allclose(poses[:, 0, 3], [0.1, 0.2, 0.2, 0.3])
    assert row == 2 and poses[row][0, 3] == pytest.approx(0.2)
    poses, row = log.around(6, 0.2)  # nothing else within 0.2 m: the frame alone
    assert len(poses) == 1 and row == 0
    poses, row = log.around(0, 0.25)
    np.testing.assert_allclose(poses[:, 0, 3], [0.0, 0.1, 0.2, 0.2])
    assert row == 0
    with pytest.raises(KeyError):
        log.around(9, 1.0)
