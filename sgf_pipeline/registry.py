"""Plugin discovery (pluggy, entry-point group ``sgf_pipeline``): the plugin manager and its stage registry."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, cast, get_args

import pluggy
from pydantic import BaseModel

from sgf_pipeline import hookspecs, observers
from sgf_pipeline.config import TOP_LEVEL_KEYS, PluginOptions, RunOptions, defaults_node
from sgf_pipeline.errors import PluginError
from sgf_pipeline.variants import BLOCK_ENV, NAME, StageRegistry

ENTRY_POINT_GROUP = "sgf_pipeline"
ALLOW_ENV = "SGF_PIPELINE_PLUGINS"


def _names_from_env(var: str) -> set[str] | None:
    raw = os.environ.get(var)
    if raw is None:
        return None
    return {n.strip() for n in raw.split(",") if n.strip()}


@dataclass
class LoadedPlugins:
    """The plugin manager, the registry built from its plugins, and the observers' config nodes."""

    manager: pluggy.PluginManager
    registry: StageRegistry
    #: top-level config node -> its options model (``sgf_observer_options``)
    observer_options: dict[str, type[BaseModel]] = field(default_factory=dict)


def load_plugins(
    allow: Iterable[str] | None = None,
    block: Iterable[str] = (),
    extra: Sequence[tuple[str, object]] = (),
) -> LoadedPlugins:
    """Load the built-in observers and every entry-point plugin, then collect their stage variants.

    ``allow`` (or ``$SGF_PIPELINE_PLUGINS``, comma-separated) restricts the entry points loaded;
    ``block`` (or ``$SGF_PIPELINE_DISABLED_PLUGINS``) excludes some; ``extra`` registers plugin
    objects directly (``(name, module_or_object)``), as tests and embedding applications do.
    """
    manager = pluggy.PluginManager(hookspecs.PROJECT)
    manager.add_hookspecs(hookspecs.PipelineHooks)
    for name, factory in observers.BUILTIN_OBSERVERS:
        manager.register(factory(), name=name)

    env_allow = _names_from_env(ALLOW_ENV)
    allowed = set(allow) if allow is not None else env_allow
    blocked = set(block) | (_names_from_env(BLOCK_ENV) or set())
    distributions: dict[str, str | None] = {}
    seen: set[str] = set()
    for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        if ep.name in seen:
            continue
        seen.add(ep.name)
        if (allowed is not None and ep.name not in allowed) or ep.name in blocked:
            continue
        dist = ep.dist.name if ep.dist is not None else None
        try:
            plugin = ep.load()
        except Exception as exc:
            raise PluginError(
                f"plugin {ep.name!r} ({ep.value}) from distribution {dist!r} failed to import: "
                f"{type(exc).__name__}: {exc}. Fix or uninstall it, or block it with {BLOCK_ENV}={ep.name}"
            ) from exc
        manager.register(plugin, name=ep.name)
        distributions[ep.name] = dist
    if allowed is not None:
        missing = sorted(allowed - seen)
        if missing:
            raise PluginError(
                f"allowed plugin(s) {', '.join(missing)} are not installed; installed entry points: "
                f"{', '.join(sorted(seen)) or 'none'}"
            )
    for name, plugin in extra:
        manager.register(plugin, name=name)
        distributions[name] = None
    _check_pending(manager, entry_points=seen)

    registry = StageRegistry()
    for impl in manager.hook.sgf_register_stages.get_hookimpls():
        impl.function(registry=registry._scoped(impl.plugin_name, distributions.get(impl.plugin_name)))
    return LoadedPlugins(manager, registry, _observer_options(manager, registry))


def _check_pending(manager: pluggy.PluginManager, entry_points: set[str]) -> None:
    """Refuse a plugin that implements a hook no hookspec declares (a misspelt hook would never be called)."""
    try:
        manager.check_pending()
    except pluggy.PluginValidationError as exc:
        callers = {name: c for name, c in vars(manager.hook).items() if isinstance(c, pluggy.HookCaller)}
        unknown = [
            (impl.plugin_name, name)
            for name, caller in callers.items()
            if not caller.has_spec()
            for impl in caller.get_hookimpls()
            if not impl.optionalhook
        ]
        plugin, hook = unknown[0] if unknown else (manager.get_name(exc.plugin), "?")
        known = ", ".join(sorted(name for name, caller in callers.items() if caller.has_spec()))
        block = f", or block the plugin with {BLOCK_ENV}={plugin}" if plugin in entry_points else ""
        raise PluginError(
            f"plugin {plugin!r} implements hook {hook!r}, which no hookspec declares; the hooks are: {known}. "
            f"Rename or remove the hook{block}"
        ) from None


def _observer_options(manager: pluggy.PluginManager, registry: StageRegistry) -> dict[str, type[BaseModel]]:
    """The config nodes the observer plugins declare, checked: new names, models that refuse unknown keys."""
    owners: dict[str, str] = {}
    nodes: dict[str, type[BaseModel]] = {}
    for impl in manager.hook.sgf_observer_options.get_hookimpls():
        where = f"plugin {impl.plugin_name!r}"
        declared = cast("dict[str, Any]", impl.function() or {})
        for name, model in declared.items():
            if not isinstance(name, str) or not NAME.match(name):
                raise PluginError(f"{where}: an observer's config node must be a lower-case identifier, got {name!r}")
            if name in TOP_LEVEL_KEYS or name in registry.kinds():
                raise PluginError(f"{where}: config node {name!r} is taken by the runner or a stage kind")
            if name in owners:
                raise PluginError(
                    f"config node {name!r} is declared by plugins {owners[name]!r} and {impl.plugin_name!r}; "
                    f"block one with {BLOCK_ENV}=<entry point name>"
                )
            if not (isinstance(model, type) and issubclass(model, BaseModel)) or (
                model.model_config.get("extra") != "forbid"
            ):
                raise PluginError(f"{where}: the options of {name!r} must be a pydantic model refusing unknown keys")
            owners[name] = impl.plugin_name
            nodes[name] = model
    return nodes


#: The root config of the runner's own options at their defaults (``conf/config.yaml`` lists it first).
RUNNER_CONFIG = "runner"


def code_config_nodes() -> dict[str, dict[str, Any]]:
    """The config nodes that the code's defaults make, by config path (what ``conf/`` need not repeat).

    ``<kind>/<variant>`` for each stage variant (its ``name`` and its Params defaults), ``<node>/<name>``
    for each observer node whose options model has a default ``name``, and :data:`RUNNER_CONFIG` for
    the runner's ``run`` and ``plugins`` nodes. Plugins load as for a run (the environment's allow and
    block lists); a plugin that fails to load contributes nothing here, and the run reports it.
    """
    try:
        loaded = [load_plugins()]
    except PluginError:
        loaded = []
        for ep in {e.name for e in metadata.entry_points(group=ENTRY_POINT_GROUP)}:
            try:
                loaded.append(load_plugins(allow=[ep]))
            except PluginError:
                continue
    nodes: dict[str, dict[str, Any]] = {
        RUNNER_CONFIG: {"run": defaults_node(RunOptions), "plugins": defaults_node(PluginOptions)}
    }
    for plugins in loaded:
        for variant in plugins.registry:
            nodes[f"{variant.kind}/{variant.name}"] = {"name": variant.name, **defaults_node(variant.params_model)}
        for node, model in plugins.observer_options.items():
            name = model.model_fields["name"].default if "name" in model.model_fields else None
            if isinstance(name, str):
                nodes[f"{node}/{name}"] = defaults_node(model)
    return nodes


def describe_params(
    model: type[BaseModel], defaults: BaseModel | None = None, prefix: str = ""
) -> list[tuple[str, str, Any, str]]:
    """``(key, type, default, description)`` of each parameter of a Params model.

    A parameter that is itself a model (a group of parameters such as ``gate``) gives one row per
    parameter inside it, keyed with dots (``gate.sigma_yaw_deg``) as a config override names it.
    """
    rows = []
    for field_name, info in model.model_fields.items():
        annotation = info.annotation
        default = getattr(defaults, field_name) if defaults is not None else info.get_default(call_default_factory=True)
        if isinstance(annotation, type) and issubclass(annotation, BaseModel) and isinstance(default, annotation):
            rows += describe_params(annotation, default, f"{prefix}{field_name}.")
            continue
        type_name = str(annotation).replace("typing.", "")  # list[str], Literal['a', 'b'], float | None
        if isinstance(annotation, type) and not get_args(annotation):
            type_name = annotation.__name__
        if isinstance(default, BaseModel):
            default = default.model_dump()
        rows.append((prefix + field_name, type_name, default, info.description or ""))
    return rows
