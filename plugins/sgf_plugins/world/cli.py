"""``sgf-world``: export a campus preset to disk (folder format), draw its map and sample frames."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir, format_validation_error
from sgf_pipeline.errors import ConfigError, DataError
from sgf_pipeline.folder_format import FolderDatasetWriter
from sgf_pipeline.io import atomic_write_json
from sgf_plugins.world.presets import PRESETS
from sgf_plugins.world.world import CampusWorld, world_params


class WorldAppOptions(BaseModel):
    """Options of ``sgf-world`` (everything in ``conf/sgf_world.yaml`` but the dataset)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    out: str | None = Field(None, description="output folder; null = the Hydra run directory")
    export: bool = Field(True, description="write the sequence in the folder dataset format")
    map: bool = Field(True, description="draw the top-down map PNG")
    samples: bool = Field(True, description="render the sample frames")
    max_frames: int | None = Field(None, ge=1, description="export only the first N frames")
    image_format: str = Field("png", pattern="^(png|jpg)$", description="image file format")
    overwrite: bool = Field(False, description="replace an existing export")
    progress: bool = Field(True, description="progress bar over frames")


def run_world_app(options: WorldAppOptions, dataset: dict[str, Any], out: Path) -> dict[str, Any]:
    """Build the world and write what ``options`` asks for into ``out``; return a summary."""
    from sgf_plugins.world.mapping import save_map, save_samples

    name = dataset.pop("name", None)
    if name not in PRESETS:
        raise ConfigError(
            f"sgf-world exports the synthetic campus presets only ({', '.join(PRESETS)}); got dataset={name!r}"
        )
    target = out / name
    if options.export and target.exists() and not options.overwrite:
        raise DataError(f"{target} exists already; choose another out=... or pass overwrite=true to replace it")
    world = CampusWorld(PRESETS[name], world_params(**dataset))
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {
        "sequence": name,
        "seed": world.seed,
        "scale": world.params.scale,
        "frames": len(world),
        "route_length_m": round(world.drive.length, 2),
        "markings_total": len(world.layout.markings),
        "markings_on_path": len(world.truth.on_path),
        "revisit_pairs": len(world.truth.revisits),
        "revisit_pairs_reverse": sum(r.reverse for r in world.truth.revisits),
    }
    if options.map:
        summary["map"] = str(save_map(world, out / "map.png"))
    if options.samples:
        summary["samples"] = {k: str(v) for k, v in save_samples(world, out / "samples").items()}
    if options.export:
        total = len(world) if options.max_frames is None else min(options.max_frames, len(world))
        writer = FolderDatasetWriter(
            out / name, name, world.calibration, world.params.rate_hz, options.image_format, options.overwrite
        )
        t0 = time.perf_counter()
        frames = world.frames(stop=total)
        if options.progress:
            from tqdm import tqdm

            frames = tqdm(frames, total=total, desc=f"sgf-world {name}", unit="frame")
        for frame in frames:
            writer.add(
                frame.timestamp,
                frame.image,
                frame.odometry,
                frame.imu_roll_pitch,
                frame.ground_truth,
                frame.truth_ids(),
            )
        truth = world.truth if total == len(world) else _truncated_truth(world, total)
        summary["export"] = str(writer.close(truth))
        summary["export_seconds"] = round(time.perf_counter() - t0, 2)
        summary["exported_frames"] = total
    atomic_write_json(out / "world.json", summary)
    return summary


def _truncated_truth(world: CampusWorld, frames: int) -> Any:
    """The ground truth of the first ``frames`` frames only (passes cut at the end, pairs re-counted)."""
    from sgf_pipeline.truth import SequenceTruth

    truth = world.truth
    passes = [p for p in truth.passes if p.end_frame < frames]
    kept = {(p.instance_id, p.number) for p in passes}
    revisits = [r for r in truth.revisits if (r.instance_id, r.second.number) in kept]
    return SequenceTruth(markings=dict(truth.markings), passes=passes, revisits=revisits)


@hydra.main(config_path=str(config_dir()), config_name="sgf_world", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Export the configured campus preset, its map and sample frames."""
    raw = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(raw, dict)
    dataset = dict(raw.pop("dataset", {}) or {})
    raw.pop("hydra", None)
    try:
        options = WorldAppOptions.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(
            f"invalid configuration:\n  {format_validation_error('sgf_world', WorldAppOptions, exc)}"
        ) from None
    out = Path(options.out) if options.out else Path(HydraConfig.get().runtime.output_dir)
    summary = run_world_app(options, dataset, out)
    lines = [f"sgf-world: {summary['sequence']} (seed {summary['seed']}, scale {summary['scale']:g})"]
    lines.append(f"  route {summary['route_length_m']:.0f} m, {summary['frames']} frames")
    lines.append(
        f"  markings on the path {summary['markings_on_path']}/{summary['markings_total']}, revisit pairs "
        f"{summary['revisit_pairs']} ({summary['revisit_pairs_reverse']} reverse)"
    )
    for key in ("export", "map"):
        if key in summary:
            lines.append(f"  {summary[key]}")
    if "samples" in summary:
        lines.append(f"  {out / 'samples'}")
    print("\n".join(lines), flush=True)


#: The ``sgf-world`` console script.
main = console(app)

if __name__ == "__main__":
    main()
