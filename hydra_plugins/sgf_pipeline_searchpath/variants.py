"""Hydra config source ``sgf-defaults://``: every variant's config node, made from its Params defaults.

A parameter's default is written once, in its pydantic Params; ``conf/`` holds only presets (a
variant with other settings). The source answers ``<kind>/<variant>`` for every registered stage
variant, so ``sgf-run loop=icp`` and ``sgf-run loop.gate.probability=0.99`` work with no YAML, and a
third-party plugin's variant is selectable as soon as it is installed.
"""

from __future__ import annotations

from typing import Any

from hydra.core.object_type import ObjectType
from hydra.plugins.config_source import ConfigLoadError, ConfigResult, ConfigSource

_NODES: dict[str, dict[str, Any]] | None = None


def _nodes() -> dict[str, dict[str, Any]]:
    """The code's config nodes, built on first use (loading the plugins) and kept for the process."""
    global _NODES
    if _NODES is None:
        from sgf_pipeline.registry import code_config_nodes

        _NODES = code_config_nodes()
    return _NODES


def _strip(path: str) -> str:
    path = path.strip("/")
    return path[: -len(".yaml")] if path.endswith(".yaml") else path


class SgfDefaultsConfigSource(ConfigSource):
    """The config nodes of the installed stage variants and observers, at their code defaults."""

    @staticmethod
    def scheme() -> str:
        """``sgf-defaults://``."""
        return "sgf-defaults"

    def available(self) -> bool:
        """Always: the plugins are loaded on first use."""
        return True

    def load_config(self, config_path: str) -> ConfigResult:
        """The node of ``<kind>/<variant>``, ``<node>/<name>`` or the runner's config."""
        from omegaconf import OmegaConf

        node = _nodes().get(_strip(config_path))
        if node is None:
            raise ConfigLoadError(f"no stage variant or observer node {_strip(config_path)!r} is registered")
        return ConfigResult(
            provider=self.provider, path=self.full_path(), config=OmegaConf.create(node), header={"package": None}
        )

    def is_group(self, config_path: str) -> bool:
        """A stage kind or an observer node (Hydra's own groups are never asked of the plugins)."""
        path = _strip(config_path)
        if path == "":
            return True
        if path.split("/")[0] == "hydra":
            return False
        return any(key.startswith(path + "/") for key in _nodes())

    def is_config(self, config_path: str) -> bool:
        """A registered variant, observer preset or the runner's config."""
        path = _strip(config_path)
        return path.split("/")[0] != "hydra" and path in _nodes()

    def list(self, config_path: str, results_filter: ObjectType | None) -> list[str]:
        """The groups and configs under ``config_path``."""
        path = _strip(config_path)
        prefix = f"{path}/" if path else ""
        names: set[str] = set()
        for key in _nodes() if path.split("/")[0] != "hydra" else ():
            if key.startswith(prefix):
                head = key[len(prefix) :].split("/")[0]
                full = prefix + head
                if results_filter in (None, ObjectType.GROUP) and self.is_group(full):
                    names.add(head)
                if results_filter in (None, ObjectType.CONFIG) and full in _nodes():
                    names.add(head)
        return sorted(names)
