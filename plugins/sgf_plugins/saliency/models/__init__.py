"""The saliency networks (PyTorch) and the one place that builds them from a variant's architecture parameters."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from torch import nn

#: Model names with a network, and the architecture parameters each one takes.
ARCHITECTURES: dict[str, tuple[str, ...]] = {
    "selfreformer": ("size", "global_dim", "level_depth", "crm_depth", "mlp_ratio"),
    "u2net": ("width",),
    "u2netp": ("width",),
    "ldf": ("resnet_depth", "resnet_width", "branch_width"),
}


def build_model(model: str, arch: Mapping[str, Any]) -> nn.Module:
    """A freshly initialised network of ``model`` with the architecture parameters ``arch``."""
    if model not in ARCHITECTURES:
        raise ValueError(f"no network named {model!r}; known: {', '.join(ARCHITECTURES)}")
    missing = [k for k in ARCHITECTURES[model] if k not in arch]
    if missing:
        raise ValueError(f"{model}: missing architecture parameters {missing}")
    if model == "selfreformer":
        from sgf_plugins.saliency.models.pvt_v2 import PvtV2Spec
        from sgf_plugins.saliency.models.selfreformer import SelfReformer, SelfReformerSpec

        spec = SelfReformerSpec(
            PvtV2Spec.named(str(arch["size"])),
            global_dim=int(arch["global_dim"]),
            level_depth=int(arch["level_depth"]),
            crm_depth=int(arch["crm_depth"]),
            mlp_ratio=int(arch["mlp_ratio"]),
        )
        return SelfReformer(spec)
    if model in ("u2net", "u2netp"):
        from sgf_plugins.saliency.models.u2net import U2NET_STAGES, U2NETP_STAGES, U2Net, U2NetSpec

        base = U2NET_STAGES if model == "u2net" else U2NETP_STAGES
        return U2Net(U2NetSpec.scaled(base, float(arch["width"])))
    from sgf_plugins.saliency.models.ldf import Ldf, LdfSpec
    from sgf_plugins.saliency.models.resnet import ResNetSpec

    return Ldf(LdfSpec(ResNetSpec(int(arch["resnet_depth"]), int(arch["resnet_width"])), int(arch["branch_width"])))


def architecture_of(model: str, params: Mapping[str, Any]) -> dict[str, Any]:
    """The architecture parameters of ``model`` picked from a variant's parameters."""
    return {k: params[k] for k in ARCHITECTURES[model]}
