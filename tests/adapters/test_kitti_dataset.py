"""dataset=kitti on six real KITTI 00 frames: intrinsics, timestamps, images and base poses."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from sgf_plugins.datasets.kitti import KittiDataset, KittiParams

from sgf_pipeline import Pipeline
from sgf_pipeline.config import config_dir
from sgf_pipeline.context import RunContext
from sgf_pipeline.geometry import invert
from sgf_pipeline.trajectory import read_kitti

from .test_calibration_io import KITTI_CALIB

INTRINSICS = {"fx": 718.856, "fy": 718.856, "cx": 607.1928, "cy": 185.2157}


def _params(root: Path, **extra: object) -> KittiParams:
    return KittiParams.model_validate(
        {
            "path": str(root),
            "poses": str(root / "poses_00_first6.txt"),
            "times": str(root / "times_00_first6.txt"),
            "intrinsics": INTRINSICS,
            **extra,
        }
    )


def test_six_frames_with_intrinsics_times_and_poses(shared_data: Path):
    root = shared_data / "kitti00_first6"
    dataset = KittiDataset(_params(root))
    context = RunContext(run_dir=None)
    dataset.begin(context)
    calib = context.calibration
    assert calib is not None
    intr = calib.intrinsics
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (
        718.856,
        718.856,
        607.1928,
        185.2157,
        1241,
        376,
    )
    assert calib.height == pytest.approx(1.65) and calib.tilt == pytest.approx(0.0)
    assert context.sequence == "kitti00_first6" and context.rate_hz == pytest.approx(9.64, abs=0.01)
    frames = list(dataset.frames())
    assert len(dataset) == len(frames) == 6
    assert [f.index for f in frames] == list(range(6))
    times = [0.0, 0.1037359, 0.2073381, 0.3110752, 0.4146917, 0.5184302]
    assert [f.timestamp for f in frames] == pytest.approx(times, abs=1e-12)
    camera_poses = read_kitti(root / "poses_00_first6.txt").poses
    c = calib.camera_to_base_matrix
    for f, cam in zip(frames, camera_poses, strict=True):
        assert not f.image_loaded  # decoded only when asked for
        expected = cv2.imread(str(root / "image_0" / f"{f.index:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert f.image.shape == (376, 1241) and np.array_equal(f.image, expected)
        np.testing.assert_allclose(invert(c) @ f.ground_truth @ c, cam, atol=1e-12)  # back to KITTI's camera poses
        np.testing.assert_array_equal(f.odometry, f.ground_truth)  # no odometry file: the poses themselves
    # the camera moved forward along its z (0.86 m per frame): the base moves along its x, stays on the ground
    forward = [f.ground_truth[0, 3] for f in frames]
    assert forward == pytest.approx([0.0, 0.8606, 1.7201, 2.5807, 3.4403, 4.3009], abs=2e-4)
    assert all(abs(f.ground_truth[2, 3]) < 0.15 for f in frames)
    assert frames[5].ground_truth[2, 2] == pytest.approx(1.0, abs=1e-4)  # z stays up


def test_kitti_layout_with_calib_txt_and_default_paths(tmp_path: Path, shared_data: Path):
    """The real KITTI layout: sequences/00/{image_0, calib.txt, times.txt} and poses/00.txt."""
    src = shared_data / "kitti00_first6"
    seq = tmp_path / "dataset" / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    for image in sorted((src / "image_0").glob("*.png")):
        (seq / "image_0" / image.name).symlink_to(image)
    (seq / "calib.txt").write_text(KITTI_CALIB)
    (seq / "times.txt").write_text((src / "times_00_first6.txt").read_text())
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / "00.txt").write_text((src / "poses_00_first6.txt").read_text())
    odometry = tmp_path / "vo.txt"  # an estimated trajectory: the poses shifted 1 m along the camera's x
    rows = [np.array(line.split(), dtype=float) for line in (src / "poses_00_first6.txt").read_text().splitlines()]
    odometry.write_text("".join(" ".join(map(str, r + np.array([0, 0, 0, 1.0] + [0] * 8))) + "\n" for r in rows))

    dataset = KittiDataset(KittiParams(path=str(seq), odometry=str(odometry)))
    frames = list(dataset.frames())
    assert len(frames) == 6
    assert frames[0].calibration.intrinsics.cx == 607.1928
    for f in frames:  # the camera's +x (right) is the base's -y
        np.testing.assert_allclose(f.odometry[:3, 3] - f.ground_truth[:3, 3], [0.0, -1.0, 0.0], atol=1e-12)


def test_kitti_through_hydra_overrides(shared_data: Path, tmp_path: Path):
    root = shared_data / "kitti00_first6"
    overrides = [
        "dataset=kitti",
        f"dataset.path={root}",
        f"dataset.poses={root / 'poses_00_first6.txt'}",
        f"dataset.times={root / 'times_00_first6.txt'}",
        "dataset.intrinsics={fx:718.856,fy:718.856,cx:607.1928,cy:185.2157}",
        "pipeline=[dataset,enhance]",
        "run.progress=false",
        "run.plots=false",
    ]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    metrics = Pipeline.from_config(cfg, run_dir=tmp_path / "run").run()
    assert metrics["dataset"]["frames"] == 6
    assert metrics["ate_rmse_m"]["odometry"] == pytest.approx(0.0, abs=1e-9)
    assert (tmp_path / "run" / "trajectory_gt.tum").is_file()
    assert sorted(p.name for p in root.iterdir()) == [
        "LICENSE.slambook2-MIT.txt",
        "SOURCE.txt",
        "disparity_000000.png",
        "image_0",
        "image_1",
        "poses_00_first6.txt",
        "times_00_first6.txt",
    ]


def test_metrics_name_the_recorded_sequence(shared_data: Path, tmp_path: Path):
    root = shared_data / "kitti00_first6"
    overrides = [
        "dataset=kitti",
        f"dataset.path={root}",
        f"dataset.poses={root / 'poses_00_first6.txt'}",
        f"dataset.times={root / 'times_00_first6.txt'}",
        "dataset.intrinsics={fx:718.856,fy:718.856,cx:607.1928,cy:185.2157}",
        "dataset.sequence=kitti_00_start",
        "pipeline=[dataset,enhance]",
        "run.progress=false",
        "run.plots=false",
    ]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    metrics = Pipeline.from_config(cfg, run_dir=tmp_path / "run").run()
    assert metrics["sequence"] == "kitti_00_start"
    assert metrics["stages"]["dataset"] == "kitti"
