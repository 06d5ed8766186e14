"""Training a saliency network on a SOD folder, on CPU: seeded, validated, checkpointed, resumable, early-stopped.

Every random choice derives from the seed (the shuffling of epoch ``e`` from ``seed + e``, the
augmentation of sample ``i`` in epoch ``e`` from ``(seed, e, i)``), so a resumed run continues
exactly as an uninterrupted one would. Checkpoints hold the network, the optimizer state and the
progress in safetensors and JSON, never pickle.
"""

from __future__ import annotations

import math
import platform
import shutil
import time
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from sgf_pipeline.cache import file_hash
from sgf_pipeline.errors import ConfigError, DataError
from sgf_pipeline.io import atomic_write_json, atomic_write_text
from sgf_plugins.saliency.augment import Augmentation
from sgf_plugins.saliency.checkpoint import BEST, load_checkpoint, save_checkpoint
from sgf_plugins.saliency.data import SodFolder, SplitSpec, make_splits
from sgf_plugins.saliency.model_card import cpu_name, init_provenance, model_card_markdown
from sgf_plugins.saliency.models import build_model
from sgf_plugins.saliency.training_set import SodTrainingSet, collate
from sgf_plugins.saliency.validation import evaluate_network
from sgf_plugins.saliency.weights import load_weights, save_weights


class DataOptions(BaseModel):
    """Which folder to train on and how to split it (config node ``data``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    root: str = Field(description="SOD folder (images/, masks/, optional splits.json and meta.jsonl)")
    description: str = Field("", description="what the folder holds (generator, world seed), for the model card")
    use_saved_splits: bool = Field(True, description="use the folder's splits.json when present")
    seed: int = Field(0, description="split seed when the splits are made here")
    val_fraction: float = Field(0.1, ge=0.0, lt=1.0, description="fraction of samples for validation")
    test_fraction: float = Field(0.1, ge=0.0, lt=1.0, description="fraction of samples for the test split")
    heldout_designs: list[str] = Field(default_factory=list, description="designs kept out of training entirely")
    group_key: str | None = Field(None, description="meta key whose samples stay in one split (e.g. a pass id)")
    max_train: int | None = Field(None, ge=1, description="use at most this many training samples")
    max_val: int | None = Field(None, ge=1, description="validate on at most this many samples")


class TrainOptions(BaseModel):
    """Optimisation, validation and output options (config node ``train``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    epochs: int = Field(40, ge=1, description="maximum number of epochs")
    max_steps: int | None = Field(None, ge=1, description="stop after this many optimizer steps in all")
    batch_size: int = Field(8, ge=1, description="images per step")
    lr: float = Field(1e-3, gt=0.0, description="peak learning rate (AdamW)")
    weight_decay: float = Field(1e-4, ge=0.0, description="AdamW weight decay")
    warmup_steps: int = Field(100, ge=0, description="linear warm-up steps before the cosine decay")
    grad_clip: float | None = Field(1.0, gt=0.0, description="clip the gradient norm to this; null = no clipping")
    input_size: int | None = Field(None, ge=32, description="training input side; null = saliency.input_size")
    augment: bool = Field(True, description="random rotation, zoom, flip, photometry, shadows, blur and noise")
    hue: float = Field(
        0.0, ge=0.0, le=1.0, description="probability of turning all hues by a random angle (paint of any colour)"
    )
    crop: int | None = Field(
        None, ge=32, description="train on crops of this side at the input resolution; null = whole images"
    )
    crop_on_marking: float = Field(0.8, ge=0.0, le=1.0, description="share of crops that hold a salient pixel")
    init_weights: str | None = Field(
        None, description="start from this weights file (fine-tuning: new optimizer and schedule); null = fresh"
    )
    seed: int = Field(0, description="seed of initialisation, shuffling and augmentation")
    monitor: Literal["mae", "maxF", "meanF", "sm"] = Field("mae", description="validation metric for best/early stop")
    patience: int = Field(8, ge=1, description="stop after this many epochs without improvement")
    val_every: int = Field(1, ge=1, description="validate every this many epochs")
    threads: int | None = Field(
        1, ge=1, description="torch intra-op threads (1 is fastest on a shared 2-core machine); null = torch's default"
    )
    resume: str | None = Field(None, description="directory of an interrupted run (its checkpoint) to continue")
    half_weights: bool = Field(True, description="store large tensors of the final weights as float16")
    export_to: str | None = Field(None, description="also copy the weights and model card to this directory")
    progress: bool = Field(True, description="show a progress bar")


def _lower_is_better(metric: str) -> bool:
    return metric == "mae"


def _learning_rate(step: int, total: int, opts: TrainOptions) -> float:
    """Linear warm-up then cosine decay to 1% of the peak."""
    if opts.warmup_steps and step < opts.warmup_steps:
        return opts.lr * (step + 1) / opts.warmup_steps
    span = max(1, total - opts.warmup_steps)
    t = min(1.0, (step - opts.warmup_steps) / span)
    return opts.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * t)))


def _better(value: float, best: float | None, metric: str) -> bool:
    if best is None:
        return True
    return value < best if _lower_is_better(metric) else value > best


def train_model(
    model: str,
    arch: Mapping[str, Any],
    default_input_size: int,
    data: DataOptions,
    opts: TrainOptions,
    out_dir: str | Path,
    command: str = "",
) -> dict[str, Any]:
    """Train ``model`` and write ``<model>.safetensors`` and its model card (``<model>.json``, ``<model>.md``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if opts.threads:
        torch.set_num_threads(opts.threads)
    torch.manual_seed(opts.seed)
    size = opts.input_size or default_input_size
    if model == "selfreformer" and size % 32:
        raise ConfigError(f"selfreformer needs an input size divisible by 32, got {size}")
    if opts.crop is not None and opts.crop > size:
        raise ConfigError(f"train.crop={opts.crop} is larger than the input size {size}; choose at most {size}")
    if model == "selfreformer" and opts.crop is not None and opts.crop % 32:
        raise ConfigError(f"selfreformer needs crops divisible by 32, got train.crop={opts.crop}")
    if opts.resume and opts.init_weights:
        raise ConfigError("train.resume and train.init_weights exclude each other: resume continues, init starts anew")

    # 1. data and splits
    folder = SodFolder(data.root)
    spec = SplitSpec(data.seed, data.val_fraction, data.test_fraction, tuple(data.heldout_designs), data.group_key)
    saved = folder.splits() if data.use_saved_splits else None
    splits = saved if saved is not None else make_splits(folder.names, folder.metas(), spec)
    train_names = splits.get("train", [])[: data.max_train]
    val_names = splits.get("val", [])[: data.max_val]
    if not train_names:
        raise DataError(f"{folder.root}: the train split is empty")
    if not val_names:
        raise DataError(f"{folder.root}: the val split is empty; set data.val_fraction > 0")

    # 2. network, optimizer, data loader
    net = build_model(model, arch)
    parameters = sum(p.numel() for p in net.parameters())
    extra = getattr(net, "targets_from_mask", None)
    augment = Augmentation(hue_probability=opts.hue) if opts.augment else None
    dataset = SodTrainingSet(folder, train_names, size, augment, opts.seed, extra, opts.crop, opts.crop_on_marking)
    steps_per_epoch = math.ceil(len(dataset) / opts.batch_size)
    total_steps = opts.epochs * steps_per_epoch
    if opts.max_steps:
        total_steps = min(total_steps, opts.max_steps)
    optimizer = torch.optim.AdamW(net.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)

    progress: dict[str, Any] = {
        "epoch": 0,
        "step": 0,
        "best": None,
        "best_epoch": None,
        "since_best": 0,
        "history": [],
        "train_seconds": 0.0,
        "train_images": 0,
    }
    if opts.init_weights:
        load_weights(net, opts.init_weights, model, arch)
    if opts.resume:
        progress = load_checkpoint(Path(opts.resume), net, optimizer, model, arch)
        best_file = Path(opts.resume) / BEST
        if best_file.is_file() and Path(opts.resume).resolve() != out.resolve():
            shutil.copyfile(best_file, out / BEST)

    # 3. epochs
    start = time.perf_counter()
    stopped_early = False
    from tqdm import tqdm

    while progress["epoch"] < opts.epochs and progress["step"] < total_steps:
        epoch = progress["epoch"]
        dataset.epoch = epoch
        generator = torch.Generator().manual_seed(opts.seed + epoch)
        loader = torch.utils.data.DataLoader(
            dataset, batch_size=opts.batch_size, shuffle=True, generator=generator, collate_fn=collate
        )
        net.train()
        t0 = time.perf_counter()
        images = 0
        losses = []
        bar = tqdm(loader, desc=f"{model} epoch {epoch + 1}/{opts.epochs}", disable=not opts.progress, leave=False)
        for x, targets in bar:
            if progress["step"] >= total_steps:
                break
            for group in optimizer.param_groups:
                group["lr"] = _learning_rate(progress["step"], total_steps, opts)
            outputs = net(x)
            loss, _ = net.loss(outputs, targets)  # type: ignore[operator]
            optimizer.zero_grad(set_to_none=True)
            if not torch.isfinite(loss):
                raise DataError(f"{model}: the loss became {float(loss)} at step {progress['step']}; lower train.lr")
            loss.backward()
            if opts.grad_clip:
                nn.utils.clip_grad_norm_(net.parameters(), opts.grad_clip)
            optimizer.step()
            progress["step"] += 1
            images += x.shape[0]
            losses.append(float(loss.detach()))
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
        bar.close()
        progress["train_seconds"] += time.perf_counter() - t0
        progress["train_images"] += images
        progress["epoch"] = epoch + 1
        record: dict[str, Any] = {"epoch": epoch + 1, "step": progress["step"], "loss": float(np.mean(losses))}

        # 4. validation, best weights, early stopping
        last = progress["epoch"] >= opts.epochs or progress["step"] >= total_steps
        if progress["epoch"] % opts.val_every == 0 or last:
            net.eval()
            metrics = evaluate_network(net, folder, val_names, size)
            record["val"] = metrics
            value = metrics[opts.monitor]
            if _better(value, progress["best"], opts.monitor):
                progress.update(best=value, best_epoch=epoch + 1, since_best=0)
                save_weights(net, out / BEST, model, arch, extra={"input_size": size})
            else:
                progress["since_best"] += opts.val_every
        progress["history"].append(record)
        save_checkpoint(out, net, optimizer, progress, model, arch)
        if opts.progress:
            val = record.get("val")
            shown = f", val {opts.monitor} {val[opts.monitor]:.4f}" if val else ""
            print(f"{model} epoch {epoch + 1}: loss {record['loss']:.4f}{shown}", flush=True)
        if progress["since_best"] >= opts.patience:
            stopped_early = True
            break
    wall = time.perf_counter() - start

    # 5. best weights, test metrics, model card
    load_weights(net, out / BEST, model, arch)
    net.eval()
    tests = {}
    for split in ("val", "test", "test_heldout"):
        names = val_names if split == "val" else splits.get(split, [])
        if names:
            tests[split] = evaluate_network(net, folder, names, size)
    weights_path = save_weights(
        net, out / f"{model}.safetensors", model, arch, half=opts.half_weights, extra={"input_size": size}
    )
    card = {
        "model": model,
        "architecture": dict(arch),
        "parameters": parameters,
        "input_size": size,
        "weights": weights_path.name,
        "weights_sha256": file_hash(weights_path),
        "weights_bytes": weights_path.stat().st_size,
        "weights_dtype": "float16 (large tensors), float32 (others)" if opts.half_weights else "float32",
        "command": command,
        "data": {
            "root": str(folder.root),
            "description": data.description,
            "splits_from": "splits.json" if saved is not None else "made here",
            "split_spec": spec.to_dict(),
            "sizes": {k: len(v) for k, v in splits.items()},
            "train_used": len(train_names),
            "val_used": len(val_names),
        },
        "training": {
            "seed": opts.seed,
            "epochs_run": progress["epoch"],
            "steps": progress["step"],
            "best_epoch": progress["best_epoch"],
            "monitor": opts.monitor,
            "stopped_early": stopped_early,
            "train_seconds": round(progress["train_seconds"], 2),
            "wall_seconds_this_run": round(wall, 2),
            "images_per_second": progress["train_images"] / max(progress["train_seconds"], 1e-9),
            "batch_size": opts.batch_size,
            "lr": opts.lr,
            "threads": torch.get_num_threads(),
            "options": opts.model_dump(),
            "init_weights_sha256": file_hash(Path(opts.init_weights)) if opts.init_weights else None,
            "init_from": init_provenance(opts.init_weights, model),
            "history": progress["history"],
        },
        "metrics": tests,
        "environment": {
            "torch": torch.__version__,
            "python": platform.python_version(),
            "machine": platform.machine(),
            "processor": cpu_name(),
        },
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    atomic_write_json(out / f"{model}.json", card)
    atomic_write_text(out / f"{model}.md", model_card_markdown(card))
    if opts.export_to:
        target = Path(opts.export_to).expanduser()
        target.mkdir(parents=True, exist_ok=True)
        for suffix in (".safetensors", ".json", ".md"):
            shutil.copyfile(out / f"{model}{suffix}", target / f"{model}{suffix}")
    return card
