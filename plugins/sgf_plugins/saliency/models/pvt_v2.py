"""PVT-v2 encoder (Wang et al. 2022): overlapping patch embeddings, spatial-reduction attention, Mix-FFN."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

#: Embedding widths, heads, MLP ratios and depths per stage: the published sizes b0, b1, b2, and this
#: project's reduced size ``t`` for real-time CPU inference (half of b0's first widths, 64 at the last two).
PVT_V2_SIZES: dict[str, dict[str, tuple[int, ...]]] = {
    "t": {"dims": (16, 32, 64, 64), "heads": (1, 1, 2, 2), "mlp": (8, 8, 4, 4), "depths": (2, 2, 2, 2)},
    "b0": {"dims": (32, 64, 160, 256), "heads": (1, 2, 5, 8), "mlp": (8, 8, 4, 4), "depths": (2, 2, 2, 2)},
    "b1": {"dims": (64, 128, 320, 512), "heads": (1, 2, 5, 8), "mlp": (8, 8, 4, 4), "depths": (2, 2, 2, 2)},
    "b2": {"dims": (64, 128, 320, 512), "heads": (1, 2, 5, 8), "mlp": (8, 8, 4, 4), "depths": (3, 4, 6, 3)},
}
SR_RATIOS = (8, 4, 2, 1)


@dataclass(frozen=True)
class PvtV2Spec:
    """The widths and depths of a four-stage PVT-v2 encoder."""

    dims: tuple[int, int, int, int]
    heads: tuple[int, int, int, int]
    mlp: tuple[int, int, int, int]
    depths: tuple[int, int, int, int]
    sr: tuple[int, int, int, int] = SR_RATIOS

    @classmethod
    def named(cls, size: str) -> PvtV2Spec:
        """One of the sizes ``t``, ``b0``, ``b1``, ``b2``."""
        if size not in PVT_V2_SIZES:
            raise ValueError(f"unknown PVT-v2 size {size!r}; known: {', '.join(PVT_V2_SIZES)}")
        s = PVT_V2_SIZES[size]
        return cls(s["dims"], s["heads"], s["mlp"], s["depths"])  # type: ignore[arg-type]


class OverlapPatchEmbed(nn.Module):
    """Overlapping patch embedding: a strided convolution followed by layer norm."""

    def __init__(self, in_ch: int, dim: int, patch: int, stride: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_ch, dim, kernel_size=patch, stride=stride, padding=patch // 2)
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, int, int]:
        """Tokens ``(B, H*W, C)`` and the token grid size."""
        x = self.proj(x)
        _, _, h, w = x.shape
        return self.norm(x.flatten(2).transpose(1, 2)), h, w


class SpatialReductionAttention(nn.Module):
    """Multi-head attention whose keys and values come from a spatially reduced token map."""

    def __init__(self, dim: int, heads: int, sr: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"width {dim} is not divisible by {heads} heads")
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)
        self.sr_ratio = sr
        if sr > 1:
            self.sr = nn.Conv2d(dim, dim, kernel_size=sr, stride=sr)
            self.norm = nn.LayerNorm(dim, eps=1e-5)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """Attend from every token to the reduced token map."""
        b, n, c = x.shape
        q = self.q(x).reshape(b, n, self.heads, c // self.heads).transpose(1, 2)
        if self.sr_ratio > 1:
            reduced = self.sr(x.transpose(1, 2).reshape(b, c, h, w)).flatten(2).transpose(1, 2)
            x = self.norm(reduced)
        kv = self.kv(x).reshape(b, -1, 2, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, kv[0], kv[1])
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class MixFFN(nn.Module):
    """Feed-forward layer with a 3x3 depth-wise convolution between its two linear layers."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.dwconv = nn.Conv2d(hidden, hidden, kernel_size=3, padding=1, groups=hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """Apply the FFN to tokens on an ``h x w`` grid."""
        x = self.fc1(x)
        b, _, c = x.shape
        x = self.dwconv(x.transpose(1, 2).reshape(b, c, h, w)).flatten(2).transpose(1, 2)
        return self.fc2(F.gelu(x))


class PvtBlock(nn.Module):
    """Pre-norm transformer block of PVT-v2."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int, sr: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = SpatialReductionAttention(dim, heads, sr)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = MixFFN(dim, dim * mlp_ratio)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """Residual attention then residual Mix-FFN."""
        x = x + self.attn(self.norm1(x), h, w)
        return x + self.mlp(self.norm2(x), h, w)


class PvtV2Encoder(nn.Module):
    """Four-stage PVT-v2 pyramid; returns the token maps of strides 4, 8, 16 and 32."""

    def __init__(self, spec: PvtV2Spec, in_ch: int = 3) -> None:
        super().__init__()
        self.spec = spec
        self.patch_embeds = nn.ModuleList()
        self.stages = nn.ModuleList()
        self.norms = nn.ModuleList()
        prev = in_ch
        for i in range(4):
            patch, stride = (7, 4) if i == 0 else (3, 2)
            self.patch_embeds.append(OverlapPatchEmbed(prev, spec.dims[i], patch, stride))
            self.stages.append(
                nn.ModuleList(
                    PvtBlock(spec.dims[i], spec.heads[i], spec.mlp[i], spec.sr[i]) for _ in range(spec.depths[i])
                )
            )
            self.norms.append(nn.LayerNorm(spec.dims[i], eps=1e-6))
            prev = spec.dims[i]
        self.apply(_init_weights)

    def forward(self, x: torch.Tensor) -> list[tuple[torch.Tensor, int, int]]:
        """``[(tokens, h, w)]`` for the four stages, finest first."""
        b = x.shape[0]
        outs = []
        for embed, blocks, norm in zip(self.patch_embeds, self.stages, self.norms, strict=True):
            tokens, h, w = embed(x)
            for block in blocks:  # type: ignore[attr-defined]
                tokens = block(tokens, h, w)
            tokens = norm(tokens)
            outs.append((tokens, h, w))
            x = tokens.transpose(1, 2).reshape(b, -1, h, w)
        return outs


def _init_weights(m: nn.Module) -> None:
    """Truncated-normal linear layers, fan-out normal convolutions, unit layer norms."""
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.LayerNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)
    elif isinstance(m, nn.Conv2d):
        fan_out = m.kernel_size[0] * m.kernel_size[1] * m.out_channels // m.groups
        nn.init.normal_(m.weight, 0.0, (2.0 / fan_out) ** 0.5)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
