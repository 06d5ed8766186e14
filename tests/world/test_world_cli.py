import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from sgf_pipeline.folder_format import read_calibration_yaml, truth_from_dict
from sgf_pipeline.trajectory import read_tum


@pytest.mark.slow
def test_sgf_world_exports_a_folder_dataset_with_map_and_samples(tmp_path: Path):
    out = tmp_path / "world"
    cmd = [
        sys.executable,
        "-m",
        "sgf_plugins.world.cli",
        "dataset.scale=0.08",
        "max_frames=12",
        f"out={out}",
        "progress=false",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "campus_delivery" in done.stdout
    seq = out / "campus_delivery"
    meta = yaml.safe_load((seq / "sequence.yaml").read_text())
    assert meta["format"] == "sgf-folder" and meta["frames"] == 12 and meta["rate_hz"] == 10.0
    images = sorted((seq / "images").glob("*.png"))
    masks = sorted((seq / "masks").glob("*.png"))
    assert len(images) == 12 and len(masks) == 12
    first = cv2.imread(str(images[0]))
    assert first.shape == (480, 640, 3) and first.std() > 10
    assert cv2.imread(str(masks[0]), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert len(read_tum(seq / "odometry.tum")) == 12 and len(read_tum(seq / "groundtruth.tum")) == 12
    assert read_calibration_yaml(seq / "calibration.yaml").intrinsics.fx == 400.0
    truth = truth_from_dict(json.loads((seq / "truth.json").read_text()))
    assert truth.markings and all(p.end_frame < 12 for p in truth.passes)
    summary = json.loads((out / "world.json").read_text())
    assert summary["exported_frames"] == 12 and summary["frames"] > 12
    world_map = cv2.imread(str(out / "map.png"))
    assert world_map is not None and min(world_map.shape[:2]) > 500
    for name in ("day", "night", "speed_bump", "speed_bump_ahead", "day_ids"):
        sample = cv2.imread(str(out / "samples" / f"{name}.png"))
        assert sample is not None and sample.shape == (480, 640, 3)
    assert cv2.imread(str(out / "samples" / "night.png")).mean() < cv2.imread(str(out / "samples" / "day.png")).mean()
    # a second export into the same place is refused without overwrite=true
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 2 and "exists already" in again.stderr


def test_sgf_world_refuses_a_dataset_that_is_not_a_campus_preset(tmp_path: Path):
    from sgf_plugins.world.cli import WorldAppOptions, run_world_app

    from sgf_pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="campus presets only"):
        run_world_app(WorldAppOptions(), {"name": "folder"}, tmp_path)
