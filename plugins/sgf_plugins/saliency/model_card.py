"""The model card of trained weights: the record of the runs they come from, and its Markdown form."""

from __future__ import annotations

import json
import platform
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sgf_plugins.saliency.checkpoint import CHECKPOINT_STATE
from sgf_plugins.saliency.weights import describe_arch, read_metadata, trained_input_size


def init_provenance(init_weights: str | None, model: str) -> dict[str, Any] | None:
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


def cpu_name() -> str:
    """The processor's model name, for the card's environment."""
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
