"""Plugin discovery (pluggy, entry-point group ``sgf_pipeline``) and the registry of stage variants."""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, cast

import pluggy
from pydantic import BaseModel

from sgf_pipeline import hookspecs
from sgf_pipeline.config import TOP_LEVEL_KEYS
from sgf_pipeline.errors import ConfigError, PluginError
from sgf_pipeline.stage import Dataset, Stage, StageClass, StageParams, StageSignature, signature_of

ENTRY_POINT_GROUP = "sgf_pipeline"
ALLOW_ENV = "SGF_PIPELINE_PLUGINS"
BLOCK_ENV = "SGF_PIPELINE_DISABLED_PLUGINS"
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True)
class VariantInfo:
    """A registered stage variant and where it came from."""

    kind: str
    name: str
    cls: StageClass
    plugin: str
    distribution: str | None
    signature: StageSignature

    @property
    def params_model(self) -> type[StageParams]:
        """The variant's pydantic ``Params`` model."""
        return self.cls.Params

    def describe_source(self) -> str:
        """``plugin (distribution)`` for listings."""
        return f"{self.plugin} ({self.distribution})" if self.distribution else self.plugin


class StageRegistry:
    """All stage variants offered by the loaded plugins, indexed by ``kind`` and ``name``."""

    def __init__(self) -> None:
        self._variants: dict[str, dict[str, VariantInfo]] = {}
        self._plugin = "<direct>"
        self._distribution: str | None = None

    def _scoped(self, plugin: str, distribution: str | None) -> StageRegistry:
        view = StageRegistry.__new__(StageRegistry)
        view._variants = self._variants
        view._plugin = plugin
        view._distribution = distribution
        return view

    def add(self, cls: StageClass) -> None:
        """Register a stage class (a :class:`Stage` or :class:`Dataset` subclass)."""
        where = f"plugin {self._plugin!r}"
        if not isinstance(cls, type) or not issubclass(cls, (Stage, Dataset)):
            raise PluginError(f"{where} registered {cls!r}, which is not a Stage or Dataset subclass")
        for attr in ("kind", "name", "output"):
            value = getattr(cls, attr, None)
            if not isinstance(value, str) or not _NAME.match(value):
                raise PluginError(f"{where}: {cls.__qualname__}.{attr} must be a lower-case identifier, got {value!r}")
        params = getattr(cls, "Params", None)
        if not isinstance(params, type) or not issubclass(params, BaseModel):
            raise PluginError(f"{where}: {cls.__qualname__}.Params must be a pydantic model")
        if params.model_config.get("extra") != "forbid":
            raise PluginError(
                f"{where}: {cls.__qualname__}.Params must refuse unknown keys; derive it from StageParams"
            )
        try:
            signature = signature_of(cls)
        except TypeError as exc:
            raise PluginError(f"{where}: {exc}") from None
        existing = self._variants.get(cls.kind, {}).get(cls.name)
        if existing is not None and existing.cls is not cls:
            raise PluginError(
                f"variant {cls.kind}={cls.name} is registered twice: by {existing.describe_source()} "
                f"and by {self._plugin}; block one with {BLOCK_ENV}=<entry point name>"
            )
        self._variants.setdefault(cls.kind, {})[cls.name] = VariantInfo(
            cls.kind, cls.name, cls, self._plugin, self._distribution, signature
        )

    def kinds(self) -> list[str]:
        """Registered stage kinds, sorted."""
        return sorted(self._variants)

    def variants(self, kind: str) -> list[VariantInfo]:
        """Registered variants of one kind, sorted by name."""
        return [self._variants[kind][n] for n in sorted(self._variants.get(kind, {}))]

    def get(self, kind: str, name: str) -> VariantInfo:
        """The variant ``kind=name``; a clear error lists the registered ones when it is unknown."""
        if kind not in self._variants:
            known = ", ".join(self.kinds()) or "none"
            raise ConfigError(
                f"{kind}: no plugin registers stages of kind {kind!r}. Registered kinds: {known}. "
                "Install the plugin that provides it, or remove it from `pipeline`."
            )
        found = self._variants[kind].get(name)
        if found is None:
            known = ", ".join(sorted(self._variants[kind]))
            raise ConfigError(
                f"{kind}: unknown variant {name!r}. Registered variants of {kind!r}: {known}. "
                f"Choose one with `{kind}=<variant>`; `sgf-plugins` lists them with their parameters."
            )
        return found

    def __iter__(self) -> Any:
        for kind in self.kinds():
            yield from self.variants(kind)


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
    from sgf_pipeline import observers

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

    registry = StageRegistry()
    for impl in manager.hook.sgf_register_stages.get_hookimpls():
        impl.function(registry=registry._scoped(impl.plugin_name, distributions.get(impl.plugin_name)))
    return LoadedPlugins(manager, registry, _observer_options(manager, registry))


def _observer_options(manager: pluggy.PluginManager, registry: StageRegistry) -> dict[str, type[BaseModel]]:
    """The config nodes the observer plugins declare, checked: new names, models that refuse unknown keys."""
    owners: dict[str, str] = {}
    nodes: dict[str, type[BaseModel]] = {}
    for impl in manager.hook.sgf_observer_options.get_hookimpls():
        where = f"plugin {impl.plugin_name!r}"
        declared = cast("dict[str, Any]", impl.function() or {})
        for name, model in declared.items():
            if not isinstance(name, str) or not _NAME.match(name):
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


def describe_params(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str, Any, str]]:
    """``(name, type, default, description)`` of each parameter of a Params model (nested models: dotted names)."""
    rows = []
    for field_name, info in model.model_fields.items():
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            rows.extend(describe_params(annotation, f"{prefix}{field_name}."))
            continue
        type_name = getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")
        default = info.get_default(call_default_factory=True)
        if isinstance(default, BaseModel):
            default = default.model_dump()
        rows.append((prefix + field_name, type_name, default, info.description or ""))
    return rows
