"""Training a saliency network on a SOD folder, on CPU: seeded, validated, checkpointed, resumable, early-stopped.

Every random choice derives from the seed (the shuffling of epoch ``e`` from ``seed + e``, the
augmentation of sample ``i`` in epoch ``e`` from ``(seed, e, i)``), so a resumed run continues
exactly as an uninterrupted one would. Checkpoints hold the network, the optimizer state and the
progress in safetensors and JSON, never pickle.
"""

from __future__ import annotations

import json
import math
import platform
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from sgf_pipeline.cache import file_hash
from sgf_pipeline.errors import ConfigError, DataError
from sgf_pipeline.io import atomic_path, atomic_write_json, atomic_write_text
from sgf_plugins.saliency.augment import Augmentation, salient_crop
from sgf_plugins.saliency.data import SodFolder, SplitSpec, make_splits
from sgf_plugins.saliency.inference import probability_module
from sgf_plugins.saliency.metrics import SodMetrics
from sgf_plugins.saliency.models import build_model
from sgf_plugins.saliency.preprocess import normalize_image, resize_mask
from sgf_plugins.saliency.weights import (
    describe_arch,
    load_weights,
    read_metadata,
    save_weights,
    trained_input_size,
)

CHECKPOINT = "checkpoint.safetensors"
CHECKPOINT_STATE = "checkpoint.json"
BEST = "best.safetensors"


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


class SodTrainingSet(torch.utils.data.Dataset[tuple[torch.Tensor, dict[str, torch.Tensor]]]):
    """Samples of a SOD folder as network inputs and targets, augmented reproducibly per epoch."""

    def __init__(
        self,
        folder: SodFolder,
        names: Sequence[str],
        size: int,
        augment: Augmentation | None,
        seed: int,
        extra_targets: Callable[[np.ndarray], dict[str, np.ndarray]] | None = None,
        crop: int | None = None,
        crop_on_marking: float = 0.8,
    ) -> None:
        self.folder = folder
        self.crop = crop
        self.crop_on_marking = crop_on_marking
        self.names = list(names)
        self.size = size
        self.augment = augment
        self.seed = seed
        self.epoch = 0
        self.extra_targets = extra_targets

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        name = self.names[index]
        import cv2

        rgb = self.folder.image(name)
        mask = resize_mask(self.folder.mask(name), self.size)
        if rgb.shape[:2] != (self.size, self.size):
            rgb = cv2.resize(rgb, (self.size, self.size), interpolation=cv2.INTER_AREA)
        rng = np.random.default_rng([self.seed, self.epoch, index])
        if self.augment is not None:
            rgb, mask = self.augment(rgb, mask, rng)
        if self.crop is not None and self.crop < self.size:
            rgb, mask = salient_crop(rgb, mask, self.crop, self.crop_on_marking, rng)
        targets = {"mask": torch.from_numpy(mask[None].copy())}
        if self.extra_targets is not None:
            for key, value in self.extra_targets(mask).items():
                targets[key] = torch.from_numpy(value[None].copy())
        return torch.from_numpy(normalize_image(rgb, rgb.shape[0])), targets


def _collate(batch: list[tuple[torch.Tensor, dict[str, torch.Tensor]]]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    images = torch.stack([b[0] for b in batch])
    targets = {k: torch.stack([b[1][k] for b in batch]) for k in batch[0][1]}
    return images, targets


def predict_folder(
    net: nn.Module, folder: SodFolder, names: Sequence[str], size: int, batch_size: int = 8
) -> Iterator[tuple[str, np.ndarray]]:
    """``(name, probability at the mask's resolution)`` for each sample, the network in eval mode."""
    import cv2

    module = probability_module(net)
    for start in range(0, len(names), batch_size):
        chunk = names[start : start + batch_size]
        x = np.stack([normalize_image(folder.image(n), size) for n in chunk])
        with torch.inference_mode():
            probs = module(torch.from_numpy(x)).numpy()[:, 0]
        for name, prob in zip(chunk, probs, strict=True):
            h, w = folder.mask(name).shape
            if prob.shape != (h, w):
                prob = cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)
            yield name, np.clip(prob, 0.0, 1.0)


def evaluate_network(net: nn.Module, folder: SodFolder, names: Sequence[str], size: int) -> dict[str, float]:
    """SOD metrics of a network on some samples of a folder (PySODMetrics conventions)."""
    acc = SodMetrics()
    for name, prob in predict_folder(net, folder, names, size):
        acc.add_probability(prob, folder.mask(name))
    return acc.results()


def _learning_rate(step: int, total: int, opts: TrainOptions) -> float:
    """Linear warm-up then cosine decay to 1% of the peak."""
    if opts.warmup_steps and step < opts.warmup_steps:
        return opts.lr * (step + 1) / opts.warmup_steps
    span = max(1, total - opts.warmup_steps)
    t = min(1.0, (step - opts.warmup_steps) / span)
    return opts.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * t)))


def _save_checkpoint(
    out: Path, net: nn.Module, optimizer: torch.optim.Optimizer, state: dict[str, Any], name: str, arch: Mapping
) -> None:
    """Network and optimizer tensors in safetensors, progress and optimizer settings in JSON."""
    from safetensors.torch import save_file

    tensors = {f"model.{k}": v.detach().contiguous() for k, v in net.state_dict().items()}
    opt = optimizer.state_dict()
    for index, values in opt["state"].items():
        for key, value in values.items():
            t = value if isinstance(value, torch.Tensor) else torch.tensor(value)
            tensors[f"optim.{index}.{key}"] = t.detach().contiguous()
    with atomic_path(out / CHECKPOINT) as tmp:
        save_file(tensors, str(tmp), metadata={"model": name, "architecture": json.dumps(dict(arch))})
    atomic_write_json(out / CHECKPOINT_STATE, {**state, "param_groups": opt["param_groups"]})


def _load_checkpoint(
    where: Path, net: nn.Module, optimizer: torch.optim.Optimizer, name: str, arch: Mapping
) -> dict[str, Any]:
    """Restore a checkpoint written by :func:`_save_checkpoint`; returns the saved progress."""
    from safetensors import safe_open

    path, state_path = where / CHECKPOINT, where / CHECKPOINT_STATE
    if not path.is_file() or not state_path.is_file():
        raise DataError(f"train.resume={where}: no {CHECKPOINT} and {CHECKPOINT_STATE} there")
    with safe_open(str(path), framework="pt") as fh:
        meta = fh.metadata() or {}
        if meta.get("model") != name or json.loads(meta.get("architecture", "{}")) != dict(arch):
            raise DataError(
                f"train.resume={where}: the checkpoint is {meta.get('model')} "
                f"({meta.get('architecture')}), not {name} ({describe_arch(arch)})"
            )
        tensors = {k: fh.get_tensor(k) for k in fh.keys()}  # noqa: SIM118
    net.load_state_dict({k[len("model.") :]: v for k, v in tensors.items() if k.startswith("model.")})
    saved = json.loads(state_path.read_text())
    optim_state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        if key.startswith("optim."):
            _, index, field = key.split(".", 2)
            optim_state.setdefault(int(index), {})[field] = value
    optimizer.load_state_dict({"state": optim_state, "param_groups": saved.pop("param_groups")})
    return saved


def _init_provenance(init_weights: str | None, model: str) -> dict[str, Any] | None:
    """The training record of the run that made ``init_weights``, for the new card.

    The model card beside the weights when there is one; otherwise, for the ``best.safetensors`` of
    a run that was stopped or is still going, that run's checkpoint progress and Hydra overrides.
    """
    if not init_weights:
        return None
    card_path = Path(init_weights).with_name(f"{model}.json")
    try:
        card = json.loads(card_path.read_text())
        training = card["training"]
        return {
            "command": card.get("command", ""),
            "data": card.get("data", {}).get("root"),
            "input_size": card.get("input_size"),
            **{
                k: training.get(k) for k in ("epochs_run", "steps", "best_epoch", "train_seconds", "options", "history")
            },
            **({"init_from": training["init_from"]} if training.get("init_from") else {}),
        }
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    return _unfinished_run_provenance(Path(init_weights)) or {
        "card": None,
        "note": f"no readable model card {card_path.name} (nor a run's {CHECKPOINT_STATE}) beside the weights",
    }


def _unfinished_run_provenance(weights: Path) -> dict[str, Any] | None:
    """The record of a run directory holding ``weights`` without a card: its checkpoint and Hydra files."""
    from omegaconf import OmegaConf

    run = weights.parent
    try:
        state = json.loads((run / CHECKPOINT_STATE).read_text())
        record: dict[str, Any] = {
            "command": "",
            "note": f"from the {CHECKPOINT_STATE} of a run that did not finish (no model card)",
            "epochs_run": int(state["epoch"]),
            "steps": int(state["step"]),
            "best_epoch": state.get("best_epoch"),
            "train_seconds": state.get("train_seconds"),
            "history": state.get("history", []),
            "input_size": trained_input_size(read_metadata(weights)),
        }
    except (OSError, ValueError, KeyError, TypeError):
        return None
    hydra = run / ".hydra"
    try:
        record["command"] = " ".join(["sgf-train", *map(str, OmegaConf.load(hydra / "overrides.yaml"))])
        config = OmegaConf.load(hydra / "config.yaml")
        record["data"] = OmegaConf.select(config, "data.root")
        record["input_size"] = record["input_size"] or OmegaConf.select(config, "saliency.input_size")
    except (OSError, ValueError, TypeError):
        pass
    return record


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
        progress = _load_checkpoint(Path(opts.resume), net, optimizer, model, arch)
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
            dataset, batch_size=opts.batch_size, shuffle=True, generator=generator, collate_fn=_collate
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
        _save_checkpoint(out, net, optimizer, progress, model, arch)
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
            "init_from": _init_provenance(opts.init_weights, model),
            "history": progress["history"],
        },
        "metrics": tests,
        "environment": {
            "torch": torch.__version__,
            "python": platform.python_version(),
            "machine": platform.machine(),
            "processor": _cpu_name(),
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


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def _init_lines(init: Mapping[str, Any] | None) -> list[str]:
    """Model-card lines for the runs the weights were fine-tuned from, earliest last."""
    lines = []
    while init:
        if init.get("command") is None:
            lines.append(f"- fine-tuned from weights without a readable model card ({init.get('note', '')})")
            break
        note = f"; {init['note']}" if init.get("note") else ""
        lines.append(
            f"- fine-tuned from: `{init['command']}` ({init.get('epochs_run')} epochs at input "
            f"{init.get('input_size')}, {float(init.get('train_seconds') or 0):.0f} s{note})"
        )
        init = init.get("init_from")
    return lines


def model_card_markdown(card: Mapping[str, Any]) -> str:
    """A human-readable model card."""
    lines = [
        f"# {card['model']} model card",
        "",
        f"- architecture: {describe_arch(card['architecture'])} ({card['parameters']:,} parameters)",
        f"- input size: {card['input_size']} px; weights: {card['weights']} ({card['weights_dtype']})",
        f"- command: `{card['command']}`",
        f"- data: {card['data']['root']} {card['data']['description']}".rstrip(),
        f"- splits: {card['data']['sizes']} ({card['data']['splits_from']}, spec {card['data']['split_spec']})",
        f"- training: {card['training']['epochs_run']} epochs, {card['training']['steps']} steps, best epoch "
        f"{card['training']['best_epoch']} by val {card['training']['monitor']}, "
        f"{card['training']['train_seconds']:.0f} s, {card['training']['images_per_second']:.1f} images/s on "
        f"{card['training']['threads']} threads ({card['environment']['processor']})",
        *_init_lines(card["training"].get("init_from")),
        f"- date: {card['date']}",
        "",
        "| split | maxF | meanF | adpF | MAE | S-measure | mean E |",
        "|---|---|---|---|---|---|---|",
    ]
    for split, m in card["metrics"].items():
        lines.append(
            f"| {split} | {m['maxF']:.3f} | {m['meanF']:.3f} | {m['adpF']:.3f} | {m['mae']:.3f} | {m['sm']:.3f} "
            f"| {m['meanEm']:.3f} |"
        )
    return "\n".join(lines) + "\n"
