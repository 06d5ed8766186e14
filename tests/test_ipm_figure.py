"""The Fig. 10 picture: a folder-format sequence over a speed bump, plain IPM vs MC-IPM, by command and in a run."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from ipm_scene import GroundScene, render, scene_calibration
from sgf_plugins.ipm.figure import PANEL, RUN_FIGURE, figure_from_frames, main, read_sequence

from sgf_pipeline import Pipeline, load_plugins
from sgf_pipeline.folder_format import FolderDatasetWriter
from sgf_pipeline.geometry import pose_from_xyz_rpy

BUMP_PITCH = {10: -0.03, 11: -0.06, 12: 0.06, 13: 0.03}  # front wheels up, then down


def write_bump_sequence(root: Path, frames: int = 14) -> Path:
    """A short drive over a speed bump, written in the project's folder format."""
    scene, calibration = GroundScene(), scene_calibration()
    writer = FolderDatasetWriter(root, "ipm_speed_bump", calibration, rate_hz=10.0)
    for k in range(frames):
        pitch = BUMP_PITCH.get(k, 0.0)
        image, ids = render(scene, calibration, 0.1 * k, 0.0, pitch)
        odometry = pose_from_xyz_rpy(0.1 * k, 0.0, 0.0, 0.0, pitch, 0.0)
        writer.add(0.1 * k, image, odometry, imu_roll_pitch=(0.0, pitch), instance_ids=ids)
    return writer.close()


@pytest.fixture(scope="module")
def bump_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_bump_sequence(tmp_path_factory.mktemp("seq") / "bump")


def test_the_sequence_reader_returns_the_written_frames(bump_sequence: Path) -> None:
    frames = list(read_sequence(bump_sequence))
    assert len(frames) == 14
    assert frames[11].imu_roll_pitch == pytest.approx((0.0, -0.06))
    assert frames[3].image.shape == (480, 640, 3)
    assert frames[5].odometry[0, 3] == pytest.approx(0.5)


def test_the_figure_command_writes_camera_ipm_and_mc_ipm(bump_sequence: Path, tmp_path: Path) -> None:
    out = tmp_path / "fig10.png"
    assert main([str(bump_sequence), "--frame", "11", "--out", str(out)]) == 0
    figure = cv2.imread(str(out))
    assert figure is not None and figure.shape[0] == PANEL
    camera_width = round(640 * PANEL / 480)
    assert figure.shape[1] == camera_width + 6 + PANEL + 6 + PANEL
    plain = figure[30:, camera_width + 6 : camera_width + 6 + PANEL].astype(int)
    mc = figure[30:, -PANEL:].astype(int)
    assert np.abs(plain - mc).mean() > 10  # nose up by 3.4 deg: plain IPM stretches the ground


def test_the_figure_command_reports_bad_input(tmp_path: Path, capsys) -> None:
    assert main([str(tmp_path), "--frame", "0", "--out", str(tmp_path / "x.png")]) == 1
    assert "no images" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def _run_over_the_bump(sequence: Path, run_dir: Path, ipm: str, plots: bool = True) -> None:
    plugins = load_plugins(allow=["dataset_folder", "enhance", "ipm", "ipm_figure"])
    config = {
        "pipeline": ["dataset", "enhance", "ipm"],
        "dataset": {"name": "folder", "path": str(sequence)},
        "enhance": {"name": "none"},
        "ipm": {"name": ipm},
        "run": {"progress": False, "plots": plots},
    }
    Pipeline.from_config(config, run_dir=run_dir, plugins=plugins).run()


def test_a_run_with_mc_ipm_draws_the_frame_it_compensated_most(bump_sequence: Path, tmp_path: Path) -> None:
    _run_over_the_bump(bump_sequence, tmp_path / "mc", "mc")
    drawn = cv2.imread(str(tmp_path / "mc" / RUN_FIGURE))
    # frames 11 and 12 pitch by 0.06 rad either way, the most of the drive: the first of them is drawn
    expected = figure_from_frames(read_sequence(bump_sequence), 11)
    np.testing.assert_array_equal(cv2.cvtColor(drawn, cv2.COLOR_BGR2RGB), expected)
    assert not (figure_from_frames(read_sequence(bump_sequence), 10) == expected).all()
    assert "![ipm_comparison](ipm_comparison.png)" in (tmp_path / "mc" / "report.md").read_text()
    # plain IPM has nothing to compare, and a run without plots draws nothing
    _run_over_the_bump(bump_sequence, tmp_path / "plain", "plain")
    _run_over_the_bump(bump_sequence, tmp_path / "quiet", "mc", plots=False)
    assert not (tmp_path / "plain" / RUN_FIGURE).exists() and not (tmp_path / "quiet" / RUN_FIGURE).exists()
