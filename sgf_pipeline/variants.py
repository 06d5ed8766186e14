"""The registry of stage variants: each registered stage class, indexed by ``kind`` and ``name``."""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass

from pydantic import BaseModel

from sgf_pipeline.errors import ConfigError, PluginError
from sgf_pipeline.stage import Dataset, Stage, StageClass, StageParams, StageSignature, signature_of

#: The environment variable listing entry-point plugins never to load (comma-separated).
BLOCK_ENV = "SGF_PIPELINE_DISABLED_PLUGINS"
#: What a stage's kind, name and output, and an observer's config node, look like.
NAME = re.compile(r"^[a-z][a-z0-9_]*$")


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
            if not isinstance(value, str) or not NAME.match(value):
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

    def __iter__(self) -> Iterator[VariantInfo]:
        for kind in self.kinds():
            yield from self.variants(kind)
