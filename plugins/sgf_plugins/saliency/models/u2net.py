"""U^2-Net and U^2-Net-P (Qin et al., Pattern Recognition 2020): nested U-structure of residual U-blocks (RSU).

An RSU-L block is a small U-Net of height L inside a residual connection; RSU-4F replaces pooling
by dilated convolutions. Eleven RSU stages form the outer U (six encoder stages, five decoder
stages); each of the six deepest-to-shallowest decoder outputs gives a side saliency map, and a 1x1
convolution fuses the six into the final map. The loss is the sum of the BCE of all seven maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

#: (height, in, mid, out) of the 11 stages of U^2-Net: encoder 1-6, decoder 5d-1d.
U2NET_STAGES: tuple[tuple[int, int, int, int], ...] = (
    (7, 3, 32, 64),
    (6, 64, 32, 128),
    (5, 128, 64, 256),
    (4, 256, 128, 512),
    (0, 512, 256, 512),
    (0, 512, 256, 512),
    (0, 1024, 256, 512),
    (4, 1024, 128, 256),
    (5, 512, 64, 128),
    (6, 256, 32, 64),
    (7, 128, 16, 64),
)
#: The same for the small U^2-Net-P (height 0 means RSU-4F).
U2NETP_STAGES: tuple[tuple[int, int, int, int], ...] = (
    (7, 3, 16, 64),
    (6, 64, 16, 64),
    (5, 64, 16, 64),
    (4, 64, 16, 64),
    (0, 64, 16, 64),
    (0, 64, 16, 64),
    (0, 128, 16, 64),
    (4, 128, 16, 64),
    (5, 128, 16, 64),
    (6, 128, 16, 64),
    (7, 128, 16, 64),
)


@dataclass(frozen=True)
class U2NetSpec:
    """Stage table of a U^2-Net: ``(height, in, mid, out)`` for the 11 RSU stages (height 0 = RSU-4F)."""

    stages: tuple[tuple[int, int, int, int], ...]

    @classmethod
    def scaled(cls, base: tuple[tuple[int, int, int, int], ...], width: float) -> U2NetSpec:
        """The base table with every width multiplied by ``width`` (input channels stay 3)."""

        def w(c: int) -> int:
            return max(1, round(c * width))

        return cls(tuple((h, cin if i == 0 else w(cin), w(mid), w(out)) for i, (h, cin, mid, out) in enumerate(base)))


class ConvBnRelu(nn.Module):
    """REBNCONV: 3x3 (dilated) convolution, batch norm, ReLU."""

    def __init__(self, cin: int, cout: int, dilation: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=dilation, dilation=dilation)
        self.bn = nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Conv -> BN -> ReLU."""
        return F.relu(self.bn(self.conv(x)))


def upsample_like(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Bilinear resize of ``x`` to the spatial size of ``like`` (nothing when the sizes agree)."""
    if x.shape[2:] == like.shape[2:]:
        return x
    return F.interpolate(x, size=like.shape[2:], mode="bilinear", align_corners=False)


class RSU(nn.Module):
    """Residual U-block of height ``height`` (RSU-L), with ``height - 2`` poolings."""

    def __init__(self, height: int, cin: int, mid: int, cout: int) -> None:
        super().__init__()
        if height < 3:
            raise ValueError(f"RSU height must be at least 3, got {height}")
        self.conv_in = ConvBnRelu(cin, cout)
        self.encoder = nn.ModuleList([ConvBnRelu(cout, mid)] + [ConvBnRelu(mid, mid) for _ in range(height - 2)])
        self.bottom = ConvBnRelu(mid, mid, dilation=2)
        self.decoder = nn.ModuleList(
            [ConvBnRelu(2 * mid, mid) for _ in range(height - 2)] + [ConvBnRelu(2 * mid, cout)]
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """U-Net inside a residual connection."""
        xin = self.conv_in(x)
        skips = []
        h = xin
        last = len(self.encoder) - 1
        for i, conv in enumerate(self.encoder):
            h = conv(h)
            skips.append(h)
            if i < last:
                h = F.max_pool2d(h, 2, stride=2, ceil_mode=True)
        h = self.bottom(h)
        for conv, skip in zip(self.decoder, reversed(skips), strict=True):
            h = conv(torch.cat([upsample_like(h, skip), skip], dim=1))
        return h + xin


class RSU4F(nn.Module):
    """Residual U-block of height 4 with dilations 1, 2, 4, 8 instead of pooling (RSU-4F)."""

    def __init__(self, cin: int, mid: int, cout: int) -> None:
        super().__init__()
        self.conv_in = ConvBnRelu(cin, cout)
        self.encoder = nn.ModuleList([ConvBnRelu(cout, mid), ConvBnRelu(mid, mid, 2), ConvBnRelu(mid, mid, 4)])
        self.bottom = ConvBnRelu(mid, mid, dilation=8)
        self.decoder = nn.ModuleList(
            [ConvBnRelu(2 * mid, mid, 4), ConvBnRelu(2 * mid, mid, 2), ConvBnRelu(2 * mid, cout)]
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Dilated U inside a residual connection."""
        xin = self.conv_in(x)
        skips = []
        h = xin
        for conv in self.encoder:
            h = conv(h)
            skips.append(h)
        h = self.bottom(h)
        for conv, skip in zip(self.decoder, reversed(skips), strict=True):
            h = conv(torch.cat([h, skip], dim=1))
        return h + xin


def rsu(height: int, cin: int, mid: int, cout: int) -> nn.Module:
    """RSU-L for ``height >= 3``, RSU-4F for height 0."""
    return RSU4F(cin, mid, cout) if height == 0 else RSU(height, cin, mid, cout)


class U2Net(nn.Module):
    """U^2-Net: returns the fused logit followed by the six side logits, all at input resolution."""

    def __init__(self, spec: U2NetSpec) -> None:
        super().__init__()
        if len(spec.stages) != 11:
            raise ValueError(f"U^2-Net has 11 stages, the spec lists {len(spec.stages)}")
        self.spec = spec
        self.stages = nn.ModuleList(rsu(*s) for s in spec.stages)
        # side outputs from decoder stages 1d..5d and encoder stage 6
        side_channels = [spec.stages[i][3] for i in (10, 9, 8, 7, 6, 5)]
        self.sides = nn.ModuleList(nn.Conv2d(c, 1, 3, padding=1) for c in side_channels)
        self.fuse = nn.Conv2d(6, 1, 1)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``[d0 (fused), d1, ..., d6]`` logits at input resolution."""
        enc = []
        h = x
        for i in range(6):
            h = self.stages[i](h)
            enc.append(h)
            if i < 5:
                h = F.max_pool2d(h, 2, stride=2, ceil_mode=True)
        dec = [enc[5]]  # stage 6 output, then 5d, 4d, 3d, 2d, 1d
        for j, skip in enumerate(reversed(enc[:5])):
            h = self.stages[6 + j](torch.cat([upsample_like(dec[-1], skip), skip], dim=1))
            dec.append(h)
        features = list(reversed(dec))  # 1d, 2d, 3d, 4d, 5d, 6
        sides = [upsample_like(side(f), x) for side, f in zip(self.sides, features, strict=True)]
        return [self.fuse(torch.cat(sides, dim=1)), *sides]

    @staticmethod
    def final(outputs: list[torch.Tensor]) -> torch.Tensor:
        """The fused logit ``d0``."""
        return outputs[0]

    def loss(self, outputs: list[torch.Tensor], targets: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict]:
        """Multi-BCE loss: the sum of the BCE of the fused map and the six side maps."""
        mask = targets["mask"]
        terms = [F.binary_cross_entropy_with_logits(o, mask) for o in outputs]
        parts = {f"d{i}": float(t.detach()) for i, t in enumerate(terms)}
        return torch.stack(terms).sum(), parts
