"""``sgf-train``: train a saliency network on a SOD folder (Hydra app; ``-m`` sweeps seeds or sizes)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import RESERVED_KEYS, config_dir, validate_options
from sgf_pipeline.errors import ConfigError
from sgf_plugins.saliency.stages import LEARNED_VARIANTS, LearnedParams


def learned_params(node: dict[str, Any]) -> tuple[str, LearnedParams, dict[str, Any]]:
    """The variant name, its validated parameters and its architecture, from a ``saliency`` config node."""
    name = node.get("name")
    classes = {cls.name: cls for cls in LEARNED_VARIANTS}
    if name not in classes:
        raise ConfigError(
            f"saliency={name}: sgf-train trains the networks {', '.join(classes)}; "
            "the classical detector has no weights"
        )
    cls = classes[name]
    params = validate_options(
        f"saliency ({name})", cls.Params, {k: v for k, v in node.items() if k not in RESERVED_KEYS}
    )
    return name, params, {k: getattr(params, k) for k in cls.arch_fields}


def run(cfg: dict[str, Any], out_dir: Path, command: str) -> dict[str, Any]:
    """Validate the composed config and train; returns the model card."""
    from sgf_plugins.saliency.training import DataOptions, TrainOptions, train_model

    name, params, arch = learned_params(dict(cfg["saliency"]))
    data = validate_options("data", DataOptions, cfg.get("data"))
    opts = validate_options("train", TrainOptions, cfg.get("train"))
    return train_model(name, arch, params.input_size, data, opts, out_dir, command)


@hydra.main(config_path=str(config_dir()), config_name="sgf_train", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> float:
    """Train the configured network and write its weights and model card in the output directory."""
    hc = HydraConfig.get()
    out_dir = Path(hc.runtime.output_dir)
    command = " ".join(["sgf-train", *hc.overrides.task])
    raw = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(raw, dict)
    card = run({str(k): v for k, v in raw.items()}, out_dir, command)
    lines = [f"sgf-train: {card['model']} ({card['parameters']:,} parameters), {card['training']['epochs_run']} epochs"]
    lines.append(
        f"  {card['training']['images_per_second']:.1f} training images/s, {card['training']['train_seconds']:.0f} s"
    )
    for split, m in card["metrics"].items():
        lines.append(f"  {split:<13} maxF {m['maxF']:.3f}  MAE {m['mae']:.3f}  meanF {m['meanF']:.3f}  S {m['sm']:.3f}")
    lines.append(f"  {out_dir / (card['model'] + '.safetensors')}")
    print("\n".join(lines), flush=True)
    val = card["metrics"]["val"]
    return float(val[card["training"]["monitor"]])


#: The console script.
main = console(app)

if __name__ == "__main__":
    main()
