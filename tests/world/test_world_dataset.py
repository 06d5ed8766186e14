from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from sgf_plugins.world import PRESETS, WorldParams, build_world
from sgf_plugins.world.dataset import CampusDataset

from sgf_pipeline import ConfigError, Pipeline, load_plugins
from sgf_pipeline.config import config_dir
from sgf_pipeline.types import Frame

VARIANTS = ("campus_delivery", "campus_large_loop", "campus_reverse_slope", "campus_large_loop_night")


def test_the_presets_are_registered_dataset_variants():
    registry = load_plugins().registry
    names = {v.name for v in registry.variants("dataset")}
    assert set(VARIANTS) <= names
    for name in VARIANTS:
        variant = registry.get("dataset", name)
        assert issubclass(variant.cls, CampusDataset) and variant.cls.output == "frame"
        assert issubclass(variant.params_model, WorldParams)
        assert variant.params_model().night is PRESETS[name].night


def test_the_default_run_streams_the_campus_with_its_truth(tmp_path: Path):
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "dataset.scale=0.05",
                "run.max_frames=6",
                "run.keyframe_distance=0",
                "run.progress=false",
                "run.plots=false",
            ],
        )
    assert cfg.dataset.name == "campus_delivery"
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path / "run")
    metrics = pipeline.run()
    ctx = pipeline.context
    assert ctx.sequence == "campus_delivery" and ctx.rate_hz == 10.0
    assert ctx.calibration is not None and ctx.calibration.intrinsics.width == 640
    assert ctx.calibration.height == pytest.approx(0.6) and np.degrees(ctx.calibration.tilt) == pytest.approx(25.0)
    assert ctx.truth is not None and ctx.truth.markings
    assert metrics["timing"]["frames"] == 6
    assert (tmp_path / "run" / "trajectory_gt.tum").exists()


def test_frames_carry_everything_a_robot_and_an_evaluator_need():
    dataset = load_plugins().registry.get("dataset", "campus_delivery").cls(WorldParams(scale=0.1))
    assert len(dataset) == len(dataset.world) > 100
    frames = list(zip(range(3), dataset.frames(), strict=False))
    for k, frame in frames:
        assert isinstance(frame, Frame) and frame.index == k
        assert frame.timestamp == pytest.approx(0.1 * k)
        assert frame.odometry.shape == (4, 4) and frame.ground_truth.shape == (4, 4)
        assert len(frame.imu_roll_pitch) == 2
        assert frame.calibration is dataset.world.calibration
        assert frame.image.dtype == np.uint8 and frame.image.shape == (480, 640, 3)
        assert frame.truth_ids().dtype == np.int32


def test_camera_parameters_change_the_calibration_and_the_image():
    world = build_world(
        "campus_delivery", scale=0.1, width=320, height=240, fx=200.0, fy=200.0, camera_tilt_deg=20.0, camera_height=0.8
    )
    calib = world.calibration
    assert (calib.intrinsics.width, calib.intrinsics.height) == (320, 240)
    assert calib.intrinsics.cx == pytest.approx(159.5) and calib.height == pytest.approx(0.8)
    assert np.degrees(calib.tilt) == pytest.approx(20.0)
    image, ids = world.render(world.drive.poses[5])
    assert image.shape == (240, 320, 3) and ids.shape == (240, 320)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"scale": 0.0}, "scale"),
        ({"scale": 1.5}, "scale"),
        ({"exclude_designs": ["squiggle"]}, "unknown marking design or family 'squiggle'"),
        ({"speed_min": 2.0}, "speed_min"),
        ({"camera_tilt_deg": 90.0}, "camera_tilt_deg"),
        ({"bev_x_min": 6.0}, "bev_x_min"),
    ],
)
def test_bad_parameters_are_clear_errors(overrides, message):
    with pytest.raises(ConfigError, match=message):
        build_world("campus_delivery", **{"seed": 0, **overrides})


def test_unknown_preset_names_the_known_ones():
    with pytest.raises(ConfigError, match="campus_large_loop"):
        build_world("campus_loop")
