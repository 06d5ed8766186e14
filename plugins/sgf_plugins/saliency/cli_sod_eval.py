"""``sgf-sod-eval``: SOD metrics of saved predictions or of saliency variants run on a SOD folder (Hydra app)."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel, ConfigDict, Field

from sgf_pipeline import Stage
from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir, validate_options
from sgf_pipeline.errors import ConfigError, DataError
from sgf_pipeline.io import atomic_write_json
from sgf_pipeline.types import Bev, BevGrid
from sgf_plugins.saliency.data import IMAGE_SUFFIXES, SodFolder, write_png
from sgf_plugins.saliency.figures import Example, example_names, write_examples
from sgf_plugins.saliency.metrics import SodMetrics, format_table, to_uint8

OUTPUT = "sod_metrics.json"
EXAMPLES = "sod_examples.png"


class SodEvalData(BaseModel):
    """The SOD folder that ``models`` run on (``data`` of conf/sgf_sod_eval.yaml)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    root: str | None = Field(None, description="SOD folder with images/ and masks/")
    split: str | None = Field(
        None, description="train | val | test | test_heldout | all; null: test with splits.json, else all"
    )
    resolution: float = Field(0.02, gt=0.0, description="metres per BEV pixel (the classical detector's scale)")
    max_images: int | None = Field(None, ge=1, description="at most this many images, spread over the split")
    min_salient_pixels: int = Field(0, ge=0, description="leave out images whose mask has fewer salient pixels")


class SodEvalOptions(BaseModel):
    """The options of ``sgf-sod-eval`` (conf/sgf_sod_eval.yaml)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    preds: dict[str, str] = Field(default_factory=dict, description="name -> folder of saved predictions")
    masks: str | None = Field(None, description="folder of ground-truth masks for preds")
    models: list[str] = Field(default_factory=list, description="saliency variants to run on data.root")
    params: dict[str, dict[str, Any]] = Field(default_factory=dict, description="per-model parameter overrides")
    data: SodEvalData = Field(default_factory=SodEvalData)
    save_predictions: bool = False
    examples: int = Field(6, ge=0, description="rows of sod_examples.png (0 = no figure)")
    threads: int | None = Field(None, ge=1, description="intra-op threads of the networks")
    warmup: int = Field(2, ge=0, description="frames run before timing")


def _summary(acc: SodMetrics, fps: float | None, **extra: Any) -> dict[str, Any]:
    r = acc.results()
    return {**r, "em": r["meanEm"], "fps": fps, "images": len(acc), **extra}


def evaluate_prediction_folder(preds: str | Path, masks: str | Path) -> dict[str, Any]:
    """Metrics of every mask in ``masks`` against the prediction of the same stem in ``preds``."""
    pred_dir, mask_dir = Path(preds).expanduser(), Path(masks).expanduser()
    for d in (pred_dir, mask_dir):
        if not d.is_dir():
            raise DataError(f"folder {d} not found")
    mask_files = sorted(p for p in mask_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not mask_files:
        raise DataError(f"{mask_dir}: no mask images")
    by_stem = {p.stem: p for p in pred_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    missing = [p.stem for p in mask_files if p.stem not in by_stem]
    if missing:
        raise DataError(f"{pred_dir}: no prediction for {len(missing)} mask(s), e.g. {', '.join(missing[:3])}")
    acc = SodMetrics()
    for mask_file in mask_files:
        gt = cv2.imread(str(mask_file), cv2.IMREAD_GRAYSCALE)
        pred = cv2.imread(str(by_stem[mask_file.stem]), cv2.IMREAD_GRAYSCALE)
        if gt is None or pred is None:
            raise DataError(f"cannot read {mask_file} or its prediction")
        if pred.shape != gt.shape:
            pred = cv2.resize(pred, (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_LINEAR)
        acc.add(pred, gt)
    return _summary(acc, None, source=str(pred_dir))


def bev_of(image: np.ndarray, valid: np.ndarray | None, resolution: float, index: int) -> Bev:
    """A BEV of an image from a SOD folder: the robot at the bottom centre, all pixels seen unless told."""
    h, w = image.shape[:2]
    grid = BevGrid(resolution, 0.0, h * resolution, -w * resolution / 2, w * resolution / 2)
    seen = np.ones((h, w), bool) if valid is None else valid
    return Bev(image=image, valid=seen, grid=grid, frame_index=index, timestamp=float(index))


def evaluate_models(
    models: Sequence[str],
    folder: SodFolder,
    names: Sequence[str],
    params: Mapping[str, Mapping[str, Any]],
    resolution: float = 0.02,
    threads: int | None = None,
    warmup: int = 2,
    save_dir: Path | None = None,
    examples: Mapping[str, Example] | None = None,
) -> dict[str, dict[str, Any]]:
    """Run each registered saliency variant on the samples and measure SOD metrics and frames per second.

    ``examples`` (by name) receive each model's map of their sample, for the figure.
    """
    from sgf_pipeline.registry import load_plugins

    registry = load_plugins().registry
    results: dict[str, dict[str, Any]] = {}
    for model in models:
        variant = registry.get("saliency", model)
        values = dict(params.get(model, {}))
        if threads and "threads" in variant.params_model.model_fields:
            values.setdefault("threads", threads)
        if not issubclass(variant.cls, Stage):  # pragma: no cover - the registry keys kinds
            raise ConfigError(f"saliency={model} is not a stage")
        try:
            stage = variant.cls(variant.params_model.model_validate(values))
        except (ValueError, FileNotFoundError) as exc:
            raise ConfigError(f"saliency={model} cannot start: {exc}") from exc
        acc = SodMetrics()
        seconds = 0.0
        for i, name in enumerate(names):
            bev = bev_of(folder.image(name), folder.valid(name), resolution, i)
            if i < warmup:
                stage.process(bev)
            t0 = time.perf_counter()
            out = stage.process(bev)
            seconds += time.perf_counter() - t0
            acc.add_probability(out.probability, folder.mask(name))
            if save_dir is not None:
                write_png(save_dir / model / f"{name}.png", to_uint8(out.probability))
            if examples is not None and name in examples:
                examples[name].maps[model] = to_uint8(out.probability)
        results[model] = _summary(acc, len(names) / seconds if seconds > 0 else None, source=str(folder.root))
    return results


def run(cfg: Mapping[str, Any], out_dir: Path) -> dict[str, dict[str, Any]]:
    """Evaluate what the config names; writes ``sod_metrics.json`` in ``out_dir`` and returns it."""
    opts: SodEvalOptions = validate_options("sgf-sod-eval", SodEvalOptions, dict(cfg))
    if not opts.preds and not opts.models:
        raise ConfigError(
            "nothing to evaluate: give +preds.<name>=<folder> masks=<folder>, or models=[...] data.root=..."
        )
    results: dict[str, dict[str, Any]] = {}
    if opts.preds:
        if not opts.masks:
            raise ConfigError("preds need the ground truth: masks=<folder of masks>")
        for name, folder in opts.preds.items():
            results[name] = evaluate_prediction_folder(folder, opts.masks)
    if opts.models:
        data = opts.data
        if not data.root:
            raise ConfigError("models need a SOD folder: data.root=<folder with images/ and masks/>")
        sod = SodFolder(data.root)
        split = data.split or ("test" if sod.splits() is not None else "all")
        names = sod.split(split)
        salient: dict[str, int] = {}

        def salient_pixels(name: str) -> int:  # each mask read once for the filter and the figure
            if name not in salient:
                salient[name] = int((sod.mask(name) > 128).sum())
            return salient[name]

        if data.min_salient_pixels > 0:
            # SOD benchmarks have a salient object in every image: an image whose mask is empty scores
            # F = 0 at every threshold, and a marking that barely entered the view is not an object yet.
            names = [n for n in names if salient_pixels(n) >= data.min_salient_pixels]
        if data.max_images is not None and len(names) > data.max_images:
            names = names[:: max(1, len(names) // data.max_images)][: data.max_images]  # spread over the split
        if not names:
            raise DataError(f"{sod.root}: split {split!r} is empty")
        save_dir = out_dir / "preds" if opts.save_predictions else None
        examples = {
            n: Example(n, sod.image(n), sod.mask(n)) for n in example_names(names, salient_pixels, opts.examples)
        }
        found = evaluate_models(
            opts.models,
            sod,
            names,
            opts.params,
            data.resolution,
            opts.threads,
            opts.warmup,
            save_dir,
            examples,
        )
        for model, values in found.items():
            results[model] = {**values, "split": split}
        if examples:
            write_examples(out_dir / EXAMPLES, list(examples.values()), opts.models)
    atomic_write_json(out_dir / OUTPUT, results)
    return results


@hydra.main(config_path=str(config_dir()), config_name="sgf_sod_eval", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Print Table 1 for the chosen predictions or models and write sod_metrics.json."""
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    raw = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(raw, dict)
    results = run({str(k): v for k, v in raw.items()}, out_dir)
    print(format_table(results))
    print(f"\n  {out_dir / OUTPUT}", flush=True)
    if (out_dir / EXAMPLES).is_file():
        print(f"  {out_dir / EXAMPLES}", flush=True)


#: The console script.
main = console(app)

if __name__ == "__main__":
    main()
