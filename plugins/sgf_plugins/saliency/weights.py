"""Saliency weights as safetensors files, with the network's name and architecture in their metadata.

A file that is missing or does not fit the configured network fails with an error that says how
to fix it.

No pickle is ever read: tensors come from safetensors, everything else from JSON metadata.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sgf_pipeline.errors import DataError

if TYPE_CHECKING:
    import torch
    from torch import nn

FORMAT = "sgf-saliency-weights"
VERSION = "1"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: Tensors with at least this many elements are stored as float16 in shipped ("half") files.
HALF_MIN_NUMEL = 1024


def default_weights_path(model: str) -> Path:
    """The weights shipped in the package for ``model``."""
    return WEIGHTS_DIR / f"{model}.safetensors"


def resolve_weights_path(model: str, weights: str | None) -> Path:
    """The configured weights file, or the packaged default."""
    return Path(weights).expanduser() if weights else default_weights_path(model)


def describe_arch(arch: Mapping[str, Any]) -> str:
    """``k=v`` list of architecture parameters, as they are written on the command line."""
    return ", ".join(f"{k}={v}" for k, v in arch.items())


def how_to_fix(model: str, arch: Mapping[str, Any]) -> str:
    """The two ways to get a fitting weights file."""
    overrides = " ".join(f"saliency.{k}={v}" for k, v in arch.items())
    return (
        f"train one with `sgf-train saliency={model} {overrides} data.root=<DUTS-style folder>` and point "
        f"`saliency.weights=<run dir>/{model}.safetensors` to it (or copy it to {default_weights_path(model)}), "
        f"or point `saliency.weights=` to a file trained for this architecture"
    )


def save_weights(
    model: nn.Module,
    path: str | Path,
    name: str,
    arch: Mapping[str, Any],
    *,
    half: bool = False,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write a network's state (parameters and buffers) with its name and architecture in the metadata.

    ``half`` stores large floating tensors (weights of convolutions and linear layers) as float16 and
    keeps small ones (biases, norms, batch-norm statistics) in float32.
    """
    import torch
    from safetensors.torch import save_file

    from sgf_pipeline.io import atomic_path

    tensors: dict[str, torch.Tensor] = {}
    for key, value in model.state_dict().items():
        t = value.detach().cpu().contiguous()
        if half and t.is_floating_point() and t.numel() >= HALF_MIN_NUMEL and "running_" not in key:
            t = t.to(torch.float16)
        tensors[key] = t
    metadata = {"format": FORMAT, "version": VERSION, "model": name, "architecture": json.dumps(dict(arch))}
    if extra:
        metadata["extra"] = json.dumps(dict(extra))
    target = Path(path)
    with atomic_path(target) as tmp:
        save_file(tensors, str(tmp), metadata=metadata)
    return target


def read_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of a weights file; a missing or unreadable file raises :class:`DataError`."""
    from safetensors import safe_open

    p = Path(path)
    if not p.is_file():
        raise DataError(f"weights file {p} not found")
    try:
        with safe_open(str(p), framework="pt") as fh:
            metadata = dict(fh.metadata() or {})
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}  # noqa: SIM118  (safe_open is not a mapping)
    except Exception as exc:
        raise DataError(f"weights file {p} is not a readable safetensors file: {exc}") from None
    return tensors, metadata


def read_metadata(path: str | Path) -> dict[str, str]:
    """The metadata of a weights file, without reading its tensors."""
    from safetensors import safe_open

    p = Path(path)
    if not p.is_file():
        raise DataError(f"weights file {p} not found")
    try:
        with safe_open(str(p), framework="pt") as fh:
            return dict(fh.metadata() or {})
    except Exception as exc:
        raise DataError(f"weights file {p} is not a readable safetensors file: {exc}") from None


def trained_input_size(metadata: Mapping[str, str]) -> int | None:
    """The input size the weights were trained at (``sgf-train`` records it), or None for files without it."""
    try:
        size = json.loads(metadata.get("extra", "{}")).get("input_size")
    except (ValueError, AttributeError):  # a file from elsewhere: no training record
        return None
    return None if size is None else int(size)


def load_weights(model: nn.Module, path: str | Path, name: str, arch: Mapping[str, Any]) -> dict[str, str]:
    """Load a weights file into ``model`` after checking that it was saved for this network and architecture."""
    p = Path(path)
    expected = f"{name} ({describe_arch(arch)})"
    if not p.is_file():
        raise DataError(
            f"weights file {p} not found; saliency={name} expects {expected}. To fix: {how_to_fix(name, arch)}"
        )
    tensors, metadata = read_weights(p)
    if metadata.get("format") != FORMAT:
        raise DataError(
            f"weights file {p} is not an sgf-pipeline saliency weights file (no '{FORMAT}' metadata); "
            f"saliency={name} expects {expected}. To fix: {how_to_fix(name, arch)}"
        )
    saved_name = metadata.get("model")
    saved_arch = json.loads(metadata.get("architecture", "{}"))
    if saved_name != name or saved_arch != dict(arch):
        held = f"{saved_name} ({describe_arch(saved_arch)})"
        if saved_name != name:
            use_file = f"choose saliency={saved_name}"
        else:
            use_file = "set the parameters to the file's: " + " ".join(
                f"saliency.{k}={v}" for k, v in saved_arch.items()
            )
        raise DataError(
            f"weights file {p} holds {held}, but saliency={name} is configured as {expected}. "
            f"To fix: {use_file}, or {how_to_fix(name, arch)}"
        )
    state = model.state_dict()
    missing = sorted(set(state) - set(tensors))
    unexpected = sorted(set(tensors) - set(state))
    wrong = sorted(k for k in set(state) & set(tensors) if tuple(state[k].shape) != tuple(tensors[k].shape))
    if missing or unexpected or wrong:
        detail = "; ".join(
            f"{label}: {', '.join(keys[:5])}{' ...' if len(keys) > 5 else ''}"
            for label, keys in (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong))
            if keys
        )
        raise DataError(f"weights file {p} does not fit {expected} ({detail}). To fix: {how_to_fix(name, arch)}")
    model.load_state_dict({k: tensors[k].to(state[k].dtype) for k in state})
    return metadata
