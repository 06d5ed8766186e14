"""SOD metrics of a network on samples of a SOD folder (the validation and test splits of a training run)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch
from torch import nn

from sgf_plugins.saliency.data import SodFolder
from sgf_plugins.saliency.inference import probability_module
from sgf_plugins.saliency.metrics import SodMetrics
from sgf_plugins.saliency.preprocess import normalize_image


def predict_folder(
    net: nn.Module, folder: SodFolder, names: Sequence[str], size: int, batch_size: int = 8
) -> Iterator[tuple[str, np.ndarray]]:
    """``(name, probability at the mask's resolution)`` for each sample, the network in eval mode."""
    import cv2

    module = probability_module(net)
    for start in range(0, len(names), batch_size):
        chunk = names[start : start + batch_size]
        x = np.stack([normalize_image(folder.image(n), size) for n in chunk])
        with torch.inference_mode():
            probs = module(torch.from_numpy(x)).numpy()[:, 0]
        for name, prob in zip(chunk, probs, strict=True):
            h, w = folder.mask(name).shape
            if prob.shape != (h, w):
                prob = cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)
            yield name, np.clip(prob, 0.0, 1.0)


def evaluate_network(net: nn.Module, folder: SodFolder, names: Sequence[str], size: int) -> dict[str, float]:
    """SOD metrics of a network on some samples of a folder (PySODMetrics conventions)."""
    acc = SodMetrics()
    for name, prob in predict_folder(net, folder, names, size):
        acc.add_probability(prob, folder.mask(name))
    return acc.results()
