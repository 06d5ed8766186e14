"""dataset=folder reads back exactly what FolderDatasetWriter (and so sgf-world) writes."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from sgf_plugins.datasets.folder import FolderDataset, FolderParams

from sgf_pipeline.context import RunContext
from sgf_pipeline.folder_format import FolderDatasetWriter
from sgf_pipeline.truth import MarkingPass, MarkingTruth, RevisitPair, SequenceTruth

from .recordings import calibration, make_frames, write_folder


def _truth() -> SequenceTruth:
    marking = MarkingTruth(7, "arrow", "standard", False, (3.0, 1.0, 0.5), (1.2, 0.4))
    first, second = MarkingPass(7, 0, 1, 3, 0.0), MarkingPass(7, 1, 8, 9, 3.1)
    return SequenceTruth({7: marking}, [first, second], [RevisitPair(7, first, second, True)])


def test_round_trip_with_masks_truth_and_imu(tmp_path: Path):
    frames = make_frames(10, seed=9)
    calib = calibration()
    writer = FolderDatasetWriter(tmp_path / "seq", "campus_test", calib, rate_hz=10.0, image_format="png")
    masks = []
    for i, f in enumerate(frames):
        mask = np.zeros((120, 160), np.uint16)
        mask[10 + i : 30 + i, 40:90] = 7 if i % 2 else 300 + i
        masks.append(mask)
        writer.add(f.t, f.image, f.odometry, f.roll_pitch, f.ground_truth, instance_ids=mask if i != 4 else None)
    root = writer.close(truth=_truth())

    dataset = FolderDataset(FolderParams(path=str(root)))
    context = RunContext(run_dir=None)
    dataset.begin(context)
    assert context.sequence == "campus_test" and context.rate_hz == 10.0
    assert context.calibration == calib
    assert context.truth == _truth()
    got = list(dataset.frames())
    assert len(dataset) == len(got) == 10
    for i, (g, f) in enumerate(zip(got, frames, strict=True)):
        assert g.index == i and g.timestamp == pytest.approx(f.t, abs=1e-6)
        assert not g.image_loaded
        assert np.array_equal(g.image, f.image)
        np.testing.assert_allclose(g.odometry, f.odometry, atol=1e-8)
        np.testing.assert_allclose(g.ground_truth, f.ground_truth, atol=1e-8)
        assert g.imu_roll_pitch == pytest.approx(f.roll_pitch, abs=1e-9)
        ids = g.truth_ids()
        if i == 4:
            assert ids is None
        else:
            assert ids is not None and ids.dtype == np.uint16 and np.array_equal(ids, masks[i])
    dataset.finalize(context)
    assert context.metrics["dataset"] == {"name": "folder", "frames": 10, "skipped": 0, "skipped_by_reason": {}}
    without_masks = list(FolderDataset(FolderParams(path=str(root), masks=False)).frames())
    assert all(f.truth_ids() is None for f in without_masks)


def test_ground_truth_at_its_own_rate_is_interpolated(tmp_path: Path):
    frames = make_frames(6, seed=1)
    root = write_folder(tmp_path / "seq", frames, calibration())
    # replace the per-image ground truth with one sampled half-way between the images (and at both ends)
    lines = (root / "groundtruth.tum").read_text().splitlines()
    rows = [np.array(line.split(), dtype=float) for line in lines]
    dense = []
    for a, b in pairwise(rows):
        dense.append(a)
        mid = (a + b) / 2
        mid[4:] /= np.linalg.norm(mid[4:])
        dense.append(mid)
    dense.append(rows[-1])
    (root / "groundtruth.tum").write_text("".join(" ".join(f"{v:.9f}" for v in r) + "\n" for r in dense[1:]))
    got = list(FolderDataset(FolderParams(path=str(root), max_time_diff=0.06)).frames())
    assert got[0].ground_truth is not None  # 0.05 s before the first sample: within max_time_diff
    for g, f in zip(got[1:], frames[1:], strict=True):
        np.testing.assert_allclose(g.ground_truth, f.ground_truth, atol=1e-7)
