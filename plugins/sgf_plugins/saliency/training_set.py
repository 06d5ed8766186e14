"""Samples of a SOD folder as training batches: network inputs and targets, augmented reproducibly per epoch."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from sgf_plugins.saliency.augment import Augmentation, salient_crop
from sgf_plugins.saliency.data import SodFolder
from sgf_plugins.saliency.preprocess import normalize_image, resize_mask


class SodTrainingSet(torch.utils.data.Dataset[tuple[torch.Tensor, dict[str, torch.Tensor]]]):
    """Samples of a SOD folder as network inputs and targets, augmented reproducibly per epoch."""

    def __init__(
        self,
        folder: SodFolder,
        names: Sequence[str],
        size: int,
        augment: Augmentation | None,
        seed: int,
        extra_targets: Callable[[np.ndarray], dict[str, np.ndarray]] | None = None,
        crop: int | None = None,
        crop_on_marking: float = 0.8,
    ) -> None:
        self.folder = folder
        self.crop = crop
        self.crop_on_marking = crop_on_marking
        self.names = list(names)
        self.size = size
        self.augment = augment
        self.seed = seed
        self.epoch = 0
        self.extra_targets = extra_targets

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        name = self.names[index]
        import cv2

        rgb = self.folder.image(name)
        mask = resize_mask(self.folder.mask(name), self.size)
        if rgb.shape[:2] != (self.size, self.size):
            rgb = cv2.resize(rgb, (self.size, self.size), interpolation=cv2.INTER_AREA)
        rng = np.random.default_rng([self.seed, self.epoch, index])
        if self.augment is not None:
            rgb, mask = self.augment(rgb, mask, rng)
        if self.crop is not None and self.crop < self.size:
            rgb, mask = salient_crop(rgb, mask, self.crop, self.crop_on_marking, rng)
        targets = {"mask": torch.from_numpy(mask[None].copy())}
        if self.extra_targets is not None:
            for key, value in self.extra_targets(mask).items():
                targets[key] = torch.from_numpy(value[None].copy())
        return torch.from_numpy(normalize_image(rgb, rgb.shape[0])), targets


def collate(batch: list[tuple[torch.Tensor, dict[str, torch.Tensor]]]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """One batch of samples: the images stacked, each target stacked under its key."""
    images = torch.stack([b[0] for b in batch])
    targets = {k: torch.stack([b[1][k] for b in batch]) for k in batch[0][1]}
    return images, targets
