"""Finished runs read back from their directories (metrics.json, config.yaml) and the config keys a sweep varied."""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sgf_pipeline.errors import DataError
from sgf_pipeline.io import read_text, read_yaml

METRIC_LOOP_KEYS = (
    "pairs_found",
    "pairs_total",
    "pairs_found_reverse",
    "pairs_total_reverse",
    "closed",
    "closed_reverse",
    "false_closed",
)
IGNORED_KEYS = ("run.progress", "run.torch_threads", "run.overwrite", "plugins.")


@dataclass
class RunRecord:
    """One finished run: its directory, metrics and effective configuration."""

    path: Path
    metrics: dict[str, Any]
    config: dict[str, Any]

    @property
    def sequence(self) -> str:
        """The dataset variant the run used."""
        return str(self.metrics.get("sequence") or self.config.get("dataset", {}).get("name", "?"))

    @property
    def seed(self) -> Any:
        """The dataset seed, when the dataset has one."""
        return self.config.get("dataset", {}).get("seed")


def flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    """A config's nested keys as dotted ones (``ipm.name``), lists as JSON."""
    out: dict[str, Any] = {}
    if isinstance(node, dict):
        for key, value in node.items():
            out.update(flatten(value, f"{prefix}{key}."))
    else:
        out[prefix[:-1]] = json.dumps(node) if isinstance(node, list) else node
    return out


def find_runs(root: str | Path) -> list[RunRecord]:
    """Every finished run below ``root`` (a run directory or a multirun directory)."""
    base = Path(root)
    if not base.exists():
        raise DataError(f"{base} does not exist; pass a run or multirun directory written by sgf-run")
    runs = []
    for metrics_path in sorted(base.rglob("metrics.json")):
        try:
            metrics = json.loads(read_text(metrics_path, "metrics file"))
        except json.JSONDecodeError as exc:
            raise DataError(f"{metrics_path} is not valid JSON ({exc}); was the run interrupted?") from None
        except RecursionError:
            raise DataError(f"{metrics_path} is not valid JSON (nested too deeply)") from None
        if not isinstance(metrics, dict):
            raise DataError(f"{metrics_path} holds a {type(metrics).__name__}, not the mapping sgf-run writes")
        _check_metrics(metrics_path, metrics)
        config_path = metrics_path.parent / "config.yaml"
        config = read_yaml(config_path, "run config") if config_path.exists() else {}
        if not isinstance(config, dict | None):
            raise DataError(f"{config_path} holds a {type(config).__name__}, not the mapping sgf-run writes")
        runs.append(RunRecord(metrics_path.parent, metrics, config or {}))
    if not runs:
        raise DataError(f"no metrics.json below {base}; pass a directory written by sgf-run")
    return runs


#: The numeric fields of metrics.json the report reads (each a number or null when present).
_NUMERIC_FIELDS = (
    ("ate_rmse_m", "odometry"),
    ("ate_rmse_m", "sgf"),
    ("sgf", "detected"),
    ("sgf", "total"),
    *(("loops", k) for k in METRIC_LOOP_KEYS),
    ("timing", "fps"),
    ("timing", "realtime_factor"),
    ("peak_rss_mb",),
)


def _check_metrics(path: Path, metrics: dict[str, Any]) -> None:
    """Refuse a metrics.json whose fields the report reads are not numbers (a hand-edited or foreign file)."""
    for keys in _NUMERIC_FIELDS:
        node: Any = metrics
        for depth, key in enumerate(keys):
            if node is None:
                break
            if not isinstance(node, dict):
                raise DataError(f"{path}: {'.'.join(keys[:depth])} must be a mapping, got {node!r:.40}")
            node = node.get(key)
        if node is not None and (isinstance(node, bool) or not isinstance(node, (int, float))):
            raise DataError(f"{path}: {'.'.join(keys)} must be a number or null, got {node!r:.40}")
    stages = value_at(metrics, "timing", "stages")
    if stages is not None and not (
        isinstance(stages, dict)
        and all(
            isinstance(row, dict)
            and (row.get("mean_ms") is None or (type(row["mean_ms"]) in (int, float)))
            and isinstance(row.get("variant", ""), str)
            for row in stages.values()
        )
    ):
        raise DataError(f"{path}: timing.stages must map stage kinds to {{variant, mean_ms, ...}}, got {stages!r:.60}")
    if not isinstance(metrics.get("sequence", ""), str):
        raise DataError(f"{path}: sequence must be a name, got {metrics['sequence']!r:.40}")


def swept_keys(runs: Iterable[RunRecord]) -> list[str]:
    """Config keys whose values differ between runs (except seeds and presentation options)."""
    flats = [flatten(r.config) for r in runs]
    keys = sorted(set().union(*flats)) if flats else []
    out = []
    for key in keys:
        if key == "dataset.seed" or key.startswith(IGNORED_KEYS):
            continue
        if key.startswith("dataset.") and key != "dataset.name":
            continue
        values = {json.dumps(f.get(key), sort_keys=True, default=str) for f in flats}
        if len(values) > 1:
            out.append(key)
    # a swept variant (``ipm.name``) brings its own parameters: those name no variant unless they
    # also differ between runs of the same variant
    chosen = {k.removesuffix(".name") for k in out if k.endswith(".name") and k != "dataset.name"}
    kept = []
    for key in out:
        stage = key.split(".", 1)[0]
        if stage in chosen and key != f"{stage}.name":
            within: dict[str, set[str]] = defaultdict(set)
            for f in flats:
                within[json.dumps(f.get(f"{stage}.name"), default=str)].add(
                    json.dumps(f.get(key), sort_keys=True, default=str)
                )
            if all(len(v) == 1 for v in within.values()):
                continue
        kept.append(key)
    return kept


def value_at(metrics: dict[str, Any], *path: str) -> Any:
    """The value at a path of nested keys of metrics.json; None where one is missing."""
    node: Any = metrics
    for p in path:
        if not isinstance(node, dict):
            return None
        node = node.get(p)
    return node
