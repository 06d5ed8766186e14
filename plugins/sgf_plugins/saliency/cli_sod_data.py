"""``sgf-sod-data``: make the saliency training data from the synthetic campus (Hydra app)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir
from sgf_pipeline.errors import ConfigError
from sgf_pipeline.io import atomic_write_json
from sgf_plugins.saliency.synthetic_data import WorldSpec, generate


@hydra.main(config_path=str(config_dir()), config_name="sgf_sod_data", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Stream each configured world through enhance + IPM and write one SOD folder with its splits."""
    plain: Any = OmegaConf.to_container(cfg, resolve=True)
    if not plain.get("out"):
        raise ConfigError("where to? set out=<new folder> for the SOD data")
    worlds = [
        WorldSpec(w["preset"], int(w["seed"]), float(w.get("scale", 1.0)), dict(w.get("overrides") or {}))
        for w in plain["worlds"]
    ]
    if not worlds:
        raise ConfigError("no worlds: list at least one {preset, seed} under `worlds`")
    split = plain["split"]
    report = generate(
        plain["out"],
        worlds,
        plain["heldout_designs"],
        plain["keyframe_distance"],
        plain["enhance"],
        plain["ipm"],
        plain["blank_fraction"],
        split["seed"],
        split["val_fraction"],
        split["test_fraction"],
    )
    sizes = {k: len(v) for k, v in report.splits.items()}
    atomic_write_json(
        Path(plain["out"]) / "generator.json", {"config": plain, "samples": report.count, "splits": sizes}
    )
    print(f"wrote {report.count} samples to {report.root}: " + ", ".join(f"{k} {v}" for k, v in sizes.items()))


#: The console script.
main = console(app)

if __name__ == "__main__":
    main()
