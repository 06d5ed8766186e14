"""Fixtures of the saliency tests: a small procedurally drawn SOD folder and weights files of untrained networks."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from sgf_plugins.saliency import procedural
from sgf_plugins.saliency.data import SplitSpec, write_sod_folder
from sgf_plugins.saliency.stages import default_architecture


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    """Tests share two cores with other work: one torch thread keeps them quick and deterministic."""
    import torch

    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def toy_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """24 drawn 64x64 BEV-like samples with splits (seed 0; the 'glyph' design held out)."""
    root = tmp_path_factory.mktemp("sod") / "toy"
    write_sod_folder(
        procedural.samples(24, seed=0, size=64),
        root,
        SplitSpec(seed=0, val_fraction=0.2, test_fraction=0.15, heldout_designs=("glyph",)),
    )
    return root


@pytest.fixture(scope="session")
def untrained_weights(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """Factory: a weights file of a freshly initialised network with the default architecture (seeded)."""
    import torch
    from sgf_plugins.saliency.models import build_model
    from sgf_plugins.saliency.weights import save_weights

    folder = tmp_path_factory.mktemp("weights")
    made: dict[str, Path] = {}

    def make(model: str) -> Path:
        if model not in made:
            torch.manual_seed(0)
            arch = default_architecture(model)
            net = build_model(model, arch)
            made[model] = save_weights(net, folder / f"{model}.safetensors", model, arch)
        return made[model]

    return make
