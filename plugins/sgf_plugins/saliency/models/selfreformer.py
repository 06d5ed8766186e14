"""SelfReformer (Yun and Lin, IEEE TMM 2023): PVT-v2 encoder, global context, transformer refinement, fusion.

The refinement is done by context refinement modules (CRM) and the fusion by performer attention;
outputs are pixel-shuffled to full resolution and trained with the confidence-aware loss.

Every level ``i`` of stride ``s_i`` (4, 8, 16, 32) predicts ``s_i^2`` channels that a pixel shuffle
turns into a full-resolution map, as in the paper. The global-context branch reshapes the four
levels to stride 16 (pixel shuffle/unshuffle), merges them, runs a transformer and predicts a coarse
map that every CRM receives (pixel-unshuffled to its level). A CRM fuses it with the level's tokens,
predicts a first map ``p1``, turns its uncertainty ``sigma(p1)(1 - sigma(p1))`` into an attention
that re-weights the features, refines them with a transformer and predicts ``p2``. Fusers carry each
level's refined tokens to the next finer level (pixel shuffle, MLP, performer attention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from sgf_plugins.saliency.models.pvt_v2 import PvtV2Encoder, PvtV2Spec

#: The encoder strides of the four levels and the stride of the global-context map.
STRIDES = (4, 8, 16, 32)
GLOBAL_STRIDE = 16
#: Loss weights of the outputs: global context, then (p1, p2) per level from coarse to fine
#: (the reference implementation zips 11 weights with 9 outputs, so these are the ones in effect).
LOSS_WEIGHTS = (1.0, 0.5, 0.5, 0.7, 0.7, 0.9, 0.9, 1.1, 1.1)


@dataclass(frozen=True)
class SelfReformerSpec:
    """The architecture of a SelfReformer network."""

    encoder: PvtV2Spec
    global_dim: int = 256
    level_depth: int = 2
    crm_depth: int = 4
    global_depth: int = 2
    mlp_ratio: int = 3
    confidence_lambda: float = 0.5


def sinusoid_encoding(n: int, dim: int, device: torch.device | None = None) -> torch.Tensor:
    """The fixed sinusoidal position encoding of ``n`` tokens, ``(1, n, dim)``."""
    position = torch.arange(n, dtype=torch.float32, device=device)[:, None]
    index = torch.arange(dim, device=device)
    rate = torch.pow(10000.0, -(2 * torch.div(index, 2, rounding_mode="floor")).float() / dim)
    angle = position * rate[None, :]
    table = torch.where(index % 2 == 0, torch.sin(angle), torch.cos(angle))
    return table[None]


class Attention(nn.Module):
    """Multi-head self-attention without bias on the query, key and value projection."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Self-attention over the tokens ``(B, N, C)``."""
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class TransformerBlock(nn.Module):
    """Pre-norm ViT block."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, dim * mlp_ratio), nn.GELU(), nn.Linear(dim * mlp_ratio, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Residual attention then residual MLP."""
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class TokenTransformer(nn.Module):
    """A stack of ViT blocks with a final layer norm, optionally adding a sinusoidal position encoding."""

    def __init__(self, dim: int, depth: int, mlp_ratio: int, position: bool, heads: int = 1) -> None:
        super().__init__()
        self.position = position
        self.blocks = nn.ModuleList(TransformerBlock(dim, heads, mlp_ratio) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Transform tokens ``(B, N, C)``."""
        if self.position:
            x = x + sinusoid_encoding(x.shape[1], x.shape[2], x.device)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)


class PerformerAttention(nn.Module):
    """Single-head performer block: softmax attention approximated by positive random features (FAVOR+)."""

    def __init__(self, dim: int, kernel_ratio: float = 0.5) -> None:
        super().__init__()
        self.dim = dim
        self.features = max(1, int(dim * kernel_ratio))
        self.kqv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, dim), nn.GELU(), nn.Linear(dim, dim))
        w = nn.init.orthogonal_(torch.empty(self.features, dim)) * math.sqrt(self.features)
        self.register_buffer("random_features", w)

    def _phi(self, x: torch.Tensor) -> torch.Tensor:
        """Positive random features ``exp(w^T x - |x|^2 / 2) / sqrt(m)``."""
        w: torch.Tensor = self.random_features  # type: ignore[assignment]
        return torch.exp(x @ w.t() - (x * x).sum(-1, keepdim=True) / 2) / math.sqrt(self.features)

    def attend(self, x: torch.Tensor) -> torch.Tensor:
        """Linear-complexity attention of the tokens ``(B, N, C)``."""
        k, q, v = torch.split(self.kqv(x), self.dim, dim=-1)
        kp, qp = self._phi(k), self._phi(q)
        normaliser = qp @ kp.sum(dim=1, keepdim=True).transpose(1, 2)  # (B, N, 1)
        y = qp @ (kp.transpose(1, 2) @ v) / (normaliser + 1e-8)
        return self.proj(y)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Residual performer attention then residual MLP."""
        x = x + self.attend(self.norm1(x))
        return x + self.mlp(self.norm2(x))


def conv_bn_lrelu(cin: int, cout: int) -> list[nn.Module]:
    """3x3 convolution, batch norm, leaky ReLU."""
    return [nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.LeakyReLU()]


class Fuser(nn.Module):
    """Carries a coarser level's tokens to a finer level: pixel shuffle, concatenation, MLP, performer."""

    def __init__(self, dim: int, coarse_dim: int) -> None:
        super().__init__()
        if coarse_dim % 4:
            raise ValueError(f"the coarser level's width {coarse_dim} must be divisible by 4 for a pixel shuffle")
        self.concat_fuse = nn.Sequential(nn.Linear(dim + coarse_dim // 4, dim), nn.GELU(), nn.Linear(dim, dim))
        self.attention = PerformerAttention(dim)

    def forward(self, fine: torch.Tensor, coarse: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """Fuse fine tokens on an ``h x w`` grid with coarse tokens on ``h/2 x w/2``."""
        b, _, c = coarse.shape
        up = F.pixel_shuffle(coarse.transpose(1, 2).reshape(b, c, h // 2, w // 2), 2).flatten(2).transpose(1, 2)
        return self.attention(self.concat_fuse(torch.cat([fine, up], dim=2)))


class ContextRefinement(nn.Module):
    """CRM: fuse the global context, predict, re-weight by the prediction's uncertainty, refine, predict again."""

    def __init__(self, dim: int, stride: int, depth: int, mlp_ratio: int) -> None:
        super().__init__()
        out = stride * stride
        self.stride = stride
        self.conv_glb = nn.Conv2d(out, dim, 3, padding=1)
        self.conv_fuse = nn.Sequential(*conv_bn_lrelu(2 * dim, dim), *conv_bn_lrelu(dim, dim), *conv_bn_lrelu(dim, dim))
        self.conv_p1 = nn.Conv2d(dim, out, 3, padding=1)
        self.conv_matt = nn.Sequential(*conv_bn_lrelu(out, dim))
        self.transformer = TokenTransformer(dim, depth, mlp_ratio, position=True)
        self.conv_p2 = nn.Conv2d(dim, out, 3, padding=1)

    def forward(
        self, tokens: torch.Tensor, context: torch.Tensor, h: int, w: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(p1, p2, refined tokens)``; ``context`` is the full-resolution global-context logit map."""
        b, _, c = tokens.shape
        x = tokens.transpose(1, 2).reshape(b, c, h, w)
        glb = self.conv_glb(F.pixel_unshuffle(context, self.stride))
        x = self.conv_fuse(torch.cat([glb, x], dim=1))
        p1 = self.conv_p1(x)
        confidence = torch.sigmoid(p1)
        x = x * (1 + self.conv_matt(confidence * (1 - confidence)))
        refined = self.transformer(x.flatten(2).transpose(1, 2))
        p2 = self.conv_p2(refined.transpose(1, 2).reshape(b, c, h, w))
        return p1, p2, refined


class GlobalContext(nn.Module):
    """The global-context branch: all levels reshaped to stride 16, merged, transformed, one coarse map."""

    def __init__(self, dims: tuple[int, ...], gdim: int, depth: int, mlp_ratio: int) -> None:
        super().__init__()
        if gdim % 16:
            raise ValueError(f"global_dim {gdim} must be divisible by 16 (stride-4 features are unshuffled by 4)")
        self.factors = [GLOBAL_STRIDE // s if s <= GLOBAL_STRIDE else -(s // GLOBAL_STRIDE) for s in STRIDES]
        widths = [gdim // (f * f) if f > 0 else gdim * f * f for f in self.factors]
        self.shapers = nn.ModuleList(
            nn.Sequential(nn.LayerNorm(d), nn.Linear(d, wd), nn.GELU()) for d, wd in zip(dims, widths, strict=True)
        )
        self.merges = nn.ModuleList(
            nn.Sequential(nn.BatchNorm2d(2 * gdim), nn.Conv2d(2 * gdim, gdim, 3, padding=1), nn.LeakyReLU())
            for _ in range(3)
        )
        self.transformer = TokenTransformer(gdim, depth, mlp_ratio, position=True)
        head: list[nn.Module] = []
        for _ in range(2):
            head += [nn.LayerNorm(gdim), nn.Linear(gdim, gdim), nn.GELU()]
        self.pred = nn.Sequential(*head, nn.LayerNorm(gdim), nn.Linear(gdim, 1))

    def forward(self, levels: list[tuple[torch.Tensor, int, int]]) -> torch.Tensor:
        """The coarse global-context logit map at stride 16, ``(B, 1, H/16, W/16)``."""
        maps = []
        for (tokens, h, w), shaper, f in zip(levels, self.shapers, self.factors, strict=True):
            x = shaper(tokens)
            x = x.transpose(1, 2).reshape(x.shape[0], -1, h, w)
            if f > 1:
                x = F.pixel_unshuffle(x, f)
            elif f < 0:
                x = F.pixel_shuffle(x, -f)
            maps.append(x)
        s4, s8, s16, s32 = maps
        out = self.merges[0](torch.cat([s16, s32], dim=1))
        out = self.merges[1](torch.cat([out, s8], dim=1))
        out = self.merges[2](torch.cat([out, s4], dim=1))
        b, _, h, w = out.shape
        tokens = self.transformer(out.flatten(2).transpose(1, 2))
        return self.pred(tokens).transpose(1, 2).reshape(b, 1, h, w)


class SelfReformer(nn.Module):
    """SelfReformer: returns the global-context map and (p1, p2) of every level from coarse to fine."""

    def __init__(self, spec: SelfReformerSpec) -> None:
        super().__init__()
        self.spec = spec
        dims = spec.encoder.dims
        self.encoder = PvtV2Encoder(spec.encoder)
        self.global_context = GlobalContext(dims, spec.global_dim, spec.global_depth, spec.mlp_ratio)
        self.level_transformers = nn.ModuleList(
            TokenTransformer(d, spec.level_depth, spec.mlp_ratio, position=False) for d in dims
        )
        self.crms = nn.ModuleList(
            ContextRefinement(d, s, spec.crm_depth, spec.mlp_ratio) for d, s in zip(dims, STRIDES, strict=True)
        )
        self.fusers = nn.ModuleList(Fuser(dims[i], dims[i + 1]) for i in range(3))
        for module in (self.global_context, self.level_transformers, self.crms, self.fusers):
            module.apply(_init_decoder)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Logits: ``[global (stride 16), p1_32, p2_32, p1_16, p2_16, p1_8, p2_8, p1_4, p2_4]`` (``s^2`` channels)."""
        if x.shape[-1] % 32 or x.shape[-2] % 32:
            raise ValueError(f"SelfReformer needs an input size divisible by 32, got {tuple(x.shape[-2:])}")
        levels = self.encoder(x)
        glob = self.global_context(levels)
        context = F.interpolate(glob, scale_factor=GLOBAL_STRIDE, mode="nearest")
        outputs = [glob]
        refined: torch.Tensor | None = None
        for i in (3, 2, 1, 0):
            tokens, h, w = levels[i]
            tokens = self.level_transformers[i](tokens)
            if refined is not None:
                tokens = self.fusers[i](tokens, refined, h, w)
            p1, p2, refined = self.crms[i](tokens, context, h, w)
            outputs += [p1, p2]
        return outputs

    @staticmethod
    def final(outputs: list[torch.Tensor]) -> torch.Tensor:
        """The saliency logit at input resolution: the finest level's refined map, pixel-shuffled."""
        return F.pixel_shuffle(outputs[-1], STRIDES[0])

    def loss(self, outputs: list[torch.Tensor], targets: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict]:
        """Confidence-aware loss: BCE on the global map, weighted BCE on every map, confidence term on each p2."""
        mask = (targets["mask"] > 0.5).float()
        total = mask.new_zeros(())
        parts: dict[str, float] = {}
        glob_target = F.max_pool2d(mask, GLOBAL_STRIDE)
        weight_map = boundary_weight(mask)
        for k, (logit, weight) in enumerate(zip(outputs, LOSS_WEIGHTS, strict=True)):
            if k == 0:
                term = F.binary_cross_entropy_with_logits(logit, glob_target)
                name = "global"
            else:
                stride = STRIDES[3 - (k - 1) // 2]
                full = F.pixel_shuffle(logit, stride)
                term = weighted_bce(full, mask, weight_map)
                name = f"p{2 - k % 2}_s{stride}"
                if k % 2 == 0:
                    term = term + confidence_loss(full, mask, self.spec.confidence_lambda)
            parts[name] = float(term.detach())
            total = total + weight * term
        return total, parts


def boundary_weight(mask: torch.Tensor, window: int = 31) -> torch.Tensor:
    """``1 + 4 |mean_31x31(mask) - mask|``: up to 5 near boundaries (zero-padded box mean, computed separably)."""
    half = window // 2
    local = F.avg_pool2d(mask, kernel_size=(window, 1), stride=1, padding=(half, 0))
    local = F.avg_pool2d(local, kernel_size=(1, window), stride=1, padding=(0, half))
    return 1 + 4 * torch.abs(local - mask)


def weighted_bce(logit: torch.Tensor, mask: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """BCE weighted by :func:`boundary_weight` (the structure loss of F3Net without its IoU term)."""
    if weight is None:
        weight = boundary_weight(mask)
    bce = F.binary_cross_entropy_with_logits(logit, mask, reduction="none")
    return ((bce * weight).sum(dim=(2, 3)) / weight.sum(dim=(2, 3))).mean()


def confidence_loss(logit: torch.Tensor, mask: torch.Tensor, lam: float, beta: float = 2.0) -> torch.Tensor:
    """Confidence-aware term: BCE weighted by the (detached) uncertainty, plus lambda times the uncertainty."""
    y = torch.sigmoid(logit)
    uncertainty = y * (1 - y)
    bce = F.binary_cross_entropy_with_logits(logit, mask, reduction="none")
    return (bce * (beta * uncertainty).detach()).mean() + lam * beta * uncertainty.mean()


def _init_decoder(m: nn.Module) -> None:
    """Truncated-normal linear layers, He-normal convolutions, unit norms."""
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, (nn.LayerNorm, nn.BatchNorm2d)):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)
    elif isinstance(m, nn.Conv2d):
        nn.init.kaiming_normal_(m.weight, mode="fan_in", nonlinearity="leaky_relu")
        if m.bias is not None:
            nn.init.zeros_(m.bias)
