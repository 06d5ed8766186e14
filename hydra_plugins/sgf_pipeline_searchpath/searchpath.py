"""The sgf apps' search path: every ``sgf_pipeline.conf`` package, then the variants' code defaults.

The code defaults come last (``sgf-defaults://``, variants.py), so a YAML preset of the same name wins.

A third-party plugin that ships ``ipm/myipm.yaml`` in its package ``my_plugin.conf`` declares
``[project.entry-points."sgf_pipeline.conf"] my_plugin = "my_plugin.conf"``; then
``sgf-run ipm=myipm`` composes its config with no change to this project.
"""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin

CONF_GROUP = "sgf_pipeline.conf"
MARKER = ".sgf_pipeline_conf"


def _is_sgf_conf(path: str | None) -> bool:
    if not path:
        return False
    if path.startswith("file://"):
        path = path[len("file://") :]
    return (Path(path) / MARKER).is_file()


class SgfPipelineSearchPathPlugin(SearchPathPlugin):
    """Extends the search path of the sgf-pipeline apps only (their conf/ holds a marker file)."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        """Append ``pkg://<package>`` for each plugin's config package."""
        if not any(_is_sgf_conf(element.path) for element in search_path.get_path()):
            return
        for ep in sorted(metadata.entry_points(group=CONF_GROUP), key=lambda e: e.name):
            search_path.append(provider=f"sgf-plugin:{ep.name}", path=f"pkg://{ep.value}")
        # Last: the variants' code defaults, for every variant no YAML above names (variants.py).
        search_path.append(provider="sgf-pipeline", path="sgf-defaults://")
