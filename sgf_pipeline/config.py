"""The composed configuration: made plain (resolved, without ``hydra``), then validated with pydantic."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic.config import JsonDict
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined, to_jsonable_python

from sgf_pipeline.errors import ConfigError

#: Keys of a stage's config node that are not the stage's parameters.
RESERVED_KEYS = ("name", "rename")

#: Top-level keys of a run's config besides the stage nodes (``hydra`` is Hydra's own and never validated).
TOP_LEVEL_KEYS = ("pipeline", "run", "plugins", "map")

#: The paper's pipeline, in data-flow order (docs/method.md).
PAPER_STAGES = ("dataset", "enhance", "ipm", "saliency", "detector", "descriptor", "association", "loop", "backend")

#: Stage kinds the shipped default config runs besides the paper's (extensions, docs/method.md).
EXTENSION_STAGES = ("odometry_scale",)


#: A parameter's ``json_schema_extra`` key: what its config node holds in place of the default, an
#: interpolation that wires a run-level key into the stage (``${oc.select:map.prior,null}``).
CONFIG_VALUE = "config_value"

#: The ``json_schema_extra`` of a stage parameter that takes the run's ``map.prior`` (a prior SGF map).
FROM_MAP_PRIOR: JsonDict = {CONFIG_VALUE: "${oc.select:map.prior,null}"}


def defaults_node(model: type[BaseModel], defaults: BaseModel | None = None) -> dict[str, Any]:
    """A model's defaults as a plain config node, the one place a parameter's default is written.

    Parameter groups become nested mappings, a parameter without a default is Hydra's ``???``
    (it must be set), and a parameter that declares a :data:`CONFIG_VALUE` holds that instead.
    """
    node: dict[str, Any] = {}
    for key, info in model.model_fields.items():
        extra = info.json_schema_extra
        if isinstance(extra, dict) and CONFIG_VALUE in extra:
            node[key] = extra[CONFIG_VALUE]
            continue
        value = getattr(defaults, key) if defaults is not None else info.get_default(call_default_factory=True)
        if isinstance(value, BaseModel):
            node[key] = defaults_node(type(value), value)
        else:
            node[key] = "???" if value is PydanticUndefined else to_jsonable_python(value)
    return node


def config_dir() -> Path:
    """The ``conf/`` folder: inside the installed package, or at the top of a checkout."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "conf", here.parent / "conf"):
        if (candidate / ".sgf_pipeline_conf").is_file():
            return candidate
    raise ConfigError(f"the configuration folder conf/ was not found next to {here}; reinstall sgf-pipeline")


class RunOptions(BaseModel):
    """Options of the runner itself (config node ``run``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    keyframe_distance: float = Field(
        0.0, ge=0.0, description="process a frame once the odometry moved this far (m) since the last one; 0 = all"
    )
    keyframe_angle: float = Field(
        0.2, gt=0.0, description="...or turned this much (rad) since the last processed frame"
    )
    max_frames: int | None = Field(None, ge=1, description="stop after this many dataset frames")
    progress: bool = Field(True, description="show a progress bar over frames")
    overwrite: bool = Field(
        False, description="replace the files of a finished or interrupted run found in the run directory"
    )
    plots: bool = Field(True, description="write the trajectory plot and report.md")
    torch_threads: int | None = Field(
        None, ge=1, description="torch intra-op threads (1 inside parallel sweeps); null = torch's default"
    )
    ate_max_time_diff: float = Field(0.01, gt=0.0, description="timestamp association tolerance for ATE (s)")
    tag: str | None = Field(
        None,
        description="a label of the run for reports (a perturbed robot or world of the robustness suite: "
        "`<variant>/<severity>`)",
    )
    cache: bool = Field(
        True,
        description="keep the outputs of stages that depend only on the dataset and the stages before them, and "
        "reuse them in later runs (sgf_pipeline.cache; `sgf-cache` shows and clears it)",
    )
    cache_dir: str | None = Field(
        None,
        description="the stage cache's folder; null = stages/ in $SGF_PIPELINE_CACHE, else "
        "~/.cache/sgf_pipeline/stages ($SGF_PIPELINE_STAGE_CACHE=off turns the cache off for every run)",
    )
    cache_max_gb: float = Field(
        20.0, gt=0.0, description="the stage cache's size bound (GB): the least recently used entries go first"
    )
    read_ahead_seconds: float = Field(
        30.0,
        gt=0.0,
        description="a keyframe waits at most this long (s of sequence time) for the path a stage's read_ahead "
        "asks for (a robot standing still); then it goes on with the path read so far",
    )


class PluginOptions(BaseModel):
    """Which entry-point plugins a run may load (config node ``plugins``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    allow: list[str] | None = Field(None, description="load only these entry points (a deployment allow-list)")
    block: list[str] = Field(default_factory=list, description="never load these entry points")


class StageConfig(BaseModel):
    """One stage's node: the variant name, an input rename map, and the variant's parameters."""

    model_config = ConfigDict(frozen=True)

    kind: str
    name: str
    rename: dict[str, str] = Field(default_factory=dict)
    params: dict[str, Any] = Field(default_factory=dict)


class PipelineConfig(BaseModel):
    """The whole validated configuration of a run."""

    model_config = ConfigDict(frozen=True)

    pipeline: tuple[str, ...]
    stages: dict[str, StageConfig]
    run: RunOptions = Field(default_factory=RunOptions)
    plugins: PluginOptions = Field(default_factory=PluginOptions)


def _find_target(node: Any, path: str) -> str | None:
    if isinstance(node, Mapping):
        for key, value in node.items():
            if key == "_target_":
                return f"{path}._target_"
            found = _find_target(value, f"{path}.{key}")
            if found:
                return found
    elif isinstance(node, (list, tuple)):
        for i, value in enumerate(node):
            found = _find_target(value, f"{path}[{i}]")
            if found:
                return found
    return None


def _located(model: type[BaseModel], loc: tuple[int | str, ...]) -> tuple[type[BaseModel], FieldInfo | None]:
    """The model holding the key at ``loc`` (into nested parameter groups) and that key's field, if it has one."""
    owner, field = model, None
    for depth, part in enumerate(loc):
        field = owner.model_fields.get(str(part))
        inner = field.annotation if field is not None else None
        if depth == len(loc) - 1 or not (isinstance(inner, type) and issubclass(inner, BaseModel)):
            return owner, field  # the key itself, or the list or mapping holding the item
        owner = inner
    return owner, field


def format_validation_error(group: str, model: type[BaseModel], error: ValidationError) -> str:
    """One line per problem: the config key, what is wrong, and the expected type.

    A key inside a nested parameter group is named with dots (``loop.gate.sigma_yaw_deg``).
    """
    lines = []
    for item in error.errors():
        loc = ".".join(str(p) for p in item["loc"])
        key = f"{group}.{loc}" if loc else group
        owner, field = _located(model, item["loc"]) if item["loc"] else (model, None)
        expected = ""
        if field is not None and field.annotation is not None:
            ann = field.annotation
            expected = f"; expected {getattr(ann, '__name__', None) or str(ann).replace('typing.', '')}"
        if item["type"] == "value_error" and not item["loc"]:  # a model's own check: its message says it all
            lines.append(f"{key}: {item['ctx']['error']}")
        elif item["type"] == "extra_forbidden":
            known = ", ".join(owner.model_fields) or "none"
            where = "this variant" if owner is model else key.rsplit(".", 1)[0]
            lines.append(f"{key}: unknown parameter (parameters of {where}: {known})")
        else:
            lines.append(f"{key}: {item['msg']} (got {item.get('input')!r}){expected}")
    return "\n  ".join(lines)


def validate_options(group: str, model: type[BaseModel], values: Mapping[str, Any] | None) -> Any:
    """Validate a plain config node against a pydantic model, with a clear error."""
    if values is not None and not isinstance(values, Mapping):
        known = ", ".join(model.model_fields)
        raise ConfigError(f"{group}: must be a mapping of options ({known}), got {values!r:.80}")
    try:
        return model.model_validate(dict(values or {}))
    except ValidationError as exc:
        raise ConfigError(f"invalid configuration:\n  {format_validation_error(group, model, exc)}") from None


def _check_finite(node: Any, path: str) -> None:
    if isinstance(node, float) and not math.isfinite(node):
        raise ConfigError(f"{path}: {node!r} is not a finite number")
    if isinstance(node, Mapping):
        for k, v in node.items():
            _check_finite(v, f"{path}.{k}")
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            _check_finite(v, f"{path}[{i}]")


def check_keys(raw: Mapping[str, Any], kinds: Iterable[str], observers: Iterable[str] = ()) -> None:
    """Refuse top-level keys that are neither runner options, nor the node of a stage kind or an observer (typos)."""
    # a blocked plugin's node of the default config may stay
    observers = sorted(observers)
    known = set(TOP_LEVEL_KEYS) | set(kinds) | set(observers) | set(PAPER_STAGES) | set(EXTENSION_STAGES) | {"hydra"}
    unknown = sorted(str(k) for k in raw if k not in known)
    if unknown:
        nodes = f" and the observers' nodes ({', '.join(observers)})" if observers else ""
        raise ConfigError(
            f"unknown top-level key(s) {unknown}: a config holds {', '.join(TOP_LEVEL_KEYS)}, one node per "
            f"stage kind ({', '.join(sorted(set(kinds)))}){nodes}; check the spelling, or install the plugin that "
            "registers that stage kind or node"
        )


def parse_config(raw: Mapping[str, Any]) -> PipelineConfig:
    """Split a composed (plain, resolved) config into validated run options and stage nodes."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"a configuration is a mapping (pipeline, run, plugins, stage nodes), got {raw!r:.80}")
    target = _find_target({k: v for k, v in raw.items() if k != "hydra"}, "")
    if target:
        target = target.lstrip(".")
        group = target.split(".")[0].split("[")[0]
        raise ConfigError(
            f"{target}: `_target_` is refused. Variants are chosen by registered name only "
            f"(`{group}=<variant>`), so that a config file can never import code."
        )
    if "pipeline" not in raw:
        raise ConfigError("the config has no `pipeline` list (the stage kinds to run, dataset first)")
    kinds = raw["pipeline"]
    if isinstance(kinds, str) or not isinstance(kinds, (list, tuple)) or not kinds:
        raise ConfigError(f"`pipeline` must be a non-empty list of stage kinds, got {kinds!r}")
    for kind in kinds:
        if not isinstance(kind, str) or not kind:
            raise ConfigError(f"`pipeline` lists stage kinds by name; {kind!r} is not a name")
    if len(set(kinds)) != len(kinds):
        raise ConfigError(f"`pipeline` lists a stage kind twice: {list(kinds)}")
    stages: dict[str, StageConfig] = {}
    for kind in kinds:
        node = raw.get(kind)
        if node is None:
            raise ConfigError(
                f"{kind}: listed in `pipeline` but has no config node; choose a variant with `{kind}=<variant>`"
            )
        if not isinstance(node, Mapping):
            raise ConfigError(f"{kind}: the config node must be a mapping with a `name` key, got {node!r}")
        name = node.get("name")
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{kind}: the config node needs a `name` (the variant), got {name!r}")
        rename = node.get("rename") or {}
        if not isinstance(rename, Mapping) or not all(isinstance(v, str) for v in rename.values()):
            raise ConfigError(f"{kind}.rename must map input names to output names, got {rename!r}")
        params = {k: v for k, v in node.items() if k not in RESERVED_KEYS}
        _check_finite(params, kind)
        stages[kind] = StageConfig(kind=kind, name=name, rename=dict(rename), params=params)
    run = validate_options("run", RunOptions, raw.get("run"))
    plugins = validate_options("plugins", PluginOptions, raw.get("plugins"))
    return PipelineConfig(pipeline=tuple(kinds), stages=stages, run=run, plugins=plugins)


def plain_config(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """A composed config as the plain, resolved mapping a run saves as ``config.yaml`` (without ``hydra``)."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(cfg, DictConfig):
        try:
            container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
        except OmegaConfBaseException as exc:
            raise ConfigError(describe_omegaconf_error(exc)) from None
        assert isinstance(container, dict)
        return {str(k): v for k, v in container.items() if k != "hydra"}
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"a configuration is a mapping (pipeline, run, plugins, stage nodes), got {cfg!r:.80}")
    return {str(k): v for k, v in dict(cfg).items() if k != "hydra"}


def describe_omegaconf_error(exc: Exception) -> str:
    """One paragraph about a config value OmegaConf cannot resolve, with the resolvers on offer."""
    from omegaconf.basecontainer import BaseContainer

    key = getattr(exc, "full_key", None) or "?"
    detail = [
        line.strip()
        for line in str(exc).splitlines()
        if line.strip() and not line.strip().startswith(("full_key:", "object_type=", "reference_type="))
    ]
    message = " ".join(" ".join(detail).split())
    resolvers = ", ".join(sorted(BaseContainer._resolvers))
    return (
        f"{key}: the value cannot be resolved: {message}. Interpolations may name other keys (${{run.max_frames}}) "
        f"or the registered resolvers ({resolvers}); none of them imports or runs code"
    )
