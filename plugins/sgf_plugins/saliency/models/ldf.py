"""LDF, the Label Decoupling Framework (Wei et al., CVPR 2020), on a small ResNet encoder.

Label decoupling splits the mask into a body map (the square root of the distance transform of the
blurred mask, normalised to 1 at the deepest pixel) and a detail map (mask minus body: the pixels
near edges). The feature interaction network has a body branch and a detail branch, each a decoder
over the encoder's four levels; their outputs are concatenated, passed through the interaction
encoder, and fed back into both decoders for a second, refined pass. Each pass predicts body,
detail and saliency; the loss is BCE on body and detail plus BCE + IoU on saliency, averaged over
the two passes. The reference trains twice (coarse labels, then labels predicted by the coarse
model); here the labels are always the distance-transform ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sgf_plugins.saliency.models.resnet import ResNetEncoder, ResNetSpec


@dataclass(frozen=True)
class LdfSpec:
    """Encoder and the width of the two branches (64 in the paper)."""

    encoder: ResNetSpec
    width: int = 64


def decouple_label(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body and detail maps (float32 in [0, 1]) of a mask in [0, 1] (thresholded at 0.5)."""
    binary = (np.asarray(mask) > 0.5).astype(np.uint8) * 255
    blurred = cv2.blur(binary, (5, 5))
    body = np.sqrt(cv2.distanceTransform(blurred, cv2.DIST_L2, 5))
    peak = float(body.max())
    if peak > 0:
        body = np.floor(body / peak * 255) / 255
    detail = np.clip(binary / 255.0 - body, 0.0, 1.0)
    return body.astype(np.float32), detail.astype(np.float32)


def conv_bn_relu(cin: int, cout: int) -> nn.Sequential:
    """3x3 convolution, batch norm, ReLU."""
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU())


class LevelSqueeze(nn.Sequential):
    """1x1 reduction of an encoder level to the branch width, then 3x3 convolution, BN, ReLU."""

    def __init__(self, cin: int, width: int) -> None:
        super().__init__(
            nn.Conv2d(cin, width, 1), nn.Conv2d(width, width, 3, padding=1), nn.BatchNorm2d(width), nn.ReLU()
        )


class BranchDecoder(nn.Module):
    """Top-down decoder of one branch; the second pass adds the interaction encoder's features."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.convs = nn.ModuleList(conv_bn_relu(width, width) for _ in range(4))

    def forward(self, levels: list[torch.Tensor], feedback: list[torch.Tensor] | None = None) -> torch.Tensor:
        """Decode levels ordered coarse to fine; returns the finest-level feature map."""
        out: torch.Tensor | None = None
        for i, (conv, level) in enumerate(zip(self.convs, levels, strict=True)):
            x = level if feedback is None else level + feedback[i]
            if out is not None:
                x = x + F.interpolate(out, size=level.shape[2:], mode="bilinear", align_corners=False)
            out = conv(x)
        assert out is not None
        return out


class InteractionEncoder(nn.Module):
    """Feature interaction: encodes the concatenated body and detail features back to four levels per branch."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.down = nn.ModuleList([conv_bn_relu(2 * width, width)] + [conv_bn_relu(width, width) for _ in range(3)])
        self.to_body = nn.ModuleList(conv_bn_relu(width, width) for _ in range(4))
        self.to_detail = nn.ModuleList(conv_bn_relu(width, width) for _ in range(4))

    def forward(self, x: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Body and detail feedback, each ordered coarse to fine."""
        levels = []
        for i, conv in enumerate(self.down):
            if i > 0:
                x = F.max_pool2d(x, kernel_size=2, stride=2)
            x = conv(x)
            levels.append(x)
        body = [conv(f) for conv, f in zip(self.to_body, levels, strict=True)]
        detail = [conv(f) for conv, f in zip(self.to_detail, levels, strict=True)]
        return body[::-1], detail[::-1]


class Ldf(nn.Module):
    """LDF: returns ``[body1, detail1, sal1, body2, detail2, sal2]`` logits at input resolution."""

    def __init__(self, spec: LdfSpec) -> None:
        super().__init__()
        self.spec = spec
        w = spec.width
        self.encoder = ResNetEncoder(spec.encoder)
        self.squeeze_body = nn.ModuleList(LevelSqueeze(c, w) for c in spec.encoder.channels)
        self.squeeze_detail = nn.ModuleList(LevelSqueeze(c, w) for c in spec.encoder.channels)
        self.interaction = InteractionEncoder(w)
        self.decoder_body = BranchDecoder(w)
        self.decoder_detail = BranchDecoder(w)
        self.head_body = nn.Conv2d(w, 1, 3, padding=1)
        self.head_detail = nn.Conv2d(w, 1, 3, padding=1)
        self.head_saliency = nn.Sequential(conv_bn_relu(2 * w, w), nn.Conv2d(w, 1, 3, padding=1))
        for name, m in self.named_modules():
            if name.startswith("encoder"):
                continue
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_in", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Two passes of the feature interaction network."""
        levels = self.encoder(x)
        body = [s(f) for s, f in zip(self.squeeze_body, levels, strict=True)][::-1]
        detail = [s(f) for s, f in zip(self.squeeze_detail, levels, strict=True)][::-1]
        size = x.shape[2:]
        outputs = []
        feedback: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None
        for _ in range(2):
            fb = self.decoder_body(body, None if feedback is None else feedback[0])
            fd = self.decoder_detail(detail, None if feedback is None else feedback[1])
            fused = torch.cat([fb, fd], dim=1)
            outputs += [
                _resize(self.head_body(fb), size),
                _resize(self.head_detail(fd), size),
                _resize(self.head_saliency(fused), size),
            ]
            feedback = self.interaction(fused)
        return outputs

    @staticmethod
    def final(outputs: list[torch.Tensor]) -> torch.Tensor:
        """The second pass's saliency logit."""
        return outputs[-1]

    @staticmethod
    def targets_from_mask(mask: np.ndarray) -> dict[str, np.ndarray]:
        """Body and detail maps of a training mask (label decoupling)."""
        body, detail = decouple_label(mask)
        return {"body": body, "detail": detail}

    def loss(self, outputs: list[torch.Tensor], targets: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict]:
        """BCE on body and detail, BCE + IoU on saliency, averaged over the two passes."""
        mask, body, detail = targets["mask"], targets["body"], targets["detail"]
        parts: dict[str, float] = {}
        total = mask.new_zeros(())
        for k in range(2):
            ob, od, os_ = outputs[3 * k : 3 * k + 3]
            lb = F.binary_cross_entropy_with_logits(ob, body)
            ld = F.binary_cross_entropy_with_logits(od, detail)
            ls = F.binary_cross_entropy_with_logits(os_, mask) + iou_loss(os_, mask)
            parts.update({f"body{k + 1}": float(lb.detach()), f"detail{k + 1}": float(ld.detach())})
            parts[f"saliency{k + 1}"] = float(ls.detach())
            total = total + lb + ld + ls
        return total / 2, parts


def _resize(x: torch.Tensor, size: torch.Size) -> torch.Tensor:
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


def iou_loss(logit: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Soft IoU loss ``1 - (inter + 1) / (union + 1)`` per image, averaged."""
    p = torch.sigmoid(logit)
    inter = (p * mask).sum(dim=(2, 3))
    union = (p + mask).sum(dim=(2, 3))
    return (1 - (inter + 1) / (union - inter + 1)).mean()
