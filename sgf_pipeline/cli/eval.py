"""``sgf-eval``: ATE and RPE of two trajectories (TUM, KITTI, EuRoC CSV files, or bag topics), printed and as JSON."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Literal

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel, ConfigDict, Field

from sgf_pipeline.bags import read_bag_trajectory, split_bag_source
from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir, validate_options
from sgf_pipeline.errors import DataError
from sgf_pipeline.evaluation import Alignment, DeltaUnit, ErrorStatistics, ate, rpe
from sgf_pipeline.io import atomic_write_json
from sgf_pipeline.trajectory import Duplicates, Trajectory, TrajectoryError, read_trajectory

log = logging.getLogger("sgf_pipeline")
#: The command line with the trajectories given as paths.
USAGE = "sgf-eval REFERENCE ESTIMATE [key=value ...]"
#: Below this share of the reference's time span covered by the estimate, a warning says so.
MIN_COVERAGE = 0.9


class RpeOptions(BaseModel):
    """The pose pairs of the relative pose error."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    delta: float = Field(1.0, gt=0.0, description="distance between the poses of a pair")
    delta_unit: DeltaUnit = Field("frames", description="frames, meters, degrees or radians")
    all_pairs: bool = Field(False, description="all pairs at that distance instead of consecutive ones")


class EvalOptions(BaseModel):
    """The options of ``sgf-eval`` (conf/sgf_eval.yaml)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    reference: str = Field(description="reference trajectory file")
    estimate: str = Field(description="estimated trajectory file")
    reference_format: Literal["auto", "tum", "kitti", "euroc"] = "auto"
    estimate_format: Literal["auto", "tum", "kitti", "euroc"] = "auto"
    reference_times: str | None = None
    estimate_times: str | None = None
    align: Alignment = "se3"
    max_time_diff: float = Field(0.01, gt=0.0)
    duplicates: Duplicates = "drop"
    rpe: RpeOptions = Field(default_factory=RpeOptions)
    output: str = "eval.json"


def _read(path: str, fmt: str, times: str | None, duplicates: Duplicates, role: str) -> Trajectory:
    """A trajectory file, or a bag's topic (``drive.bag:/topic``)."""
    try:
        bag = split_bag_source(path)
        if bag is not None:
            return read_bag_trajectory(bag[0], bag[1], duplicates)
        return read_trajectory(path, fmt, times, duplicates)  # type: ignore[arg-type]
    except (TrajectoryError, DataError) as exc:
        raise DataError(f"{role}: {exc}") from None


def _resolved(source: str) -> str:
    """The absolute path of a file, or of a bag with its topic."""
    bag = split_bag_source(source)
    return f"{bag[0].resolve()}:{bag[1]}" if bag is not None else str(Path(source).resolve())


def coverage(reference: Trajectory, estimate: Trajectory) -> float | None:
    """The share of the reference's time span the estimate's span overlaps (None for a single instant)."""
    start, end = float(reference.timestamps[0]), float(reference.timestamps[-1])
    if end <= start:
        return None
    overlap = min(end, float(estimate.timestamps[-1])) - max(start, float(estimate.timestamps[0]))
    return max(0.0, overlap) / (end - start)


def evaluate(options: EvalOptions) -> dict[str, Any]:
    """ATE, RPE translation and RPE rotation of ``estimate`` against ``reference``."""
    reference = _read(
        options.reference, options.reference_format, options.reference_times, options.duplicates, "reference"
    )
    estimate = _read(options.estimate, options.estimate_format, options.estimate_times, options.duplicates, "estimate")
    common = {"align": options.align, "max_time_diff": options.max_time_diff}
    rpe_args = {"delta": options.rpe.delta, "delta_unit": options.rpe.delta_unit, "all_pairs": options.rpe.all_pairs}
    results: dict[str, ErrorStatistics] = {
        "ate": ate(reference, estimate, **common),  # type: ignore[arg-type]
        "rpe_translation": rpe(reference, estimate, relation="translation", **rpe_args, **common),  # type: ignore[arg-type]
        "rpe_rotation": rpe(reference, estimate, relation="rotation", **rpe_args, **common),  # type: ignore[arg-type]
    }
    covered = coverage(reference, estimate)
    if covered is not None and covered < MIN_COVERAGE:
        log.warning(
            "the estimate covers %.0f %% of the reference's time span (estimate t=%.3f..%.3f s, reference "
            "t=%.3f..%.3f s): a truncated estimate is scored on the part it has",
            100.0 * covered,
            estimate.timestamps[0],
            estimate.timestamps[-1],
            reference.timestamps[0],
            reference.timestamps[-1],
        )
    return {
        "reference": _resolved(options.reference),
        "estimate": _resolved(options.estimate),
        "reference_poses": len(reference),
        "estimate_poses": len(estimate),
        "matched_pairs": results["ate"].pairs,
        "coverage": covered,
        "duplicates": options.duplicates,
        "align": options.align,
        "max_time_diff": options.max_time_diff,
        "rpe_delta": options.rpe.delta,
        "rpe_delta_unit": options.rpe.delta_unit,
        "rpe_all_pairs": options.rpe.all_pairs,
        "units": {"ate": "m", "rpe_translation": "m", "rpe_rotation": "deg"},
        **{name: stats.as_dict() for name, stats in results.items()},
    }


def table(report: dict[str, Any]) -> str:
    """The figures as a small text table."""
    labels = {"ate": "ATE (m)", "rpe_translation": "RPE translation (m)", "rpe_rotation": "RPE rotation (deg)"}
    head = f"  {'metric':<21}{'rmse':>11}{'mean':>11}{'median':>11}{'std':>11}{'min':>11}{'max':>11}{'pairs':>8}"
    lines = [
        f"sgf-eval: {Path(report['estimate']).name} vs {Path(report['reference']).name} "
        f"({report['align']} alignment; RPE per {report['rpe_delta']:g} {report['rpe_delta_unit']})",
        head,
    ]
    for key, label in labels.items():
        s = report[key]
        values = "".join(f"{s[k]:>11.6f}" for k in ("rmse", "mean", "median", "std", "min", "max"))
        lines.append(f"  {label:<21}{values}{s['pairs']:>8d}")
    covered = report.get("coverage")
    span = "" if covered is None else f"; the estimate spans {100 * covered:.0f} % of the reference's time"
    lines.append(
        f"  {report['matched_pairs']} pose pairs matched within {report['max_time_diff']:g} s (estimate "
        f"{report['estimate_poses']} poses, reference {report['reference_poses']}{span})"
    )
    return "\n".join(lines)


@hydra.main(config_path=str(config_dir()), config_name="sgf_eval", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> float:
    """Compute, print and write the trajectory errors; returns the ATE RMSE (for sweeps)."""
    container = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(container, dict)
    raw = {str(k): v for k, v in container.items() if k != "hydra"}
    for key in ("reference", "estimate"):
        if not raw.get(key):
            raise DataError(f"give the {key} trajectory: {USAGE} (or reference=<file> estimate=<file>)")
    options: EvalOptions = validate_options("sgf-eval", EvalOptions, raw)
    report = evaluate(options)
    output = Path(options.output)
    if not output.is_absolute():
        output = Path(HydraConfig.get().runtime.output_dir) / output
    atomic_write_json(output, report)
    print(table(report))
    print(f"\n  {output}", flush=True)
    return float(report["ate"]["rmse"])


#: The ``sgf-eval`` console script: ``sgf-eval REFERENCE ESTIMATE`` or ``reference=... estimate=...``.
main = console(app, positional=("reference", "estimate"), usage=USAGE)

if __name__ == "__main__":
    main()
