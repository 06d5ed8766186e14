"""Training checkpoints: the network and optimizer tensors in safetensors, the progress in JSON, never pickle."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from sgf_pipeline.errors import DataError
from sgf_pipeline.io import atomic_path, atomic_write_json
from sgf_plugins.saliency.weights import describe_arch

CHECKPOINT = "checkpoint.safetensors"
CHECKPOINT_STATE = "checkpoint.json"
BEST = "best.safetensors"


def save_checkpoint(
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


def load_checkpoint(
    where: Path, net: nn.Module, optimizer: torch.optim.Optimizer, name: str, arch: Mapping
) -> dict[str, Any]:
    """Restore a checkpoint written by :func:`save_checkpoint`; returns the saved progress."""
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
