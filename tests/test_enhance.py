"""enhance=none (identity) and enhance=clahe (contrast of dark night images, paper Sec. IV-C)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from ipm_scene import GroundScene, render, scene_calibration
from pydantic import ValidationError
from sgf_plugins.ipm.enhance import ClaheEnhancement, ClaheParams, NoEnhancement, as_rgb
from sgf_testing import conf_node

from sgf_pipeline import DataError, StageParams, load_plugins
from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.types import CameraImage, Frame

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = Calibration.from_mounting(Intrinsics(fx=300, fy=300, cx=159.5, cy=119.5, width=320, height=240), 1.0, 0.3)


def _frame(image: np.ndarray) -> Frame:
    return Frame(7, 0.7, image, np.eye(4), CALIBRATION)


@pytest.fixture(scope="module")
def night() -> tuple[np.ndarray, np.ndarray]:
    """The test ground scene at night: 10 % of the day's light plus sensor noise, and its marking mask."""
    image, ids = render(GroundScene(), scene_calibration(320, 240), 0.0)
    rng = np.random.default_rng(1)
    dark = image.astype(float) * 0.1 + rng.normal(0.0, 0.8, image.shape[:2])[:, :, None]
    dark[:, :, 2] *= 0.9  # the LED's warm tint
    return np.clip(dark, 0, 255).astype(np.uint8), ids


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float64)


def _local_contrast(grey: np.ndarray, mask: np.ndarray) -> float:
    return float(np.abs(cv2.Laplacian(cv2.GaussianBlur(grey, (0, 0), 1.0), cv2.CV_64F))[mask].mean())


def test_none_is_the_identity(night) -> None:
    image, _ = night
    out = NoEnhancement(StageParams()).process(_frame(image))
    assert isinstance(out, CameraImage) and out.frame_index == 7
    assert np.array_equal(out.pixels, image)
    grey = image[:, :, 0]
    assert np.array_equal(NoEnhancement(StageParams()).process(_frame(grey)).pixels, np.repeat(grey[:, :, None], 3, 2))


def test_clahe_raises_the_contrast_of_a_dark_image(night) -> None:
    image, ids = night
    ground = np.zeros(ids.shape, dtype=bool)
    ground[70:] = True  # below the horizon
    paint, asphalt = (ids > 0) & ground, (ids == 0) & ground
    before = _grey(image)
    gains = {}
    for clip in (2.0, 4.0):
        out = ClaheEnhancement(ClaheParams(clip_limit=clip)).process(_frame(image)).pixels
        assert out.shape == image.shape and out.dtype == np.uint8
        after = _grey(out)
        gains[clip] = (
            (after[paint].mean() - after[asphalt].mean()) / (before[paint].mean() - before[asphalt].mean()),
            _local_contrast(after, ground) / _local_contrast(before, ground),
            after.mean() / before.mean(),
        )
        print(
            f"clip {clip}: marking contrast x{gains[clip][0]:.2f}, local contrast x{gains[clip][1]:.2f}, "
            f"brightness x{gains[clip][2]:.2f}"
        )
    marking, local, brightness = gains[2.0]
    assert marking > 1.3 and local > 1.5 and brightness > 1.5
    assert all(strong > weak for strong, weak in zip(gains[4.0], gains[2.0], strict=True))


def test_clahe_tiles_change_the_result(night) -> None:
    image, _ = night
    coarse = ClaheEnhancement(ClaheParams(tiles=2)).process(_frame(image)).pixels
    fine = ClaheEnhancement(ClaheParams(tiles=16)).process(_frame(image)).pixels
    assert np.abs(coarse.astype(int) - fine.astype(int)).mean() > 1.0


def test_clahe_keeps_grey_images_grey_and_leaves_hue(night) -> None:
    image, _ = night
    grey = ClaheEnhancement(ClaheParams()).process(_frame(image[:, :, 0])).pixels
    assert grey.shape == (240, 320, 3)
    assert np.array_equal(grey[:, :, 0], grey[:, :, 1]) and np.array_equal(grey[:, :, 1], grey[:, :, 2])
    colour = ClaheEnhancement(ClaheParams()).process(_frame(image)).pixels.astype(int)
    assert colour[:, :, 2].mean() < colour[:, :, 0].mean()  # the warm tint survives


def test_bad_input_and_parameters() -> None:
    with pytest.raises(DataError, match=r"expected an \(H, W\) or \(H, W, 3\) image"):
        as_rgb(np.zeros((4, 4, 4), np.uint8))
    for stage in (NoEnhancement(StageParams()), ClaheEnhancement(ClaheParams())):
        with pytest.raises(DataError, match="must be uint8"):
            stage.process(_frame(np.zeros((240, 320), np.uint16)))
    with pytest.raises(ValidationError):
        ClaheParams(clip_limit=0.0)
    with pytest.raises(ValidationError):
        ClaheParams(tiles=0)


def test_registered_and_configured() -> None:
    registry = load_plugins(allow=["enhance"]).registry
    assert {v.name for v in registry.variants("enhance")} == {"none", "clahe"}
    node = conf_node("enhance/auto")  # the default: CLAHE on dark frames only
    assert node.pop("name") == "clahe"
    assert node == ClaheParams(max_brightness=0.3).model_dump()


def test_clahe_max_brightness_enhances_night_frames_only(night) -> None:
    image, _ = night
    day, _ = render(GroundScene(), scene_calibration(320, 240), 0.0)
    stage = ClaheEnhancement(ClaheParams(max_brightness=0.3))
    assert day.mean() / 255.0 > 0.3 > image.mean() / 255.0
    assert np.array_equal(stage.process(_frame(day)).pixels, day)
    always = ClaheEnhancement(ClaheParams()).process(_frame(image)).pixels
    assert np.array_equal(stage.process(_frame(image)).pixels, always)
    assert not np.array_equal(always, image)
