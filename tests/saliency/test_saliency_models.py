"""The networks: parameter counts from their layer definitions, output shapes, losses, and that training learns."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from sgf_plugins.saliency import procedural
from sgf_plugins.saliency.models import ARCHITECTURES, build_model
from sgf_plugins.saliency.models.ldf import decouple_label, iou_loss
from sgf_plugins.saliency.models.pvt_v2 import PVT_V2_SIZES
from sgf_plugins.saliency.models.selfreformer import boundary_weight, confidence_loss, weighted_bce
from sgf_plugins.saliency.models.u2net import U2NET_STAGES, U2NETP_STAGES
from sgf_plugins.saliency.preprocess import normalize_image
from sgf_plugins.saliency.stages import default_architecture

DEFAULT_ARCH = {m: default_architecture(m) for m in ARCHITECTURES}


# -- parameter counts, written from the papers' layer tables ------------------------------------


def conv(cin: int, cout: int, k: int, bias: bool = True, groups: int = 1) -> int:
    return cin // groups * cout * k * k + (cout if bias else 0)


def linear(i: int, o: int, bias: bool = True) -> int:
    return i * o + (o if bias else 0)


def norm(c: int) -> int:
    return 2 * c  # layer norm or batch norm: scale and shift


def count(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def pvt_v2_params(dims, heads, mlp, depths) -> int:
    total, prev = 0, 3
    for i, d in enumerate(dims):
        sr = (8, 4, 2, 1)[i]
        total += conv(prev, d, 7 if i == 0 else 3) + norm(d)  # overlapping patch embedding
        attention = linear(d, d) + linear(d, 2 * d) + linear(d, d) + ((conv(d, d, sr) + norm(d)) if sr > 1 else 0)
        hidden = d * mlp[i]
        ffn = linear(d, hidden) + conv(hidden, hidden, 3, groups=hidden) + linear(hidden, d)
        total += depths[i] * (norm(d) + attention + norm(d) + ffn) + norm(d)
        prev = d
    return total


def vit(d: int, depth: int, mlp: int) -> int:
    block = norm(d) + linear(d, 3 * d, bias=False) + linear(d, d) + norm(d) + linear(d, d * mlp) + linear(d * mlp, d)
    return depth * block + norm(d)


def selfreformer_params(size: str, g: int, level_depth: int, crm_depth: int, mlp: int) -> int:
    s = PVT_V2_SIZES[size]
    dims = s["dims"]
    total = pvt_v2_params(dims, s["heads"], s["mlp"], s["depths"])
    # global context: shapers to g * (16 / stride)^-2 channels, three merges, transformer, 3-layer head
    widths = (g // 16, g // 4, g, 4 * g)
    total += sum(norm(d) + linear(d, w) for d, w in zip(dims, widths, strict=True))
    total += 3 * (norm(2 * g) + conv(2 * g, g, 3)) + vit(g, 2, mlp)
    total += 2 * (norm(g) + linear(g, g)) + norm(g) + linear(g, 1)
    for d, stride in zip(dims, (4, 8, 16, 32), strict=True):
        out = stride * stride
        total += vit(d, level_depth, mlp)  # level transformer
        crm = conv(out, d, 3) + conv(2 * d, d, 3) + norm(d) + 2 * (conv(d, d, 3) + norm(d))
        crm += conv(d, out, 3) + conv(out, d, 3) + norm(d) + vit(d, crm_depth, mlp) + conv(d, out, 3)
        total += crm
    for fine, coarse in itertools.pairwise(dims):  # fusers
        total += linear(fine + coarse // 4, fine) + linear(fine, fine)
        total += linear(fine, 3 * fine) + linear(fine, fine) + 2 * norm(fine) + 2 * linear(fine, fine)
    return total


def rsu_params(height: int, cin: int, mid: int, cout: int) -> int:
    rebn = lambda i, o: conv(i, o, 3) + norm(o)  # noqa: E731
    n = 4 if height == 0 else height  # RSU-4F has the layout of RSU-4
    return (
        rebn(cin, cout)
        + rebn(cout, mid)
        + (n - 1) * rebn(mid, mid)
        + (n - 2) * rebn(2 * mid, mid)
        + rebn(2 * mid, cout)
    )


def u2net_params(stages) -> int:
    total = sum(rsu_params(*s) for s in stages)
    total += sum(conv(stages[i][3], 1, 3) for i in (10, 9, 8, 7, 6, 5)) + conv(6, 1, 1)
    return total


def resnet_params(depth: int, w: int) -> int:
    layouts = {18: ("basic", (2, 2, 2, 2)), 34: ("basic", (3, 4, 6, 3)), 50: ("bottleneck", (3, 4, 6, 3))}
    kind, layers = layouts[depth]
    exp = 4 if kind == "bottleneck" else 1
    total = conv(3, w, 7, bias=False) + norm(w)
    cin = w
    for i, n in enumerate(layers):
        p = w * 2**i
        for j in range(n):
            stride = 2 if (j == 0 and i > 0) else 1
            if kind == "basic":
                total += conv(cin, p, 3, False) + norm(p) + conv(p, p, 3, False) + norm(p)
            else:
                total += conv(cin, p, 1, False) + norm(p) + conv(p, p, 3, False) + norm(p)
                total += conv(p, 4 * p, 1, False) + norm(4 * p)
            if stride != 1 or cin != p * exp:
                total += conv(cin, p * exp, 1, False) + norm(p * exp)
            cin = p * exp
    return total


def ldf_params(depth: int, w: int, b: int) -> int:
    exp = 4 if depth == 50 else 1
    channels = [w * 2**i * exp for i in range(4)]
    cbr = conv(b, b, 3) + norm(b)
    total = resnet_params(depth, w)
    total += 2 * sum(conv(c, b, 1) + conv(b, b, 3) + norm(b) for c in channels)  # body and detail squeezes
    total += conv(2 * b, b, 3) + norm(b) + 3 * cbr + 8 * cbr  # interaction encoder
    total += 2 * 4 * cbr  # two branch decoders
    total += 2 * conv(b, 1, 3) + conv(2 * b, b, 3) + norm(b) + conv(b, 1, 3)  # heads
    return total


@pytest.mark.parametrize(
    "arch",
    [DEFAULT_ARCH["selfreformer"], {"size": "b0", "global_dim": 256, "level_depth": 2, "crm_depth": 4, "mlp_ratio": 3}],
)
def test_selfreformer_parameter_count(arch: dict) -> None:
    net = build_model("selfreformer", arch)
    assert count(net) == selfreformer_params(
        arch["size"], arch["global_dim"], arch["level_depth"], arch["crm_depth"], 3
    )


def test_pvt_v2_encoders_match_the_published_sizes() -> None:
    from sgf_plugins.saliency.models.pvt_v2 import PvtV2Encoder, PvtV2Spec

    # PVT-v2 paper: b0 3.7 M and b2 25.4 M parameters with the 1000-class head (256 and 512 inputs)
    published = {"b0": 3.7e6 - linear(256, 1000), "b2": 25.4e6 - linear(512, 1000)}
    for size, expected in published.items():
        s = PVT_V2_SIZES[size]
        n = count(PvtV2Encoder(PvtV2Spec.named(size)))
        assert n == pvt_v2_params(s["dims"], s["heads"], s["mlp"], s["depths"])
        assert n == pytest.approx(expected, rel=0.02)


def test_u2net_parameter_counts() -> None:
    assert count(build_model("u2net", DEFAULT_ARCH["u2net"])) == u2net_params(
        [(h, i if k == 0 else round(i / 4), round(m / 4), round(o / 4)) for k, (h, i, m, o) in enumerate(U2NET_STAGES)]
    )
    full, small = build_model("u2net", {"width": 1.0}), build_model("u2netp", {"width": 1.0})
    assert count(full) == u2net_params(U2NET_STAGES)
    assert count(small) == u2net_params(U2NETP_STAGES)
    # U^2-Net paper, Table 5: 44.0 M and 1.1 M parameters (176.3 MB and 4.7 MB)
    assert count(full) == pytest.approx(44.0e6, rel=0.005)
    assert count(small) * 4 / 1e6 == pytest.approx(4.7, rel=0.05)


def test_ldf_and_resnet_parameter_counts() -> None:
    from sgf_plugins.saliency.models.resnet import ResNetEncoder, ResNetSpec

    # torchvision's ResNet-18 and ResNet-50 without their 1000-class layer
    assert count(ResNetEncoder(ResNetSpec(18, 64))) == 11_689_512 - linear(512, 1000) == resnet_params(18, 64)
    assert count(ResNetEncoder(ResNetSpec(50, 64))) == 25_557_032 - linear(2048, 1000) == resnet_params(50, 64)
    a = DEFAULT_ARCH["ldf"]
    assert count(build_model("ldf", a)) == ldf_params(a["resnet_depth"], a["resnet_width"], a["branch_width"])
    assert count(build_model("ldf", {"resnet_depth": 50, "resnet_width": 64, "branch_width": 64})) == ldf_params(
        50, 64, 64
    )


# -- outputs ------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", list(ARCHITECTURES))
def test_output_shapes(model: str) -> None:
    net = build_model(model, DEFAULT_ARCH[model]).eval()
    size = 64
    with torch.inference_mode():
        outputs = net(torch.zeros(2, 3, size, size))
        final = net.final(outputs)
    assert final.shape == (2, 1, size, size)
    shapes = [tuple(o.shape) for o in outputs]
    if model == "selfreformer":
        # global context at stride 16, then (p1, p2) per level coarse to fine with stride^2 channels
        expected = [(2, 1, 4, 4)]
        for stride in (32, 16, 8, 4):
            expected += [(2, stride * stride, size // stride, size // stride)] * 2
        assert shapes == expected
    elif model in ("u2net", "u2netp"):
        assert shapes == [(2, 1, size, size)] * 7  # fused + six side outputs
    else:
        assert shapes == [(2, 1, size, size)] * 6  # (body, detail, saliency) x 2 passes


def test_selfreformer_refuses_sizes_not_divisible_by_32() -> None:
    net = build_model("selfreformer", DEFAULT_ARCH["selfreformer"])
    with pytest.raises(ValueError, match="divisible by 32"):
        net(torch.zeros(1, 3, 48, 48))


# -- losses -------------------------------------------------------------------------------------


def test_selfreformer_loss_terms_by_hand() -> None:
    logit = torch.zeros(1, 1, 40, 40)
    empty = torch.zeros(1, 1, 40, 40)
    assert float(weighted_bce(logit, empty)) == pytest.approx(np.log(2), rel=1e-6)  # weight 1 everywhere
    # sigma(0) = 0.5: BCE log 2 weighted by 2 * 0.25, plus lambda * 2 * 0.25
    assert float(confidence_loss(logit, empty, lam=0.5)) == pytest.approx(0.5 * np.log(2) + 0.25, rel=1e-6)
    mask = torch.zeros(1, 1, 40, 40)
    mask[..., 10:30, 10:30] = 1
    w = boundary_weight(mask)
    assert float(w.max()) <= 5.0 and float(w.min()) >= 1.0
    assert float(w[0, 0, 20, 10]) > float(w[0, 0, 20, 20])  # heavier at the boundary than in the middle
    assert float(w[0, 0, 20, 20]) == pytest.approx(1 + 4 * (1 - 400 / 961), rel=1e-5)


def test_u2net_multi_bce_and_ldf_iou_by_hand() -> None:
    net = build_model("u2netp", {"width": 0.25})
    outputs = [torch.zeros(1, 1, 8, 8)] * 7
    loss, parts = net.loss(outputs, {"mask": torch.ones(1, 1, 8, 8)})
    assert float(loss) == pytest.approx(7 * np.log(2), rel=1e-6) and len(parts) == 7
    big = torch.full((1, 1, 8, 8), 50.0)
    assert float(iou_loss(big, torch.ones(1, 1, 8, 8))) == pytest.approx(0.0, abs=1e-6)
    assert float(iou_loss(-big, torch.ones(1, 1, 8, 8))) == pytest.approx(1 - 1 / 65, rel=1e-4)


def test_label_decoupling() -> None:
    yy, xx = np.mgrid[0:64, 0:64]
    disk = ((yy - 32) ** 2 + (xx - 32) ** 2 <= 20**2).astype(np.float32)
    body, detail = decouple_label(disk)
    assert body.max() == pytest.approx(1.0) and body[32, 32] == pytest.approx(1.0, abs=0.02)  # deepest at centre
    assert body[0, 0] == 0 and detail[0, 0] == 0
    assert detail[32, 13] > 0.5 > detail[32, 30]  # detail at the edge, body inside
    inside = disk > 0
    assert np.allclose(np.clip(body + detail, 0, 1)[inside], 1.0, atol=1 / 255 + 1e-6)


# -- training lowers the loss -------------------------------------------------------------------


@pytest.mark.parametrize("model", list(ARCHITECTURES))
def test_a_few_steps_lower_the_loss(model: str) -> None:
    torch.manual_seed(0)
    net = build_model(model, DEFAULT_ARCH[model]).train()
    rng = np.random.default_rng(1)
    samples = [procedural.sample(rng, 64, max_markings=2) for _ in range(4)]
    x = torch.from_numpy(np.stack([normalize_image(s[0], 64) for s in samples]))
    masks = [s[1].astype(np.float32) for s in samples]
    targets = {"mask": torch.from_numpy(np.stack(masks)[:, None])}
    extra = getattr(net, "targets_from_mask", None)
    if extra is not None:
        for key in extra(masks[0]):
            targets[key] = torch.from_numpy(np.stack([extra(m)[key] for m in masks])[:, None])
    optimizer = torch.optim.AdamW(net.parameters(), lr=2e-3)
    losses = []
    for _ in range(8):
        loss, parts = net.loss(net(x), targets)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
        assert all(np.isfinite(v) for v in parts.values())
    assert losses[-1] < 0.8 * losses[0], losses
