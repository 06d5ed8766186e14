"""Salient ground feature detection (paper Sec. III-B): the ``saliency`` stage variants and their tools.

Registered variants: ``selfreformer`` (SelfReformer*, the paper's model), ``u2net``, ``u2netp``,
``ldf`` and ``classical``. Training (``sgf-train``), SOD evaluation (``sgf-sod-eval``), the SOD folder
format and the metrics live in the submodules; torch is imported only when a network is built.
"""

from __future__ import annotations

from sgf_pipeline import StageRegistry, hookimpl
from sgf_plugins.saliency.stages import VARIANTS


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the saliency variants."""
    for cls in VARIANTS:
        registry.add(cls)
