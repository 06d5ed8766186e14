"""The saliency stage variants: registration, configs, weights errors, ONNX runtime, the classical detector."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from sgf_plugins.saliency import procedural
from sgf_plugins.saliency.classical import marking_saliency
from sgf_plugins.saliency.cli_sod_eval import bev_of
from sgf_plugins.saliency.cli_sod_eval import run as sod_eval_run
from sgf_plugins.saliency.data import write_sod_folder
from sgf_plugins.saliency.metrics import SodMetrics
from sgf_plugins.saliency.stages import LEARNED_VARIANTS, VARIANTS, default_architecture
from sgf_plugins.saliency.weights import default_weights_path, save_weights

from sgf_pipeline import Dataset, Pipeline, RunContext, Stage, hookimpl, load_plugins
from sgf_pipeline.errors import ConfigError, DataError
from sgf_pipeline.types import Bev, BevGrid, Frame, SaliencyMap

LEARNED = [cls.name for cls in LEARNED_VARIANTS]


def test_variants_are_registered_with_bev_in_and_saliency_out() -> None:
    registry = load_plugins().registry
    assert [v.name for v in registry.variants("saliency")] == sorted(c.name for c in VARIANTS)
    for v in registry.variants("saliency"):
        assert [(i.parameter, i.types) for i in v.signature.inputs] == [("bev", (Bev,))]
        assert v.signature.output_types == (SaliencyMap,) and v.cls.output == "saliency"


def test_plugin_listing_does_not_import_torch() -> None:
    code = "import sys, sgf_plugins.saliency, sgf_pipeline; sgf_pipeline.load_plugins(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def _bev(seed: int = 3, size: int = 128) -> tuple[Bev, np.ndarray]:
    rgb, mask, meta = procedural.sample(np.random.default_rng(seed), size)
    return bev_of(rgb, meta["valid"], 0.02, 0), mask


@pytest.mark.parametrize("model", LEARNED)
def test_missing_weights_name_the_file_the_architecture_and_the_fix(model: str, tmp_path: Path) -> None:
    cls = {c.name: c for c in LEARNED_VARIANTS}[model]
    missing = tmp_path / "none.safetensors"
    with pytest.raises(DataError) as info:
        cls(cls.Params(weights=str(missing)))
    text = str(info.value)
    assert str(missing) in text and f"sgf-train saliency={model}" in text and "saliency.weights=" in text
    for key, value in default_architecture(model).items():
        assert f"{key}={value}" in text
    if not default_weights_path(model).is_file():  # until weights are shipped, the default fails the same way
        with pytest.raises(DataError, match=str(default_weights_path(model))):
            cls(cls.Params())


def test_mismatched_weights(tmp_path: Path, untrained_weights: Callable[[str], Path]) -> None:
    from sgf_plugins.saliency.stages import U2NetParams, U2NetPParams, U2NetPSaliency, U2NetSaliency

    small = untrained_weights("u2netp")
    with pytest.raises(DataError, match=r"holds u2netp .* choose saliency=u2netp"):
        U2NetSaliency(U2NetParams(weights=str(small)))
    with pytest.raises(DataError, match=r"set the parameters to the file's: saliency.width=1.0"):
        U2NetPSaliency(U2NetPParams(weights=str(small), width=0.5))
    # metadata that claims the right architecture over tensors of another one
    from sgf_plugins.saliency.models import build_model

    forged = save_weights(
        build_model("u2netp", {"width": 0.5}), tmp_path / "forged.safetensors", "u2netp", {"width": 1.0}
    )
    with pytest.raises(DataError, match=r"does not fit u2netp .*wrong shape"):
        U2NetPSaliency(U2NetPParams(weights=str(forged)))
    alien = tmp_path / "alien.safetensors"
    from safetensors.numpy import save_file

    save_file({"w": np.zeros(3, np.float32)}, str(alien))
    with pytest.raises(DataError, match="not an sgf-pipeline saliency weights file"):
        U2NetPSaliency(U2NetPParams(weights=str(alien)))
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x80\x04not safetensors")  # e.g. a pickle: never loaded
    with pytest.raises(DataError, match="not a readable safetensors"):
        U2NetPSaliency(U2NetPParams(weights=str(garbage)))


@pytest.mark.parametrize("model", LEARNED)
def test_onnx_runtime_matches_torch(model: str, tmp_path: Path, untrained_weights: Callable[[str], Path]) -> None:
    cls = {c.name: c for c in LEARNED_VARIANTS}[model]
    weights = str(untrained_weights(model))
    bev, _ = _bev()
    torch_map = cls(cls.Params(weights=weights, runtime="torch")).process(bev)
    onnx_stage = cls(cls.Params(weights=weights, runtime="onnx", onnx_path=str(tmp_path / "m.onnx"), threads=1))
    onnx_map = onnx_stage.process(bev)
    assert (tmp_path / "m.onnx").is_file()
    assert torch_map.probability.shape == onnx_map.probability.shape == bev.valid.shape
    assert torch_map.probability.dtype == np.float32
    assert np.abs(torch_map.probability - onnx_map.probability).max() < 1e-4
    assert torch_map.probability[~bev.valid].max() == 0.0 and torch_map.probability.min() >= 0.0
    assert torch_map.probability.max() <= 1.0 and torch_map.bev is bev


def test_onnx_cache_is_keyed_by_the_weights(
    tmp_path: Path, untrained_weights: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    from sgf_plugins.saliency.stages import LdfParams, LdfSaliency

    monkeypatch.setenv("SGF_PIPELINE_CACHE", str(tmp_path / "cache"))
    stage = LdfSaliency(LdfParams(weights=str(untrained_weights("ldf")), runtime="onnx"))
    first = stage.predictor.onnx_path
    assert first.parent == tmp_path / "cache" / "onnx" and first.is_file()
    again = LdfSaliency(LdfParams(weights=str(untrained_weights("ldf")), runtime="onnx"))
    assert again.predictor.onnx_path == first
    other = LdfSaliency(LdfParams(weights=str(untrained_weights("ldf")), runtime="onnx", input_size=64))
    assert other.predictor.onnx_path != first


def test_onnx_threads_follow_torch_unless_set(
    tmp_path: Path, untrained_weights: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    # onnx is the default runtime; with threads=null its session takes torch's thread count, which the
    # runner sets from run.torch_threads after the stages are built (1 inside parallel sweeps)
    import torch
    from sgf_plugins.saliency.stages import U2NetPParams, U2NetPSaliency

    monkeypatch.setenv("SGF_PIPELINE_CACHE", str(tmp_path / "cache"))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        stage = U2NetPSaliency(U2NetPParams(weights=str(untrained_weights("u2netp"))))
        assert stage.predictor.runtime == "onnx" and stage.predictor._session_threads == 2
        torch.set_num_threads(1)
        stage.begin(RunContext(None))
        assert stage.predictor._session_threads == 1
        fixed = U2NetPSaliency(U2NetPParams(weights=str(untrained_weights("u2netp")), threads=2))
        fixed.begin(RunContext(None))
        assert fixed.predictor._session_threads == 2
    finally:
        torch.set_num_threads(before)


def test_selfreformer_input_size_must_divide_by_32(untrained_weights: Callable[[str], Path]) -> None:
    from sgf_plugins.saliency.stages import SelfReformerParams, SelfReformerSaliency

    with pytest.raises(ValueError, match="multiple of 32"):
        SelfReformerSaliency(SelfReformerParams(weights=str(untrained_weights("selfreformer")), input_size=100))


def test_weights_run_at_another_input_size_than_trained_warn(tmp_path: Path) -> None:
    import warnings

    import torch
    from sgf_plugins.saliency.models import build_model
    from sgf_plugins.saliency.stages import LdfParams, LdfSaliency

    arch = default_architecture("ldf")
    torch.manual_seed(0)
    weights = save_weights(
        build_model("ldf", arch), tmp_path / "ldf.safetensors", "ldf", arch, extra={"input_size": 64}
    )
    with pytest.warns(UserWarning, match=r"trained at input size 64, run at 96.*saliency.input_size=64"):
        LdfSaliency(LdfParams(weights=str(weights), input_size=96))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        LdfSaliency(LdfParams(weights=str(weights), input_size=64))  # as trained: silent


# -- classical detector -------------------------------------------------------------------------


def test_classical_finds_drawn_markings() -> None:
    acc = SodMetrics()
    rng = np.random.default_rng(11)
    for _ in range(12):
        rgb, mask, meta = procedural.sample(rng, 128, max_markings=2)
        if not mask.any():
            continue
        prob = marking_saliency(rgb, meta["valid"], 0.04)  # 128 px over 5.12 m
        assert prob.dtype == np.float32 and prob.shape == mask.shape
        assert prob[~meta["valid"]].max() == 0.0
        acc.add_probability(prob, mask.astype(np.uint8) * 255)
    r = acc.results()
    assert r["maxF"] > 0.7 and r["mae"] < 0.05, r


def test_a_grey_bev_is_read_as_its_three_equal_channels(untrained_weights: Callable[[str], Path]) -> None:
    """A mono camera (KITTI's image_0, EuRoC) gives grey BEVs: every saliency stage takes them."""
    bev, _ = _bev()
    grey = cv2.cvtColor(np.ascontiguousarray(bev.image), cv2.COLOR_RGB2GRAY)
    as_three = replace(bev, image=np.repeat(grey[:, :, None], 3, axis=2))
    classical = {c.name: c for c in VARIANTS}["classical"]
    for image in (grey, grey[:, :, None]):
        as_grey = replace(bev, image=image)
        for cls, params in (
            (classical, {}),
            ({c.name: c for c in LEARNED_VARIANTS}["u2netp"], {"weights": str(untrained_weights("u2netp"))}),
        ):
            stage = cls(cls.Params(**params))
            expected = stage.process(as_three).probability
            assert expected.max() > 0.0
            np.testing.assert_array_equal(stage.process(as_grey).probability, expected)
    with pytest.raises(ValueError, match=r"\(H, W\) grey image, got shape \(128, 128, 2\)"):
        classical(classical.Params()).process(replace(bev, image=np.zeros((128, 128, 2), np.uint8)))


def test_classical_is_quiet_on_bare_ground_and_scales_with_resolution() -> None:
    rng = np.random.default_rng(4)
    ground = procedural.ground_texture(rng, 128)
    assert marking_saliency(ground, None, 0.04).mean() < 0.01
    line = ground.copy()
    line[60:66, 10:118] = 240  # a 0.24 m wide stripe at 0.04 m/px
    prob = marking_saliency(line, None, 0.04)
    assert prob[62, 20:100].mean() > 0.9
    # the same pixels read at 0.01 m/px are a 6 cm stripe, twice as wide as a 3 cm top-hat disc
    assert marking_saliency(line, None, 0.01, kernel_m=0.03)[62, 20:100].mean() < 0.1
    assert marking_saliency(line, np.zeros((128, 128), bool), 0.04).max() == 0.0


def test_sod_eval_runs_models_on_a_folder(
    toy_folder: Path, tmp_path: Path, untrained_weights: Callable[[str], Path]
) -> None:
    cfg = {
        "models": ["classical", "u2net"],
        "params": {"u2net": {"weights": str(untrained_weights("u2net")), "input_size": 64}},
        "data": {"root": str(toy_folder), "split": "test", "resolution": 0.08},
        "save_predictions": True,
        "warmup": 1,
        "examples": 2,
    }
    results = sod_eval_run(cfg, tmp_path)
    for model in ("classical", "u2net"):
        r = results[model]
        assert r["fps"] > 0 and r["images"] == 3 and r["split"] == "test"
        assert set(r) >= {"maxF", "meanF", "adpF", "mae", "sm", "em", "fps"}
        assert len(list((tmp_path / "preds" / model).glob("*.png"))) == 3
    # the figure: two samples of the split with an object, their masks and both models' saved maps
    from sgf_plugins.saliency.data import SodFolder
    from sgf_plugins.saliency.figures import Example, example_grid, example_names

    sod = SodFolder(toy_folder)
    names = example_names(sod.split("test"), lambda n: int((sod.mask(n) > 128).sum()), 2)
    assert len(names) == 2
    saved = {
        m: {n: cv2.imread(str(tmp_path / "preds" / m / f"{n}.png"), 0) for n in names} for m in ("classical", "u2net")
    }
    rows = [Example(n, sod.image(n), sod.mask(n), {m: saved[m][n] for m in saved}) for n in names]
    figure = cv2.cvtColor(cv2.imread(str(tmp_path / "sod_examples.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(figure, example_grid(rows, ["classical", "u2net"]))
    with pytest.raises(ConfigError, match="nothing to evaluate"):
        sod_eval_run({}, tmp_path)
    with pytest.raises(ConfigError, match="unknown variant"):
        sod_eval_run({"models": ["nope"], "data": {"root": str(toy_folder)}}, tmp_path)
    # a mistyped option fails before any model runs, naming the key
    with pytest.raises(ConfigError, match=r"sgf-sod-eval\.examples: .*got 'many'"):
        sod_eval_run({**cfg, "examples": "many"}, tmp_path)
    with pytest.raises(ConfigError, match=r"sgf-sod-eval\.data\.splt: unknown parameter"):
        sod_eval_run({**cfg, "data": {"root": str(toy_folder), "splt": "val"}}, tmp_path)
    with pytest.raises(ConfigError, match=r"sgf-sod-eval\.warmup: .*greater than or equal to 0"):
        sod_eval_run({**cfg, "warmup": -1}, tmp_path)


def test_sod_eval_scores_every_image_of_a_folder_without_splits(tmp_path: Path) -> None:
    """A plain images/ + masks/ folder: every image is scored, and the printed table says how many."""
    from sgf_plugins.saliency.data import SodFolder

    root = tmp_path / "plain"
    write_sod_folder(procedural.samples(17, seed=3, size=64), root, split=None)
    assert not (root / "splits.json").exists() and SodFolder(root).splits() is None
    cfg = {"models": ["classical"], "data": {"root": str(root), "resolution": 0.08}, "warmup": 0, "examples": 0}
    results = sod_eval_run(cfg, tmp_path / "all")
    assert results["classical"]["images"] == 17 and results["classical"]["split"] == "all"
    # a split named explicitly is still made by seed, as sgf-train makes it: a part of the folder
    some = sod_eval_run({**cfg, "data": {**cfg["data"], "split": "test"}}, tmp_path / "test")["classical"]
    assert 0 < some["images"] < 17 and some["split"] == "test"
    proc = subprocess.run(
        [
            str(Path(sys.executable).with_name("sgf-sod-eval")),
            "models=[classical]",
            f"data.root={root}",
            "data.resolution=0.08",
            "examples=0",
            f"hydra.run.dir={tmp_path / 'cli'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    header, _, row = proc.stdout.splitlines()[:3]
    assert header.split()[-1] == "images" and row.split()[0] == "classical" and row.split()[-1] == "17"


# -- in a pipeline ------------------------------------------------------------------------------


class ToyFrames(Dataset):
    """Three procedurally drawn frames (the BEV is the image)."""

    name = "toy_bev_frames"

    def frames(self) -> Iterator[Frame]:
        rng = np.random.default_rng(0)
        for i in range(3):
            rgb, _, _ = procedural.sample(rng, 64)
            yield Frame(i, 0.1 * i, rgb, np.eye(4), None)  # type: ignore[arg-type]

    def __len__(self) -> int:
        return 3


class ToyIpm(Stage):
    """Pretends the camera image is already a BEV."""

    kind = "ipm"
    name = "toy_identity"
    output = "bev"

    def process(self, frame: Frame) -> Bev:
        h, w = frame.image.shape[:2]
        grid = BevGrid(0.08, 0.0, h * 0.08, -w * 0.04, w * 0.04)
        return Bev(frame.image, frame.image.max(axis=2) > 0, grid, frame.index, frame.timestamp)


class _ToyPlugin:
    @hookimpl
    def sgf_register_stages(self, registry):
        registry.add(ToyFrames)
        registry.add(ToyIpm)


def test_saliency_runs_in_a_pipeline(tmp_path: Path) -> None:
    plugins = load_plugins(extra=[("toy", _ToyPlugin())])
    cfg = {
        "pipeline": ["dataset", "ipm", "saliency"],
        "dataset": {"name": "toy_bev_frames"},
        "ipm": {"name": "toy_identity"},
        "saliency": {"name": "classical", "kernel_m": 1.0},
        "run": {"progress": False, "plots": False},
    }
    pipeline = Pipeline.from_config(cfg, plugins=plugins)
    maps = [pipeline.process(f).outputs["saliency"] for f in pipeline.frames()]
    assert len(maps) == 3 and all(isinstance(m, SaliencyMap) and m.probability.shape == (64, 64) for m in maps)
    cfg["saliency"] = {"name": "ldf", "weights": str(tmp_path / "missing.safetensors")}
    with pytest.raises(ConfigError, match=r"saliency=ldf cannot start: weights file .*missing.safetensors not found"):
        Pipeline.from_config(cfg, plugins=plugins)


def test_ground_truth_saliency_is_the_visible_paint_and_needs_instances() -> None:
    from sgf_plugins.saliency.stages import GroundTruthParams, GroundTruthSaliency

    grid = BevGrid(resolution=0.02, x_min=0.5, x_max=1.78, y_min=-0.64, y_max=0.64)
    image = np.full((64, 64), 60, np.uint8)
    ids = np.zeros((64, 64), np.int32)
    ids[10:30, 10:20] = 3
    ids[40:50, 40:60] = 5
    image[ids > 0] = 220
    valid = np.ones((64, 64), bool)
    valid[:, 50:] = False  # the camera sees only part of marking 5
    stage = GroundTruthSaliency(GroundTruthParams(object_masks=False))
    prob = stage.process(Bev(image, valid, grid, 0, 0.0, instance_ids=ids)).probability
    assert prob.dtype == np.float32
    assert np.array_equal(prob > 0.5, (ids > 0) & valid) and set(np.unique(prob)) == {0.0, 1.0}
    with pytest.raises(DataError, match="saliency=ground_truth needs marking instances"):
        stage.process(Bev(image, valid, grid, 0, 0.0))
