"""The SGF figure observer: selected SGFs and their groups drawn at the end of a run (Fig. 4 and 5)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from test_sgf_pipeline import TestPlugin, config, recorded  # noqa: F401  (recorded is a fixture)

from sgf_pipeline import Pipeline, load_plugins


def test_figures_of_selected_sgfs_and_groups(recorded, tmp_path: Path):  # noqa: F811
    plugins = load_plugins(extra=[("sgf_test_stream", TestPlugin())])
    run_dir = tmp_path / "run"
    Pipeline.from_config(config(run_dir_plots=True), run_dir=run_dir, plugins=plugins).run()
    frames = cv2.imread(str(run_dir / "sgf_frames.png"))
    groups = cv2.imread(str(run_dir / "sgf_groups.png"))
    assert frames is not None and groups is not None
    # 14 selected SGFs -> 6 columns x 3 rows of tiles; 7 groups of 2 -> 6 rows of 2 members.
    assert frames.shape[1] > frames.shape[0] and groups.shape[0] > groups.shape[1]
    # The outlines are drawn in saturated group colours, which the grey synthetic BEVs do not have.
    hsv = cv2.cvtColor(frames, cv2.COLOR_BGR2HSV)
    assert np.count_nonzero(hsv[:, :, 1] > 150) > 500
    # the run's report shows them under the trajectories, once each
    report = (run_dir / "report.md").read_text()
    assert report.count("![sgf_frames](sgf_frames.png)") == 1 and report.count("![sgf_groups](sgf_groups.png)") == 1
    assert report.index("![trajectories](trajectory.png)") < report.index("## Figures") < report.index("sgf_frames.png")


def test_no_figures_without_plots(recorded, tmp_path: Path):  # noqa: F811
    plugins = load_plugins(extra=[("sgf_test_stream", TestPlugin())])
    run_dir = tmp_path / "run"
    Pipeline.from_config(config(run_dir_plots=False), run_dir=run_dir, plugins=plugins).run()
    assert not (run_dir / "sgf_frames.png").exists()
