"""The stage cache: a rerun reuses the front-end's outputs, and writes what an uncached run writes."""

from __future__ import annotations

import filecmp
import json
import logging
import multiprocessing
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from safetensors import safe_open
from safetensors.numpy import load_file, save_file

from sgf_pipeline import Pipeline
from sgf_pipeline.cache import STAGE_CACHE_ENV, StageCache, cache_dir, code_fingerprint
from sgf_pipeline.cache.codec import NotCacheableError, decode, encode
from sgf_pipeline.cache.keys import _imported_names
from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.config import RunOptions, config_dir
from sgf_pipeline.errors import CacheError, DataError
from sgf_pipeline.types import Bev, BevGrid, SaliencyMap

#: The main job, a tenth of its route (about 220 keyframes, a reverse loop closed): every stage as shipped.
MAIN_JOB = ["dataset.scale=0.1", "run.progress=false"]
#: The stages of the main job whose outputs depend only on the dataset and the stages before them.
CACHEABLE = ["descriptor", "detector", "enhance", "ipm", "odometry_scale", "saliency"]
FILES = ("loops.csv", "loop_candidates.csv", "trajectory_gt.tum", "trajectory_odometry.tum", "trajectory_sgf.tum")


@contextmanager
def stage_cache_on() -> Iterator[None]:
    """The stage cache as a user has it (the test session turns it off)."""
    saved = os.environ.pop(STAGE_CACHE_ENV, None)
    try:
        yield
    finally:
        if saved is not None:
            os.environ[STAGE_CACHE_ENV] = saved


def run(run_dir: Path, cache: Path | None, *overrides: str) -> dict[str, Any]:
    """The main job into ``run_dir`` with the stage cache in ``cache`` (None: off)."""
    extra = [f"run.cache_dir={cache}"] if cache is not None else ["run.cache=false"]
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*MAIN_JOB, *extra, *overrides])
    with stage_cache_on():
        return Pipeline.from_config(cfg, run_dir=run_dir).run()


def without_timings(metrics: dict[str, Any]) -> dict[str, Any]:
    """The metrics that do not measure time or memory (nor the cache's own report)."""

    def strip(node: Any) -> Any:
        if isinstance(node, dict):
            return {
                k: strip(v)
                for k, v in node.items()
                if k not in ("timing", "cache", "peak_rss_mb")
                and not k.endswith(("_ms", "_ms_max", "_ms_median"))
                and "seconds" not in k
            }
        return node

    return strip(metrics)


def assert_same_run(a: Path, b: Path) -> None:
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert without_timings(ma) == without_timings(mb)
    for name in FILES:
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    map_a, map_b = load_file(str(a / "sgf_map.safetensors")), load_file(str(b / "sgf_map.safetensors"))
    assert map_a.keys() == map_b.keys()
    for key in map_a:
        np.testing.assert_array_equal(map_a[key], map_b[key], err_msg=key)


@dataclass
class Filled:
    uncached: Path
    filling: Path
    cached: Path
    cache: Path
    metrics: dict[str, dict[str, Any]]


@pytest.fixture(scope="module")
def filled(tmp_path_factory: pytest.TempPathFactory) -> Filled:
    """The main job uncached, then filling a cache, then from it."""
    root = tmp_path_factory.mktemp("stage_cache")
    cache = root / "cache"
    metrics = {
        "uncached": run(root / "uncached", None),
        "filling": run(root / "filling", cache),
        "cached": run(root / "cached", cache),
    }
    return Filled(root / "uncached", root / "filling", root / "cached", cache, metrics)


def copy_cache(filled: Filled, tmp_path: Path) -> Path:
    target = tmp_path / "cache"
    shutil.copytree(filled.cache, target)
    return target


@pytest.mark.slow
def test_a_cached_rerun_hits_every_cacheable_stage_and_writes_what_an_uncached_run_writes(filled: Filled) -> None:
    assert "cache" not in filled.metrics["uncached"]
    assert filled.metrics["filling"]["cache"]["hits"] == []
    assert filled.metrics["filling"]["cache"]["misses"] == CACHEABLE
    report = filled.metrics["cached"]["cache"]
    assert report["hits"] == CACHEABLE and report["misses"] == []
    assert report["dataset_from_cache"] is True  # nothing rendered
    assert filled.metrics["cached"]["timing"]["stages"]["saliency"]["total_s"] == 0.0
    assert filled.metrics["cached"]["timing"]["stages"]["loop"]["calls"] > 0
    assert filled.metrics["cached"]["loops"]["closed"] >= 1  # the route's loop is in what is compared
    assert_same_run(filled.uncached, filled.filling)
    assert_same_run(filled.uncached, filled.cached)
    assert (filled.cached / "sgf_groups.png").is_file()  # the figures are drawn from the cached outputs


@pytest.mark.slow
def test_a_changed_parameter_misses_that_stage_and_the_stages_after_it(filled: Filled, tmp_path: Path) -> None:
    cache = copy_cache(filled, tmp_path)
    detector = run(tmp_path / "detector", cache, "detector.min_area=41")["cache"]
    assert detector["misses"] == ["descriptor", "detector"]
    assert detector["hits"] == ["enhance", "ipm", "odometry_scale", "saliency"]
    assert detector["dataset_from_cache"] is False
    association = run(tmp_path / "association", cache, "association.match.new_group_distance=0.6")["cache"]
    assert association["hits"] == CACHEABLE  # a later stage's parameter: the whole front-end from the cache


@pytest.mark.slow
def test_changed_weights_miss_the_saliency_and_the_stages_after_it(filled: Filled, tmp_path: Path) -> None:
    from sgf_plugins.saliency.weights import default_weights_path

    cache = copy_cache(filled, tmp_path)
    weights = tmp_path / "selfreformer.safetensors"
    shutil.copy(default_weights_path("selfreformer"), weights)
    first = run(tmp_path / "a", cache, f"saliency.weights={weights}")["cache"]
    assert first["misses"] == ["descriptor", "detector", "saliency"]  # another file: another key
    assert run(tmp_path / "b", cache, f"saliency.weights={weights}")["cache"]["misses"] == []
    with safe_open(str(weights), "np") as f:
        metadata = f.metadata()
    tensors = load_file(str(weights))
    name = sorted(tensors)[-1]
    tensors[name] = tensors[name] * np.float32(1.01)  # the same file, other weights
    save_file(tensors, str(weights), metadata=metadata)
    changed = run(tmp_path / "c", cache, f"saliency.weights={weights}")["cache"]
    assert changed["misses"] == ["descriptor", "detector", "saliency"]
    assert changed["hits"] == ["enhance", "ipm", "odometry_scale"]


@pytest.mark.slow
def test_changed_code_of_one_stage_misses_it_and_the_stages_after_it(
    filled: Filled, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import sgf_pipeline.cache.keys as keys

    cache = copy_cache(filled, tmp_path)
    real = keys.code_fingerprint

    def edited(module: str) -> str:  # as if sgf_plugins/sgf/descriptor.py had been edited
        return "edited" if module == "sgf_plugins.sgf.descriptor" else real(module)

    monkeypatch.setattr(keys, "code_fingerprint", edited)
    report = run(tmp_path / "run", cache)["cache"]
    assert report["misses"] == ["descriptor"]
    assert report["hits"] == ["detector", "enhance", "ipm", "odometry_scale", "saliency"]


@pytest.mark.slow
def test_a_damaged_entry_is_recomputed_with_a_warning(
    filled: Filled, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    cache = copy_cache(filled, tmp_path)
    (arrays,) = (cache / "saliency").glob("*/arrays.zip")
    data = bytearray(arrays.read_bytes())
    data[len(data) // 2] ^= 0xFF
    arrays.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="sgf_pipeline"):
        metrics = run(tmp_path / "run", cache)
    assert any("damaged" in r.message and "saliency" in r.message for r in caplog.records)
    assert metrics["cache"]["misses"] == ["saliency"]  # the stages after it keep their entries: same key
    assert_same_run(filled.uncached, tmp_path / "run")
    assert StageCache(cache, 10**12).lookup("saliency", arrays.parent.name) is not None  # whole again


def test_a_run_with_the_cache_off_leaves_no_entry(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(STAGE_CACHE_ENV, raising=False)
    assert cache_dir(RunOptions(cache=False, cache_dir=str(tmp_path))) is None
    assert cache_dir(RunOptions(cache_dir=str(tmp_path))) == tmp_path
    monkeypatch.setenv(STAGE_CACHE_ENV, "off")
    assert cache_dir(RunOptions(cache_dir=str(tmp_path))) is None
    monkeypatch.delenv(STAGE_CACHE_ENV)
    monkeypatch.setenv("SGF_PIPELINE_CACHE", str(tmp_path / "caches"))
    assert cache_dir(RunOptions()) == tmp_path / "caches" / "stages"


# -- entries -------------------------------------------------------------------------------------


def fill(root: str, key: str, value: float, start: Any) -> None:
    """Fill one entry of ``key`` in another process, starting together with the other writer."""
    cache = StageCache(Path(root), 10**12)
    writer = cache.writer("saliency", key, {"stage": "saliency=test"})
    start.wait()
    for i in range(50):
        writer.add(i, {"probability": np.full((64, 64), value + i, np.float32)})
    writer.commit()


def test_two_jobs_filling_the_same_key_leave_one_whole_entry(tmp_path: Path) -> None:
    context = multiprocessing.get_context("spawn")
    start = context.Barrier(2)
    jobs = [context.Process(target=fill, args=(str(tmp_path), "k" * 32, 1.0, start)) for _ in range(2)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(120)
        assert job.exitcode == 0
    cache = StageCache(tmp_path, 10**12)
    assert [e.key for e in cache.entries()] == ["k" * 32]
    assert not list((tmp_path / "saliency").glob(".tmp-*"))  # the loser's folder is gone
    entry = cache.lookup("saliency", "k" * 32)
    assert entry is not None
    for i in range(50):
        np.testing.assert_array_equal(entry.next(i)["probability"], np.full((64, 64), 1.0 + i, np.float32))
    entry.close()


def test_a_run_that_stops_keeps_no_entry(tmp_path: Path) -> None:
    cache = StageCache(tmp_path, 10**12)
    writer = cache.writer("ipm", "a" * 32, {})
    writer.add(0, np.zeros(3))
    writer.abort()
    assert cache.entries() == [] and not list(tmp_path.rglob("*.zip"))


def test_the_least_recently_used_entries_go_first(tmp_path: Path) -> None:
    cache = StageCache(tmp_path, 10**12)
    for n, key in enumerate(("a", "b", "c")):
        writer = cache.writer("ipm", key * 32, {})
        writer.add(0, np.random.default_rng(n).random(20_000))  # ~150 kB each, incompressible
        writer.commit()
        os.utime(tmp_path / "ipm" / (key * 32) / "manifest.json", (1000.0 + n, 1000.0 + n))
    entry = cache.lookup("ipm", "a" * 32)  # used now: newest
    assert entry is not None
    entry.close()
    sizes = {e.key[0]: e.bytes for e in cache.entries()}
    cache.max_bytes = sizes["a"] + sizes["c"]
    removed = cache.evict()
    assert [e.key[0] for e in removed] == ["b"]
    assert sorted(e.key[0] for e in cache.entries()) == ["a", "c"]
    assert [e.key[0] for e in cache.clear()] == ["c", "a"]
    assert cache.entries() == []


# -- the format ----------------------------------------------------------------------------------


def roundtrip(value: Any, inputs: dict[str, Any] | None = None) -> Any:
    arrays: dict[str, np.ndarray] = {}

    def sink(array: np.ndarray) -> str:
        arrays[str(len(arrays))] = array.copy()
        return str(len(arrays) - 1)

    refs = {id(v): k for k, v in (inputs or {}).items()}
    data = json.loads(json.dumps(encode(value, sink, refs)))
    return decode(data, arrays.__getitem__, inputs)


def test_values_come_back_equal_and_of_their_types() -> None:
    grid = BevGrid(0.02, 0.5, 5.62, -2.56, 2.56)
    bev = Bev(np.arange(12, dtype=np.uint8).reshape(3, 4), np.ones((3, 4), bool), grid, 7, 0.7)
    saliency = SaliencyMap(np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4), bev)
    back = roundtrip(saliency, {"bev": bev})
    assert back.bev is bev  # an input is referenced, not copied
    np.testing.assert_array_equal(back.probability, saliency.probability)
    assert back.probability.dtype == np.float32
    value = {"counts": {3: (1, 2.5), 4: None}, "tags": frozenset({"a", "b"}), "scalar": np.float32(0.25), "grid": grid}
    again = roundtrip(value)
    assert again["counts"] == {3: (1, 2.5), 4: None}
    assert again["tags"] == frozenset({"a", "b"})
    assert again["scalar"] == np.float32(0.25) and again["scalar"].dtype == np.float32
    assert again["grid"] == grid and again["grid"].width == 256
    calibration = Calibration.from_mounting(
        Intrinsics(fx=400, fy=400, cx=319.5, cy=239.5, width=640, height=480), 0.6, 0.4
    )
    assert roundtrip(calibration) == calibration


def test_a_file_cannot_name_a_class_that_is_not_loaded_nor_store_objects() -> None:
    data = {"c": "os:system", "f": {}}
    with pytest.raises(DataError, match="not a dataclass"):
        decode(data, lambda name: np.zeros(1))
    with pytest.raises(DataError, match="not loaded"):
        decode({"c": "some_module_never_imported:Thing", "f": {}}, lambda name: np.zeros(1))
    with pytest.raises(NotCacheableError):
        encode(np.array([object()]), lambda a: "0")
    with pytest.raises(NotCacheableError):
        encode(object(), lambda a: "0")


def test_the_code_fingerprint_follows_the_modules_a_stage_imports(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    package = tmp_path / "toy_cache_pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("")
    (package / "stage.py").write_text("from .sub import helper\n\ndef f():\n    from toy_cache_pkg import lazy\n")
    (package / "sub" / "helper.py").write_text("X = 1\n")
    (package / "lazy.py").write_text("Y = 1\n")
    (package / "unrelated.py").write_text("Z = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import toy_cache_pkg  # noqa: F401

    assert _imported_names(package / "stage.py", "toy_cache_pkg.stage") >= {
        "toy_cache_pkg.sub.helper",
        "toy_cache_pkg.lazy",
    }
    before = code_fingerprint("toy_cache_pkg.stage")
    (package / "unrelated.py").write_text("Z = 2\n")
    code_fingerprint.cache_clear()
    assert code_fingerprint("toy_cache_pkg.stage") == before
    (package / "sub" / "helper.py").write_text("X = 2\n")
    code_fingerprint.cache_clear()
    after_helper = code_fingerprint("toy_cache_pkg.stage")
    assert after_helper != before
    (package / "lazy.py").write_text("Y = 2\n")
    code_fingerprint.cache_clear()
    assert code_fingerprint("toy_cache_pkg.stage") != after_helper
    code_fingerprint.cache_clear()


def test_sgf_cache_shows_and_clears_the_entries(tmp_path: Path) -> None:
    import subprocess
    import sys

    cache = StageCache(tmp_path, 10**12)
    for kind, key in (("ipm", "a" * 32), ("saliency", "b" * 32)):
        writer = cache.writer(kind, key, {"stage": f"{kind}=test"})
        writer.add(0, np.zeros(10))
        writer.commit()
    command = [str(Path(sys.executable).parent / "sgf-cache"), f"dir={tmp_path}"]
    shown = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    assert "ipm=test" in shown and "saliency=test" in shown and "2 entries" in shown
    cleared = subprocess.run(
        [*command[:1], "clear", "kind=ipm", command[1]], capture_output=True, text=True, check=True
    )
    assert "removed 1 entries" in cleared.stdout
    assert [e.kind for e in cache.entries()] == ["saliency"]
    bad = subprocess.run([*command, "action=purge"], capture_output=True, text=True)
    assert bad.returncode == 2 and "action=purge" in bad.stderr


# -- the runner with small stages ----------------------------------------------------------------


@pytest.fixture
def toy(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):  # type: ignore[no-untyped-def]
    from toy_stages import ToyPlugin

    from sgf_pipeline import load_plugins

    monkeypatch.delenv(STAGE_CACHE_ENV, raising=False)
    plugins = load_plugins(extra=[("toy", ToyPlugin())])
    cfg = {
        "pipeline": ["dataset", "enhance", "measure", "counter", "gate", "consumer"],
        "dataset": {"name": "figure_eight", "frames": 30},
        "enhance": {"name": "none"},
        "measure": {"name": "brightness"},
        "counter": {"name": "feedback", "start": 5},  # Previous[int]: never cached
        "gate": {"name": "even"},  # None on odd frames
        "consumer": {"name": "strict"},  # skipped when its input is None
        "run": {"progress": False, "cache_dir": str(tmp_path / "cache")},
    }
    return lambda: Pipeline.from_config(cfg, plugins=plugins)


def outputs(pipeline: Pipeline) -> list[dict[str, Any]]:
    steps = [pipeline.process(frame).outputs for frame in pipeline.frames()]
    return [{k: v for k, v in step.items() if k not in ("frame", "image")} for step in steps]


def test_the_runner_takes_only_the_stages_before_any_feedback_from_the_cache(toy) -> None:  # type: ignore[no-untyped-def]
    first = toy()
    computed = outputs(first)
    assert first.finish()["cache"]["misses"] == ["consumer", "enhance", "gate", "measure"]
    second = toy()
    assert outputs(second) == computed
    report = second.finish()["cache"]
    assert report["hits"] == ["consumer", "enhance", "gate", "measure"] and report["dataset_from_cache"]
    assert [step["consumed"] for step in computed[:4]] == [0, None, 20, None]
    assert [step["count"] for step in computed[:3]] == [5, 6, 7]  # the feedback stage ran


def test_a_run_fed_other_frames_computes_everything_or_is_refused(toy) -> None:  # type: ignore[no-untyped-def]
    outputs(toy())  # nothing kept: finish() was not called
    driven = toy()
    for frame in driven.dataset.frames():  # a robot's driver: the cache stays out of it
        driven.process(frame)
    assert "cache" not in driven.finish()
    mixed = toy()
    first = next(iter(mixed.frames()))
    mixed.process(first)
    with pytest.raises(CacheError, match=r"did not come from Pipeline.frames\(\)"):
        mixed.process(next(iter(mixed.dataset.frames())))
    mixed.release()


def test_a_run_that_skips_frames_keeps_no_entry(toy, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    pipeline = toy()
    for n, frame in enumerate(pipeline.frames()):
        if n % 2 == 0:
            pipeline.process(frame)
    assert pipeline.finish()["cache"]["misses"] == ["consumer", "enhance", "gate", "measure"]
    assert StageCache(tmp_path / "cache", 10**12).entries() == []


def test_the_run_summary_says_how_many_stages_came_from_the_cache() -> None:
    from sgf_pipeline.cli.run import summary

    metrics: dict[str, Any] = {"sequence": "toy", "ate_rmse_m": {"odometry": 2.0, "sgf": 0.5}}
    metrics |= {"sgf": {"detected": 3, "total": 4}, "loops": dict.fromkeys(("pairs_found", "closed"), None)}
    metrics["loops"] |= dict.fromkeys(("pairs_total", "pairs_found_reverse", "pairs_total_reverse"), None)
    metrics["loops"] |= dict.fromkeys(("closed_reverse", "false_closed"), None)
    assert "from the cache" not in summary(metrics, Path("nowhere"))
    metrics["cache"] = {"hits": ["ipm", "saliency"], "misses": ["detector"], "dataset_from_cache": False}
    assert "stages from the cache       2 of 3\n" in summary(metrics, Path("nowhere"))
    metrics["cache"] = {"hits": ["ipm", "saliency"], "misses": [], "dataset_from_cache": True}
    assert "stages from the cache       2 of 2, no image read" in summary(metrics, Path("nowhere"))
