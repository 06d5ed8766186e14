"""Salient object detection metrics (MaxF, MeanF, adaptive F, MAE, S-measure, E-measure) with PySODMetrics' conventions.

SOD toolkits differ in small ways that change the third decimal; this module follows PySODMetrics
(and through it D.-P. Fan's MATLAB toolbox after its ``>=`` threshold fix), so that numbers are
comparable with published tables:

- the ground truth is ``mask > 128`` (8-bit masks; soft masks are binarised);
- each prediction is read as 8-bit grey, divided by 255 and min-max normalised per image
  (MATLAB's ``mapminmax(im2double(...))``); a constant prediction is left as it is;
- F-measure uses ``beta^2 = 0.3``; the threshold curve has 256 thresholds ``pred*255 >= t``
  for ``t = 255, ..., 0`` on the floor-quantised prediction; each image has its own curve and the
  curves are averaged over images before taking the maximum (MaxF) or the mean (MeanF);
- adaptive F and adaptive E threshold each image at ``min(2 * mean(pred), 1)``;
- MAE is averaged over images; S-measure uses ``alpha = 0.5``; ``eps`` is ``np.spacing(1)``.

One deliberate difference: when the mask's centroid lies on the last row or column, a quadrant
of the S-measure's region term is empty; it has weight 0 and is skipped here, where PySODMetrics
returns NaN for that image (and so for the mean over the data set).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

EPS = float(np.spacing(1))
BETA2 = 0.3
THRESHOLDS = 256


def prepare(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalise an 8-bit prediction and mask: ``pred`` min-max scaled to [0, 1] (float64), ``gt > 128``."""
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} differs from mask shape {gt.shape}")
    if pred.dtype != np.uint8 or gt.dtype != np.uint8:
        raise TypeError(f"expected uint8 prediction and mask, got {pred.dtype} and {gt.dtype}")
    truth = gt > 128
    p = pred / 255
    lo, hi = p.min(), p.max()
    if hi != lo:
        p = (p - lo) / (hi - lo)
    return p, truth


def to_uint8(probability: np.ndarray) -> np.ndarray:
    """A probability map in [0, 1] as the 8-bit grey image a saved prediction would hold (rounded)."""
    return np.clip(np.rint(np.asarray(probability, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def adaptive_threshold(pred: np.ndarray) -> float:
    """Twice the mean prediction, at most 1."""
    return min(2.0 * float(pred.mean()), 1.0)


def _cumulative_counts(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with ``floor(pred*255) >= t`` inside and outside the mask, for t = 255 ... 0."""
    q = (pred * 255).astype(np.uint8)
    fg = np.bincount(q[gt], minlength=THRESHOLDS)
    bg = np.bincount(q[~gt], minlength=THRESHOLDS)
    return np.cumsum(fg[::-1]), np.cumsum(bg[::-1])


def f_measure(precision: np.ndarray | float, recall: np.ndarray | float, beta2: float = BETA2) -> np.ndarray:
    """F-measure of precision and recall (0 where both are 0)."""
    p = np.asarray(precision, dtype=np.float64)
    r = np.asarray(recall, dtype=np.float64)
    numerator = (1 + beta2) * p * r
    denominator = np.where(numerator == 0, 1, beta2 * p + r)
    return numerator / denominator


def f_curve(pred: np.ndarray, gt: np.ndarray, beta2: float = BETA2) -> np.ndarray:
    """F-measure at the 256 thresholds (index 0 is ``>= 255``, index 255 is ``>= 0``)."""
    tp, fp = _cumulative_counts(pred, gt)
    positives = tp + fp
    positives[positives == 0] = 1
    precision = tp / positives
    recall = tp / max(int(np.count_nonzero(gt)), 1)
    return f_measure(precision, recall, beta2)


def adaptive_f(pred: np.ndarray, gt: np.ndarray, beta2: float = BETA2) -> float:
    """F-measure of the prediction binarised at the adaptive threshold."""
    binary = pred >= adaptive_threshold(pred)
    tp = int(np.count_nonzero(binary & gt))
    if tp == 0:
        return 0.0
    precision = tp / np.count_nonzero(binary)
    recall = tp / np.count_nonzero(gt)
    return float((1 + beta2) * precision * recall / (beta2 * precision + recall))


def mae(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean absolute error between the prediction and the binary mask."""
    return float(np.mean(np.abs(pred - gt)))


def _s_object(x: np.ndarray) -> float:
    mean = float(np.mean(x))
    std = float(np.std(x, ddof=1)) if x.size > 1 else 0.0
    return 2 * mean / (mean**2 + 1 + std + EPS)


def _ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    n = pred.size
    x = float(np.mean(pred))
    y = float(np.mean(gt))
    sigma_x = float(np.sum((pred - x) ** 2)) / (n - 1 + EPS)
    sigma_y = float(np.sum((gt - y) ** 2)) / (n - 1 + EPS)
    sigma_xy = float(np.sum((pred - x) * (gt - y))) / (n - 1 + EPS)
    alpha = 4 * x * y * sigma_xy
    beta = (x**2 + y**2) * (sigma_x + sigma_y)
    if alpha != 0:
        return alpha / (beta + EPS)
    return 1.0 if beta == 0 else 0.0


def s_measure(pred: np.ndarray, gt: np.ndarray, alpha: float = 0.5) -> float:
    """Structure measure (Fan et al. 2017): object-aware and region-aware similarity."""
    y = float(np.mean(gt))
    if y == 0:
        return 1 - float(np.mean(pred))
    if y == 1:
        return float(np.mean(pred))
    fg = _s_object(pred[gt]) * y
    bg = _s_object((1 - pred)[~gt]) * (1 - y)
    object_score = fg + bg
    h, w = gt.shape
    cy, cx = np.argwhere(gt).mean(axis=0).round()
    cy, cx = int(cy) + 1, int(cx) + 1  # MATLAB's 1-based centroid, so each quadrant includes it
    area = h * w
    w_lt = cx * cy / area
    w_rt = cy * (w - cx) / area
    w_lb = (h - cy) * cx / area
    w_rb = 1 - w_lt - w_rt - w_lb
    quadrants = (
        (pred[:cy, :cx], gt[:cy, :cx], w_lt),
        (pred[:cy, cx:], gt[:cy, cx:], w_rt),
        (pred[cy:, :cx], gt[cy:, :cx], w_lb),
        (pred[cy:, cx:], gt[cy:, cx:], w_rb),
    )
    # a quadrant is empty when the centroid lies on the last row or column: its weight is 0 and it
    # adds nothing (PySODMetrics returns NaN for the whole image there)
    region_score = sum(_ssim(p, g) * wq for p, g, wq in quadrants if p.size)
    return max(0.0, alpha * object_score + (1 - alpha) * region_score)


def _enhanced_sum(tp: np.ndarray | int, fp: np.ndarray | int, gt_fg: int, size: int) -> np.ndarray | float:
    """Sum of the enhanced alignment matrix given the counts of a binarised prediction (E-measure)."""
    pred_fg = np.asarray(tp) + np.asarray(fp)
    pred_bg = size - pred_fg
    if gt_fg == 0:
        return pred_bg
    if gt_fg == size:
        return pred_fg
    fn = gt_fg - np.asarray(tp)
    tn = pred_bg - fn
    mean_pred = pred_fg / size
    mean_gt = gt_fg / size
    parts = (
        (tp, 1 - mean_pred, 1 - mean_gt),
        (fp, 1 - mean_pred, -mean_gt),
        (fn, -mean_pred, 1 - mean_gt),
        (tn, -mean_pred, -mean_gt),
    )
    total: np.ndarray | float = 0.0
    for count, a, b in parts:
        align = 2 * (a * b) / (a**2 + b**2 + EPS)
        total = total + (align + 1) ** 2 / 4 * count
    return total


def e_curve(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Enhanced-alignment measure (Fan et al. 2018) at the 256 thresholds."""
    tp, fp = _cumulative_counts(pred, gt)
    size = gt.size
    return np.asarray(_enhanced_sum(tp, fp, int(np.count_nonzero(gt)), size), dtype=np.float64) / (size - 1 + EPS)


def adaptive_e(pred: np.ndarray, gt: np.ndarray) -> float:
    """E-measure of the prediction binarised at the adaptive threshold."""
    binary = pred >= adaptive_threshold(pred)
    tp = int(np.count_nonzero(binary & gt))
    fp = int(np.count_nonzero(binary & ~gt))
    size = gt.size
    return float(_enhanced_sum(tp, fp, int(np.count_nonzero(gt)), size)) / (size - 1 + EPS)


@dataclass
class SodMetrics:
    """Accumulates per-image SOD metrics and reduces them as PySODMetrics does."""

    beta2: float = BETA2
    f_curves: list[np.ndarray] = field(default_factory=list)
    e_curves: list[np.ndarray] = field(default_factory=list)
    adaptive_fs: list[float] = field(default_factory=list)
    adaptive_es: list[float] = field(default_factory=list)
    maes: list[float] = field(default_factory=list)
    s_measures: list[float] = field(default_factory=list)

    def add(self, pred: np.ndarray, gt: np.ndarray) -> None:
        """Add one 8-bit prediction and its 8-bit mask."""
        p, g = prepare(pred, gt)
        self.f_curves.append(f_curve(p, g, self.beta2))
        self.adaptive_fs.append(adaptive_f(p, g, self.beta2))
        self.maes.append(mae(p, g))
        self.s_measures.append(s_measure(p, g))
        self.e_curves.append(e_curve(p, g))
        self.adaptive_es.append(adaptive_e(p, g))

    def add_probability(self, probability: np.ndarray, gt: np.ndarray) -> None:
        """Add a probability map in [0, 1] (quantised to 8 bits as a saved PNG would be)."""
        self.add(to_uint8(probability), gt)

    def __len__(self) -> int:
        return len(self.maes)

    def results(self) -> dict[str, float]:
        """maxF, meanF, adpF, mae, sm, maxEm, meanEm, adpEm over the images added so far."""
        if not self.maes:
            raise ValueError("no images were added")
        f = np.mean(np.array(self.f_curves, dtype=np.float64), axis=0)
        e = np.mean(np.array(self.e_curves, dtype=np.float64), axis=0)
        return {
            "maxF": float(f.max()),
            "meanF": float(f.mean()),
            "adpF": float(np.mean(np.array(self.adaptive_fs, dtype=np.float64))),
            "mae": float(np.mean(np.array(self.maes, dtype=np.float64))),
            "sm": float(np.mean(np.array(self.s_measures, dtype=np.float64))),
            "maxEm": float(e.max()),
            "meanEm": float(e.mean()),
            "adpEm": float(np.mean(np.array(self.adaptive_es, dtype=np.float64))),
        }


def evaluate_pairs(pairs: Iterable[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Metrics over ``(pred_uint8, mask_uint8)`` pairs."""
    acc = SodMetrics()
    for pred, gt in pairs:
        acc.add(pred, gt)
    return acc.results()


def format_table(rows: Mapping[str, Mapping[str, float | None]]) -> str:
    """Table 1 of the paper (F_m, M, F_A, S_m) plus adaptive F, mean E-measure, frames/s and the images scored."""
    columns = [("maxF", "F_m ^"), ("mae", "M v"), ("meanF", "F_A ^"), ("sm", "S_m ^"), ("adpF", "adpF ^")]
    columns += [("em", "E_m ^"), ("fps", "fps"), ("images", "images")]
    width = max([len("Method"), *(len(k) for k in rows)])
    header = f"{'Method':<{width}}  " + "  ".join(f"{title:>7}" for _, title in columns)
    lines = [header, "-" * len(header)]
    for name, values in rows.items():
        cells = []
        for key, _ in columns:
            v = values.get(key)
            if v is None:
                cells.append(f"{'-':>7}")
            elif key == "fps":
                cells.append(f"{v:>7.1f}")
            elif key == "images":
                cells.append(f"{int(v):>7d}")
            else:
                cells.append(f"{v:>7.3f}".replace("0.", " ."))
        lines.append(f"{name:<{width}}  " + "  ".join(cells))
    return "\n".join(lines)
