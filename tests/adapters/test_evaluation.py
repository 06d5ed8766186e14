"""ATE and RPE reproduce evo on evo's own test trajectories; trajectory files round-trip through evo."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sgf_pipeline.errors import DataError
from sgf_pipeline.evaluation import ate, ate_rmse, rpe
from sgf_pipeline.trajectory import Trajectory, read_trajectory

# evo 1.38.1's evo_ape results on these files (shared/data/README.md)
EVO_APE = [
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "none", 7.790289),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "se3", 1.303450),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "sim3", 0.937709),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "se3", 0.013470),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", "sim3", 0.006123),
]


def _read(path: Path) -> Trajectory:
    return read_trajectory(path, duplicates="drop")  # fr2_desk's ground truth repeats one timestamp


@pytest.mark.parametrize(("ref", "est", "align", "expected"), EVO_APE)
def test_ate_reproduces_evo_ape(shared_data: Path, ref: str, est: str, align: str, expected: float):
    evo = shared_data / "evo"
    result = ate(_read(evo / ref), _read(evo / est), align)  # type: ignore[arg-type]
    assert result.rmse == pytest.approx(expected, abs=1e-6)
    assert ate_rmse(_read(evo / ref), _read(evo / est), align) == result.rmse  # type: ignore[arg-type]
    assert result.min <= result.median <= result.max and result.rmse >= result.mean


def test_kitti_with_times_file_gives_the_same_ate(shared_data: Path):
    evo = shared_data / "evo"
    times = evo / "KITTI_00_gt_times.txt"
    gt = read_trajectory(evo / "KITTI_00_gt.txt", "kitti", times)
    orb = read_trajectory(evo / "KITTI_00_ORB.txt", "kitti", times)
    assert gt.timestamps[1] == pytest.approx(0.1037359)
    result = ate(gt, orb, "se3")
    assert result.rmse == pytest.approx(1.303450, abs=1e-6)
    assert result.pairs == 4541


def _evo_files(evo_dir: Path, ref: str, est: str):  # type: ignore[no-untyped-def]
    """Both files read by evo's own file_interface (an independent path to the same data)."""
    from evo.core import sync
    from evo.tools import file_interface

    if ref.startswith("KITTI"):
        return file_interface.read_kitti_poses_file(evo_dir / ref), file_interface.read_kitti_poses_file(evo_dir / est)
    r = file_interface.read_tum_trajectory_file(evo_dir / ref)
    e = file_interface.read_tum_trajectory_file(evo_dir / est)
    return sync.associate_trajectories(r, e, max_diff=0.01)


RPE_CASES = [
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", 1, "frames", "translation", "none"),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", 100, "meters", "rotation", "sim3"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", 1, "frames", "rotation", "se3"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", 0.1, "meters", "translation", "sim3"),
]


@pytest.mark.parametrize(("ref", "est", "delta", "unit", "relation", "align"), RPE_CASES)
def test_rpe_matches_evo_library(shared_data: Path, ref, est, delta, unit, relation, align):  # type: ignore[no-untyped-def]
    import copy

    from evo.core import metrics
    from evo.core.units import Unit
    from evo.main_rpe import rpe as evo_rpe

    evo = shared_data / "evo"
    ours = rpe(_read(evo / ref), _read(evo / est), delta, unit, relation, align)
    traj_ref, traj_est = _evo_files(evo, ref, est)
    theirs = evo_rpe(
        copy.deepcopy(traj_ref),
        copy.deepcopy(traj_est),
        metrics.PoseRelation.translation_part if relation == "translation" else metrics.PoseRelation.rotation_angle_deg,
        delta=delta,
        delta_unit={"frames": Unit.frames, "meters": Unit.meters}[unit],
        align=align != "none",
        correct_scale=align == "sim3",
    )
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert getattr(ours, key) == pytest.approx(theirs.stats[key], rel=1e-9, abs=1e-12), key
    assert ours.pairs == len(theirs.np_arrays["error_array"]) > 10


def test_rpe_and_ate_refuse_what_cannot_be_computed():
    ts = np.arange(5, dtype=float)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = ts
    a = Trajectory(ts, poses)
    far = Trajectory(ts + 100.0, poses)
    with pytest.raises(DataError, match=r"no poses of the two trajectories are within 0\.01 s"):
        ate(a, far)
    with pytest.raises(DataError, match="unknown alignment 'affine'"):
        ate(a, a, "affine")  # type: ignore[arg-type]
    with pytest.raises(DataError, match="delta unit 'seconds'"):
        rpe(a, a, 1.0, "seconds")  # type: ignore[arg-type]
    with pytest.raises(DataError, match="empty index list"):
        rpe(a, a, 50.0, "meters")
    assert ate(a, a, "none").rmse == 0.0
    two = Trajectory(ts[:2], poses[:2])
    with pytest.raises(DataError, match="at least 3 associated poses"):
        ate(two, two, "se3")


def test_sgf_eval_cli_writes_json(shared_data: Path, tmp_path: Path):
    evo = shared_data / "evo"
    out = tmp_path / "eval"
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "sgf-eval"),
            f"reference={evo / 'KITTI_00_gt.txt'}",
            f"estimate={evo / 'KITTI_00_ORB.txt'}",
            "align=sim3",
            "rpe.delta=10",
            f"hydra.run.dir={out}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "ATE (m)" in proc.stdout and "0.937709" in proc.stdout
    report = json.loads((out / "eval.json").read_text())
    assert report["ate"]["rmse"] == pytest.approx(0.937709, abs=1e-6)
    assert report["ate"]["pairs"] == 4541
    expected = rpe(_read(evo / "KITTI_00_gt.txt"), _read(evo / "KITTI_00_ORB.txt"), 10, "frames", "rotation", "sim3")
    assert report["rpe_rotation"]["rmse"] == pytest.approx(expected.rmse, rel=1e-12)
    assert report["units"] == {"ate": "m", "rpe_translation": "m", "rpe_rotation": "deg"}
    assert not any(p.name.startswith(".") and p.suffix == ".part" for p in out.iterdir())


def test_sgf_eval_cli_names_a_bad_file(tmp_path: Path):
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n1 0 0 nan 0 0 0 1\n")
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "sgf-eval"),
            f"reference={bad}",
            f"estimate={bad}",
            f"hydra.run.dir={tmp_path / 'out'}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert (
        "reference:" in proc.stderr
        and "bad.tum:2: non-finite pose (NaN or inf) or zero-length quaternion on line(s) [2]" in proc.stderr
    )
