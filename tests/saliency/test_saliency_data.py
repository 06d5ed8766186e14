"""The SOD folder format, its splits, the generation interface and the training augmentation."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from sgf_plugins.saliency import procedural
from sgf_plugins.saliency.augment import Augmentation, rotate_hue, salient_crop
from sgf_plugins.saliency.data import SodFolder, SplitSpec, make_splits, write_sod_folder
from sgf_plugins.saliency.preprocess import normalize_image, resize_mask
from sgf_plugins.saliency.synthetic_data import samples_from_bevs

from sgf_pipeline.errors import DataError
from sgf_pipeline.truth import MarkingPass, MarkingTruth, SequenceTruth
from sgf_pipeline.types import Bev, BevGrid


def test_written_folder_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    mask = np.zeros((20, 30), bool)
    mask[5:10, 5:25] = True
    valid = np.ones((20, 30), bool)
    valid[:, :3] = False
    samples = [
        (rgb, mask, {"name": "a", "designs": ["arrow"], "valid": valid, "pass": np.int64(3)}),
        (rgb, mask.astype(np.float32) * 0.5, {"name": "b"}),
        (rgb, mask.astype(np.uint16) * 7, {}),  # instance ids
    ]
    report = write_sod_folder(samples, tmp_path / "sod", split=None)
    assert report.count == 3 and report.splits == {}
    folder = SodFolder(tmp_path / "sod")
    assert folder.names == ["000002", "a", "b"]
    assert np.array_equal(folder.image("a"), rgb)  # PNG is lossless, RGB order kept
    assert folder.mask("a").max() == 255 and np.array_equal(folder.mask("a") > 128, mask)
    assert folder.mask("b").max() == 128  # soft masks keep their level
    assert np.array_equal(folder.mask("000002") == 255, mask)
    assert np.array_equal(folder.valid("a"), valid) and folder.valid("b") is None
    assert folder.meta("a") == {"name": "a", "designs": ["arrow"], "pass": 3}
    assert folder.splits() is None
    with pytest.raises(ValueError, match="duplicate"):
        write_sod_folder([(rgb, mask, {"name": "x"})] * 2, tmp_path / "dup", split=None)
    with pytest.raises(ValueError, match="shape"):
        write_sod_folder([(rgb, mask[:5], {})], tmp_path / "bad", split=None)


def test_duts_style_folder_needs_images_and_masks(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match="images/ and masks/"):
        SodFolder(tmp_path)
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "x.jpg"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DataError, match="no image"):
        SodFolder(tmp_path)
    cv2.imwrite(str(tmp_path / "masks" / "x.png"), np.zeros((4, 4), np.uint8))
    folder = SodFolder(tmp_path)
    assert folder.names == ["x"] and folder.split("all") == ["x"]


def test_splits_are_seeded_disjoint_and_hold_out_designs() -> None:
    names = [f"{i:03d}" for i in range(100)]
    metas = {n: {"designs": ["glyph"] if i % 10 == 0 else ["arrow"], "pass": i // 4} for i, n in enumerate(names)}
    spec = SplitSpec(seed=3, val_fraction=0.1, test_fraction=0.2, heldout_designs=("glyph",))
    splits = make_splits(names, metas, spec)
    assert splits == make_splits(list(reversed(names)), metas, spec)  # independent of the order given
    assert splits != make_splits(names, metas, SplitSpec(seed=4, val_fraction=0.1, test_fraction=0.2))
    assert sorted(n for members in splits.values() for n in members) == names  # a partition
    assert splits["test_heldout"] == [n for i, n in enumerate(names) if i % 10 == 0]
    assert (len(splits["test"]), len(splits["val"]), len(splits["train"])) == (18, 9, 63)
    grouped = make_splits(names, metas, SplitSpec(seed=3, val_fraction=0.1, test_fraction=0.2, group_key="pass"))
    for split, members in grouped.items():
        for other, rest in grouped.items():
            if other != split:
                assert not {metas[n]["pass"] for n in members} & {metas[n]["pass"] for n in rest}, (split, other)
    with pytest.raises(ValueError, match="train set"):
        make_splits(names, metas, SplitSpec(val_fraction=0.5, test_fraction=0.5))


def test_generation_interface_writes_splits(tmp_path: Path) -> None:
    spec = SplitSpec(seed=1, val_fraction=0.25, test_fraction=0.25, heldout_designs=("ring",))
    report = write_sod_folder(procedural.samples(16, seed=2, size=32), tmp_path / "sod", spec)
    folder = SodFolder(tmp_path / "sod")
    saved = json.loads((tmp_path / "sod" / "splits.json").read_text())
    assert saved["spec"]["heldout_designs"] == ["ring"] and folder.splits() == report.splits
    for name in folder.split("test_heldout"):
        assert "ring" in folder.meta(name)["designs"]
    for name in folder.split("train"):
        assert "ring" not in folder.meta(name)["designs"]
    assert all(folder.valid(n) is not None for n in folder.names)


def test_augmentation_is_reproducible_and_keeps_masks_aligned() -> None:
    mask = np.zeros((64, 64), np.float32)
    mask[20:40, 10:50] = 1.0
    rgb = np.repeat((mask * 255).astype(np.uint8)[:, :, None], 3, axis=2)
    aug = Augmentation(
        brightness=0, contrast=0, saturation=0, gamma=0, noise=0, blur_probability=0, shadow_probability=0
    )
    for seed in range(5):
        img_a, m_a = aug(rgb, mask, np.random.default_rng(seed))
        img_b, m_b = aug(rgb, mask, np.random.default_rng(seed))
        assert np.array_equal(img_a, img_b) and np.array_equal(m_a, m_b)
        assert np.abs(img_a[:, :, 0] / 255.0 - m_a).max() < 0.01  # geometry applied identically
        assert m_a.sum() > 0.3 * mask.sum()  # the zoom keeps the shape in view
    img, m = Augmentation()(rgb, mask, np.random.default_rng(0))
    assert img.shape == rgb.shape and img.dtype == np.uint8 and m.dtype == np.float32
    assert m.min() >= 0.0 and m.max() <= 1.0


def test_hue_rotation_turns_paint_colours_and_keeps_grey() -> None:
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[:, :2] = (255, 0, 0)  # red paint
    rgb[:, 2:4] = (0, 200, 0)  # green paint
    rgb[:, 4:] = (90, 90, 90)  # grey ground
    turned = rotate_hue(rgb, 120.0)
    assert tuple(turned[0, 0]) == (0, 255, 0)  # red -> green
    assert tuple(turned[0, 2]) == (0, 0, 200)  # green -> blue
    assert tuple(turned[0, 4]) == (90, 90, 90)  # no hue, no change
    assert np.array_equal(rotate_hue(rgb, 360.0), rgb)
    big = np.zeros((40, 60, 3), np.uint8)
    big[:, :30] = (255, 0, 0)
    big[:, 30:] = (90, 90, 90)
    always = Augmentation(brightness=0, contrast=0, saturation=0, gamma=0, noise=0, blur_probability=0,
                          shadow_probability=0, hue_probability=1.0)  # fmt: skip
    hues = set()
    for seed in range(20):
        img, _ = always(big, np.zeros((40, 60), np.float32), np.random.default_rng(seed))
        spread = img.max(axis=2).astype(int) - img.min(axis=2)
        paint = spread > 200
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
        hues.add(int(np.median(hsv[..., 0][paint])) // 10)
    assert len(hues) >= 8  # the red paint came out in many colours


def test_salient_crop_holds_a_marking_at_full_resolution() -> None:
    rng = np.random.default_rng(0)
    mask = np.zeros((256, 256), np.float32)
    mask[200:210, 30:40] = 1.0
    rgb = np.zeros((256, 256, 3), np.uint8)
    rgb[..., 0] = np.arange(256)[:, None]  # rows and columns encoded in the image
    rgb[..., 1] = np.arange(256)[None, :]
    held = 0
    for _ in range(50):
        img, m = salient_crop(rgb, mask, 64, 1.0, rng)
        assert img.shape == (64, 64, 3) and m.shape == (64, 64)
        y0, x0 = int(img[0, 0, 0]), int(img[0, 0, 1])  # where the window lies
        assert np.array_equal(m, mask[y0 : y0 + 64, x0 : x0 + 64])  # image and mask cut alike, not resized
        held += m.sum() > 0
    assert held == 50
    anywhere = [salient_crop(rgb, mask, 64, 0.0, rng)[1].sum() > 0 for _ in range(200)]
    assert 0 < sum(anywhere) < 100  # uniform windows rarely meet the small marking
    blank = np.zeros_like(mask)
    assert salient_crop(rgb, blank, 64, 1.0, rng)[1].sum() == 0
    with pytest.raises(ValueError, match="does not fit"):
        salient_crop(rgb, mask, 512, 1.0, rng)


def test_network_input_normalisation() -> None:
    rgb = np.full((10, 20, 3), 255, np.uint8)
    x = normalize_image(rgb, 8)
    assert x.shape == (3, 8, 8) and x.dtype == np.float32
    assert x[0, 0, 0] == pytest.approx((1 - 0.485) / 0.229)
    m = resize_mask(np.full((16, 16), 255, np.uint8), 8)
    assert m.shape == (8, 8) and m.max() == 1.0


def test_samples_from_synthetic_bevs(tmp_path: Path) -> None:
    grid = BevGrid(0.02, 0.0, 0.64, -0.32, 0.32)
    truth = SequenceTruth(
        markings={
            1: MarkingTruth(1, "arrow_left", "standard", False, (0, 0, 0), (1, 0.3)),
            2: MarkingTruth(2, "campus_logo", "custom", False, (5, 0, 0), (1, 1)),
        },
        passes=[MarkingPass(1, 0, 0, 1, 0.0), MarkingPass(2, 0, 2, 2, 0.0)],
    )
    bevs = []
    for frame in range(4):
        ids = np.zeros((32, 32), np.uint16)
        if frame < 2:
            ids[5:15, 5:15] = 1
        elif frame == 2:
            ids[10:20, 10:30] = 2
            ids[0:2, 0:5] = 1  # 10 pixels: too few to count as in view
        image = np.full((32, 32, 3), 90, np.uint8)
        bevs.append(Bev(image, np.ones((32, 32), bool), grid, frame, 0.1 * frame, instance_ids=ids))
    bevs.append(Bev(image, np.ones((32, 32), bool), grid, 9, 0.9))  # no instance ids: skipped
    samples = list(samples_from_bevs(bevs, truth, "campus_delivery"))
    assert [s[2]["frame"] for s in samples] == [0, 1, 2, 3]
    assert samples[0][2]["designs"] == ["arrow_left"] and samples[0][2]["group"] == "campus_delivery:1:0"
    assert samples[1][2]["group"] == samples[0][2]["group"]  # one pass, one group
    assert samples[2][2]["designs"] == ["campus_logo"] and samples[2][2]["categories"] == ["custom"]
    assert samples[2][1].sum() == 200 + 10  # the mask keeps every marking pixel
    assert samples[3][2]["designs"] == [] and samples[3][2]["group"] == "campus_delivery:blank:0"
    spec = SplitSpec(seed=0, val_fraction=0.25, test_fraction=0.0, heldout_designs=("campus_logo",), group_key="group")
    report = write_sod_folder(samples, tmp_path / "sod", spec)
    assert report.splits["test_heldout"] == ["campus_delivery_000002"]
    assert SodFolder(tmp_path / "sod").meta("campus_delivery_000000")["group"] == "campus_delivery:1:0"


def test_unknown_split_name(toy_folder: Path) -> None:
    folder = SodFolder(toy_folder)
    with pytest.raises(DataError, match="no split named 'holdout'"):
        folder.split("holdout")
    assert sorted(
        folder.split("train") + folder.split("val") + folder.split("test") + folder.split("test_heldout")
    ) == (folder.names)
