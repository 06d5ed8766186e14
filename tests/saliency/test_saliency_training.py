"""sgf-train: the train -> save -> load -> infer path on tiny data, checkpoint and resume, early stopping."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from sgf_plugins.saliency import procedural, training
from sgf_plugins.saliency.cli_sod_eval import bev_of
from sgf_plugins.saliency.cli_train import run as train_run
from sgf_plugins.saliency.data import SodFolder, SplitSpec, write_sod_folder
from sgf_plugins.saliency.stages import LdfParams, LdfSaliency, default_architecture
from sgf_plugins.saliency.training import DataOptions, TrainOptions, train_model
from sgf_plugins.saliency.training_set import SodTrainingSet
from sgf_plugins.saliency.weights import read_weights

from sgf_pipeline.cache import file_hash
from sgf_pipeline.config import config_dir
from sgf_pipeline.errors import ConfigError, DataError

QUICK = {"batch_size": 4, "warmup_steps": 2, "progress": False, "threads": 1, "lr": 2e-3}


def _compose(overrides: list[str]) -> dict:
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("sgf_train", overrides=overrides)
    raw = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(raw, dict)
    return raw


def test_train_save_load_infer(toy_folder: Path, tmp_path: Path) -> None:
    cfg = _compose(
        [
            "saliency=ldf",
            f"data.root={toy_folder}",
            "train.epochs=2",
            "train.batch_size=4",
            "train.warmup_steps=2",
            "train.progress=false",
            "train.threads=1",
            "saliency.input_size=64",
            f"train.export_to={tmp_path / 'shipped'}",
        ]
    )
    card = train_run(cfg, tmp_path / "run", "sgf-train saliency=ldf ...")
    weights = tmp_path / "run" / "ldf.safetensors"
    for name in ("ldf.safetensors", "ldf.json", "ldf.md", "best.safetensors", "checkpoint.safetensors"):
        assert (tmp_path / "run" / name).is_file(), name
    assert (tmp_path / "shipped" / "ldf.safetensors").read_bytes() == weights.read_bytes()
    written = json.loads((tmp_path / "run" / "ldf.json").read_text())
    assert written == json.loads(json.dumps(card))
    assert card["architecture"] == default_architecture("ldf") and card["input_size"] == 64
    assert card["command"] == "sgf-train saliency=ldf ..."
    assert card["data"]["splits_from"] == "splits.json" and card["data"]["sizes"]["test_heldout"] > 0
    assert card["training"]["epochs_run"] == 2 and card["training"]["images_per_second"] > 0
    assert len(card["training"]["history"]) == 2 and all("val" in h for h in card["training"]["history"])
    assert set(card["metrics"]) == {"val", "test", "test_heldout"}
    assert 0.0 <= card["metrics"]["test"]["mae"] <= 1.0
    # half-precision storage of the large tensors only
    tensors, meta = read_weights(weights)
    assert meta["model"] == "ldf" and json.loads(meta["architecture"]) == default_architecture("ldf")
    assert {str(t.dtype) for t in tensors.values() if t.is_floating_point()} == {"torch.float16", "torch.float32"}
    assert all(str(t.dtype) == "torch.float32" for k, t in tensors.items() if "running_" in k)
    # the stage loads them and gives the same map as the full-precision best weights, within float16 rounding
    rgb, _, meta_s = procedural.sample(np.random.default_rng(3), 64)
    bev = bev_of(rgb, meta_s["valid"], 0.02, 0)
    half = LdfSaliency(LdfParams(weights=str(weights), input_size=64)).process(bev).probability
    full = (
        LdfSaliency(LdfParams(weights=str(tmp_path / "run" / "best.safetensors"), input_size=64))
        .process(bev)
        .probability
    )
    assert half.shape == (64, 64) and half.dtype == np.float32
    assert np.abs(half - full).max() < 2e-2
    assert half[~meta_s["valid"]].max() == 0.0


def test_resume_continues_exactly(toy_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    arch = default_architecture("u2net")
    opts = TrainOptions(epochs=2, input_size=32, **QUICK)
    data = DataOptions(root=str(toy_folder), max_train=8, max_val=4)
    straight = train_model("u2net", arch, 32, data, opts, tmp_path / "straight")

    real_save = training.save_checkpoint
    calls = []

    def crash_after_first_epoch(*args, **kwargs):
        real_save(*args, **kwargs)
        calls.append(1)
        raise KeyboardInterrupt  # the run dies right after its first checkpoint

    monkeypatch.setattr(training, "save_checkpoint", crash_after_first_epoch)
    with pytest.raises(KeyboardInterrupt):
        train_model("u2net", arch, 32, data, opts, tmp_path / "first")
    monkeypatch.setattr(training, "save_checkpoint", real_save)
    resumed = train_model(
        "u2net", arch, 32, data, opts.model_copy(update={"resume": str(tmp_path / "first")}), tmp_path / "second"
    )
    assert calls == [1]
    assert resumed["training"]["epochs_run"] == 2 and len(resumed["training"]["history"]) == 2
    a, _ = read_weights(tmp_path / "straight" / "best.safetensors")
    b, _ = read_weights(tmp_path / "second" / "best.safetensors")
    assert all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)
    assert resumed["metrics"] == straight["metrics"]
    with pytest.raises(DataError, match="checkpoint is u2net"):
        train_model(
            "u2netp",
            default_architecture("u2netp"),
            32,
            data,
            opts.model_copy(update={"resume": str(tmp_path / "first")}),
            tmp_path / "x",
        )


def test_early_stopping(tmp_path: Path) -> None:
    # nothing is salient anywhere: val maxF stays 0, so it never improves after the first epoch
    write_sod_folder(
        procedural.samples(10, seed=0, size=32, max_markings=0), tmp_path / "blank", SplitSpec(val_fraction=0.3)
    )
    opts = TrainOptions(epochs=6, input_size=32, monitor="maxF", patience=2, **QUICK)
    card = train_model(
        "ldf", default_architecture("ldf"), 32, DataOptions(root=str(tmp_path / "blank")), opts, tmp_path / "r"
    )
    assert card["training"]["stopped_early"] is True
    assert card["training"]["epochs_run"] == 3 and card["training"]["best_epoch"] == 1


def test_config_errors(toy_folder: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="classical"):
        train_run(_compose(["saliency=classical", f"data.root={toy_folder}"]), tmp_path, "")
    with pytest.raises(ConfigError, match=r"train\.epochs"):
        train_run(_compose([f"data.root={toy_folder}", "train.epochs=0"]), tmp_path, "")
    with pytest.raises(ConfigError, match="divisible by 32"):
        train_run(_compose([f"data.root={toy_folder}", "train.input_size=48", "train.progress=false"]), tmp_path, "")
    with pytest.raises(DataError, match="images/ and masks/"):
        train_run(_compose([f"data.root={tmp_path}"]), tmp_path, "")


def test_crops_and_fine_tuning_from_weights(toy_folder: Path, tmp_path: Path) -> None:
    arch = default_architecture("ldf")
    data = DataOptions(root=str(toy_folder), max_train=8, max_val=4)
    # crops: full-resolution windows of the input, the validation on whole images
    crops = SodTrainingSet(SodFolder(str(toy_folder)), data_names(toy_folder)[:4], 64, None, 0, None, 32, 1.0)
    x, targets = crops[0]
    assert x.shape == (3, 32, 32) and targets["mask"].shape == (1, 32, 32) and float(targets["mask"].sum()) > 0
    opts = TrainOptions(epochs=1, input_size=64, crop=32, hue=0.5, **QUICK)
    first = train_model("ldf", arch, 64, data, opts, tmp_path / "first")
    assert first["training"]["options"]["crop"] == 32 and first["training"]["init_weights_sha256"] is None
    # fine-tuning starts from the given weights: at a learning rate of 1e-12 they stay as they were
    start = tmp_path / "first" / "best.safetensors"
    tuned = train_model(
        "ldf", arch, 64, data, opts.model_copy(update={"init_weights": str(start), "lr": 1e-12}), tmp_path / "tuned"
    )
    assert tuned["training"]["init_weights_sha256"] == file_hash(start)
    # the card keeps the first run's record: its command, epochs and history
    init = tuned["training"]["init_from"]
    assert init["epochs_run"] == 1 and init["options"]["crop"] == 32 and len(init["history"]) == 1
    assert "- fine-tuned from: `` (1 epochs at input 64" in (tmp_path / "tuned" / "ldf.md").read_text()
    a, _ = read_weights(start)
    b, _ = read_weights(tmp_path / "tuned" / "best.safetensors")
    learned = [k for k in a if a[k].is_floating_point() and "running" not in k]  # batch-norm statistics move
    assert len(learned) > 20 and max(float((a[k] - b[k]).abs().max()) for k in learned) < 1e-6
    # weights of a run that did not finish (no card beside them): its checkpoint keeps the record
    (tmp_path / "first" / "ldf.json").unlink()
    again = train_model(
        "ldf", arch, 64, data, opts.model_copy(update={"init_weights": str(start), "lr": 1e-12}), tmp_path / "again"
    )
    init = again["training"]["init_from"]
    assert init["epochs_run"] == 1 and init["input_size"] == 64 and len(init["history"]) == 1
    assert "did not finish" in init["note"]
    (tmp_path / "first" / "checkpoint.json").unlink()
    lost = train_model(
        "ldf", arch, 64, data, opts.model_copy(update={"init_weights": str(start), "lr": 1e-12}), tmp_path / "lost"
    )
    assert lost["training"]["init_from"]["card"] is None
    assert "without a readable model card" in (tmp_path / "lost" / "ldf.md").read_text()
    with pytest.raises(DataError, match="not found"):
        train_model(
            "ldf",
            arch,
            64,
            data,
            opts.model_copy(update={"init_weights": str(tmp_path / "none.safetensors")}),
            tmp_path / "x",
        )
    with pytest.raises(ConfigError, match="exclude each other"):
        train_model(
            "ldf",
            arch,
            64,
            data,
            opts.model_copy(update={"init_weights": str(start), "resume": str(tmp_path / "first")}),
            tmp_path / "y",
        )
    with pytest.raises(ConfigError, match="larger than the input size"):
        train_model("ldf", arch, 64, data, opts.model_copy(update={"crop": 96}), tmp_path / "z")


def data_names(root: Path) -> list[str]:
    """The training names of a SOD folder whose masks hold a salient pixel."""
    folder = SodFolder(str(root))
    return [n for n in folder.splits()["train"] if folder.mask(n).max() > 128]
