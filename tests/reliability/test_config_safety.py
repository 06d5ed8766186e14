"""A configuration from someone else can never run code or read past its own values into the run.

Checked three ways: the source never calls what could import or execute from a config (Hydra's
instantiate, eval, pickle, ...); at run time a `_target_` anywhere is refused before anything is
imported, and every OmegaConf resolver is known and harmless; and any config (fuzzed) gives a
pipeline or a ConfigError. Wrong types, unknown keys and out-of-range values name the key.
"""

from __future__ import annotations

import ast
import contextlib
import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest
from adapters.recordings import calibration, make_frames, write_folder
from hydra import compose, initialize_config_dir
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf
from sgf_testing import ROOT
from toy_stages import ToyPlugin

from sgf_pipeline import ConfigError, Pipeline, SgfError, load_plugins
from sgf_pipeline.config import config_dir, parse_config

# -- the source ---------------------------------------------------------------------------------

#: Calls that import or run code named by data, or unpickle it.
FORBIDDEN_CALLS = {
    "eval",
    "exec",
    "compile",
    "__import__",
    "importlib.import_module",
    "hydra.utils.instantiate",
    "hydra.utils.call",
    "hydra.utils.get_class",
    "hydra.utils.get_method",
    "hydra.utils.get_object",
    "instantiate",
    "pydoc.locate",
    "yaml.load",
    "yaml.unsafe_load",
    "yaml.full_load",
    "torch.load",
    "os.system",
    "os.popen",
    "pickle.load",
    "pickle.loads",
}
FORBIDDEN_MODULES = {"pickle", "cPickle", "dill", "cloudpickle", "shelve", "marshal", "joblib"}


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _offences(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Call):
            name = _dotted(node.func)
            if name in FORBIDDEN_CALLS:
                found.append(f"{where}: calls {name}")
            for keyword in node.keywords:
                if keyword.arg == "allow_pickle" and not (
                    isinstance(keyword.value, ast.Constant) and keyword.value.value is False
                ):
                    found.append(f"{where}: allow_pickle")
        elif isinstance(node, ast.Import):
            found += [f"{where}: imports {a.name}" for a in node.names if a.name.split(".")[0] in FORBIDDEN_MODULES]
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.module.split(".")[0] in FORBIDDEN_MODULES:
                found.append(f"{where}: imports from {node.module}")
            if node.module in ("hydra.utils", "hydra._internal.instantiate._instantiate2"):
                found.append(f"{where}: imports from {node.module}")
    return found


def test_no_source_file_can_import_or_run_code_named_by_data():
    files = [p for d in ("sgf_pipeline", "plugins", "hydra_plugins") for p in (ROOT / d).rglob("*.py")]
    assert len(files) > 40
    offences = [o for path in files for o in _offences(path)]
    assert offences == []


def test_the_scan_finds_what_it_looks_for(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    bad = tmp_path / "bad.py"
    bad.write_text(
        "import pickle\nfrom hydra.utils import instantiate\nimport numpy as np\n"
        "x = eval('1')\ny = np.load('a', allow_pickle=True)\nz = instantiate({})\n"
    )
    assert _offences(bad) == [
        "bad.py:1: imports pickle",
        "bad.py:2: imports from hydra.utils",
        "bad.py:4: calls eval",
        "bad.py:5: allow_pickle",
        "bad.py:6: calls instantiate",
    ]


# -- `_target_` ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def toy_plugins():
    return load_plugins(extra=[("toy", ToyPlugin())])


def _toy_config(**extra: Any) -> dict[str, Any]:
    cfg: dict[str, Any] = {
        "pipeline": ["dataset", "enhance"],
        "dataset": {"name": "figure_eight", "frames": 4},
        "enhance": {"name": "none"},
        "run": {"progress": False},
    }
    cfg.update(extra)
    return cfg


CANARY = {"_target_": "reliability.canary.fire", "_args_": ["boom"]}


@pytest.mark.parametrize(
    ("where", "cfg", "key"),
    [
        ("a stage node", _toy_config(enhance={"name": "none", **CANARY}), "enhance._target_"),
        (
            "a nested value",
            _toy_config(enhance={"name": "clahe", "opts": [{"x": CANARY}]}),
            r"enhance.opts\[0\].x._target_",
        ),
        ("the run node", _toy_config(run={"progress": False, "hook": CANARY}), "run.hook._target_"),
        ("the plugins node", _toy_config(plugins=CANARY), "plugins._target_"),
        ("the top level", {**_toy_config(), **CANARY}, "_target_"),
        ("a node outside the pipeline", _toy_config(backend=CANARY), "backend._target_"),
    ],
)
def test_a_target_anywhere_is_refused_before_anything_is_imported(toy_plugins, where: str, cfg, key: str):
    with pytest.raises(ConfigError, match=rf"^{key}: `_target_` is refused\. Variants are chosen by registered name"):
        Pipeline.from_config(cfg, plugins=toy_plugins)
    assert "reliability.canary" not in sys.modules
    assert "SGF_CANARY_IMPORTED" not in os.environ and "SGF_CANARY_FIRED" not in os.environ


def test_hydra_instantiate_is_never_called_by_a_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    import hydra.utils
    from hydra._internal.instantiate import _instantiate2

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("instantiate was called")

    monkeypatch.setattr(_instantiate2, "instantiate", refuse)
    monkeypatch.setattr(hydra.utils, "instantiate", refuse)
    monkeypatch.setattr(hydra.utils, "call", refuse)
    folder = write_folder(tmp_path / "seq", make_frames(3, seed=1), calibration())
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "dataset=folder",
                f"dataset.path={folder}",
                "pipeline=[dataset,enhance,ipm]",
                "run.progress=false",
                "run.plots=false",
            ],
        )
    metrics = Pipeline.from_config(cfg, run_dir=tmp_path / "run").run()
    assert metrics["timing"]["frames"] == 3 and metrics["stages"]["ipm"] == "mc"


# -- OmegaConf resolvers --------------------------------------------------------------------------

#: Every resolver a composed sgf config can use, and what it gives (docs/reliability.md has the table).
DOCUMENTED_RESOLVERS = {
    "oc.env": "an environment variable's value (or a default)",
    "oc.create": "a config node from a YAML-like literal",
    "oc.decode": "a value parsed by OmegaConf's grammar (no Python)",
    "oc.deprecated": "another key's value, with a warning",
    "oc.select": "another key's value, or a default",
    "oc.dict.keys": "the keys of a config node",
    "oc.dict.values": "the values of a config node",
    "now": "the current time, formatted (Hydra)",
    "hydra": "a value of Hydra's own config (Hydra)",
    "python_version": "the Python version (Hydra)",
    "ray_pkg_version": "a package's version string (Hydra's Ray launcher, when installed)",
}


def _compose(*overrides: str):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("config", overrides=["dataset=folder", "pipeline=[dataset]", *overrides])


def test_every_registered_resolver_is_documented():
    from omegaconf.basecontainer import BaseContainer

    _compose()
    registered = set(BaseContainer._resolvers)
    assert registered <= set(DOCUMENTED_RESOLVERS), registered - set(DOCUMENTED_RESOLVERS)
    assert {"oc.env", "oc.decode", "oc.create", "now", "hydra"} <= registered
    doc = (ROOT / "docs" / "reliability.md").read_text()
    for name in DOCUMENTED_RESOLVERS:
        assert f"`{name}`" in doc, f"docs/reliability.md does not describe the resolver {name}"


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("${eval:1+1}", r"dataset.path: the value cannot be resolved: Unsupported interpolation type eval"),
        ("${python:os.system}", r"Unsupported interpolation type python"),
        ('${oc.decode:\'__import__("os").system("touch pwned")\'}', r"dataset.path: the value cannot be resolved: .*"),
        ("${oc.env:SGF_SURELY_NOT_SET_123}", r"Environment variable 'SGF_SURELY_NOT_SET_123' not found"),
        ("${no.such.key}", r"Interpolation key 'no.such.key' not found"),
        ("???", r"dataset.path: the value cannot be resolved: Missing mandatory value"),
    ],
)
def test_a_value_that_cannot_be_resolved_is_a_config_error(tmp_path: Path, monkeypatch, value: str, message: str):
    monkeypatch.chdir(tmp_path)
    cfg = _compose()
    OmegaConf.update(cfg, "dataset.path", value, force_add=True)
    with pytest.raises(ConfigError, match=message) as err:
        Pipeline.from_config(cfg)
    assert "registered resolvers (" in str(err.value) and "none of them imports or runs code" in str(err.value)
    assert not (tmp_path / "pwned").exists()


def test_oc_create_cannot_smuggle_a_target():
    cfg = _compose()
    OmegaConf.update(cfg, "dataset.extra", "${oc.create:{_target_: os.system, _args_: [true]}}", force_add=True)
    with pytest.raises(ConfigError, match=r"dataset.extra._target_: `_target_` is refused"):
        Pipeline.from_config(cfg)


def test_oc_env_values_reach_the_effective_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    folder = write_folder(tmp_path / "seq", make_frames(2, seed=3), calibration())
    monkeypatch.setenv("SGF_TEST_DATA", str(folder))
    cfg = _compose("dataset.path=${oc.env:SGF_TEST_DATA}", "run.progress=false")
    Pipeline.from_config(cfg, run_dir=tmp_path / "run").run()
    saved = (tmp_path / "run" / "config.yaml").read_text()
    assert f"path: {folder}" in saved and "oc.env" not in saved  # resolved values are saved: no secrets in configs


# -- any config: a pipeline or a ConfigError -----------------------------------------------------

JSONISH = st.recursive(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-3, 10**12),
        st.floats(allow_nan=True, allow_infinity=True),
        st.sampled_from(["none", "clahe", "figure_eight", "brightness", "feedback", "dataset", "enhance", "x"]),
    ),
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(
            st.sampled_from(["name", "frames", "step", "clip_limit", "tiles", "rename", "start", "q"]), inner
        ),
    ),
    max_leaves=12,
)
STAGE_NODE = st.fixed_dictionaries(
    {"name": st.one_of(st.sampled_from(["none", "clahe", "figure_eight", "brightness", "feedback"]), JSONISH)},
    optional={k: JSONISH for k in ("frames", "step", "clip_limit", "tiles", "rename", "start", "bogus")},
)
CONFIG = st.fixed_dictionaries(
    {},
    optional={
        "pipeline": st.one_of(
            st.lists(st.sampled_from(["dataset", "enhance", "measure", "counter", "teleport"]), max_size=4), JSONISH
        ),
        "dataset": STAGE_NODE,
        "enhance": STAGE_NODE,
        "measure": STAGE_NODE,
        "counter": STAGE_NODE,
        "run": st.one_of(
            st.fixed_dictionaries(
                {}, optional={k: JSONISH for k in ("max_frames", "keyframe_distance", "progress", "progres")}
            ),
            JSONISH,
        ),
        "plugins": st.one_of(st.fixed_dictionaries({}, optional={"allow": JSONISH, "block": JSONISH}), JSONISH),
        "typo": JSONISH,
    },
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cfg=CONFIG)
def test_any_config_gives_a_pipeline_or_a_config_error(toy_plugins, cfg: dict[str, Any]):
    try:
        pipeline = Pipeline.from_config(cfg, plugins=toy_plugins)
    except ConfigError as exc:
        assert str(exc) and "Traceback" not in str(exc)
        return
    assert pipeline.order[0].kind == "dataset"
    with contextlib.suppress(SgfError):  # a stage may refuse its input (a StageError names it)
        pipeline.run()


# -- wrong types, unknown keys, out-of-range values ----------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["ipm=mc", "ipm.queue_size=0"], r"ipm.queue_size: Input should be greater than or equal to 1 \(got 0\)"),
        (["ipm=mc", "ipm.pitch_threshold=-0.1"], r"ipm.pitch_threshold: Input should be greater than 0"),
        (["ipm=mc", "ipm.resolution=fine"], r"ipm.resolution: Input should be a valid number.*expected float"),
        (["ipm=plain", "ipm.x_max=0.1"], r"x_max \(0.1\) must be greater than x_min \(0.5\)"),
        (["ipm=mc", "ipm.attitude=gps"], r"ipm.attitude: Input should be 'auto', 'imu' or 'odometry'"),
        (
            ["ipm=mc", "+ipm.queue_sise=10"],
            r"ipm.queue_sise: unknown parameter \(parameters of this variant: .*queue_size",
        ),
        (["enhance=clahe", "enhance.tiles=[1,2]"], r"enhance.tiles: Input should be a valid integer"),
        (["dataset.max_time_diff=0"], r"dataset.max_time_diff: Input should be greater than 0"),
        (["dataset.strict=maybe"], r"dataset.strict: Input should be a valid boolean"),
        (["run.keyframe_angle=0"], r"run.keyframe_angle: Input should be greater than 0"),
        (["run.max_frames=0"], r"run.max_frames: Input should be greater than or equal to 1"),
        (["run.ate_max_time_diff=inf"], r"run.ate_max_time_diff: Input should be a finite number"),
        (["run=fast"], r"run: must be a mapping of options \(keyframe_distance, .*\), got 'fast'"),
        (["plugins.allow=enhance"], r"plugins.allow: Input should be a valid list"),
        (["+rn.max_frames=3"], r"unknown top-level key\(s\) \['rn'\]: a config holds pipeline, run, plugins"),
        (["pipeline=[dataset,1]"], r"`pipeline` lists stage kinds by name; 1 is not a name"),
        (["pipeline=dataset"], r"`pipeline` must be a non-empty list of stage kinds, got 'dataset'"),
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, overrides: list[str], message: str):
    folder = write_folder(tmp_path / "seq", make_frames(2, seed=3), calibration())
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["dataset=folder", f"dataset.path={folder}", *overrides])
    if "pipeline=" not in " ".join(overrides):
        OmegaConf.update(cfg, "pipeline", [k for k in ("dataset", "enhance", "ipm") if k in cfg])
    with pytest.raises(ConfigError, match=message):
        Pipeline.from_config(cfg)


def test_an_allow_list_leaves_the_nodes_of_other_paper_stages_alone(tmp_path: Path):
    """A deployment that allows only some plugins still composes the default config's other stage nodes."""
    folder = write_folder(tmp_path / "seq", make_frames(2, seed=3), calibration())
    cfg = _compose(
        f"dataset.path={folder}",
        "pipeline=[dataset,enhance]",
        "plugins.allow=[dataset_folder,enhance]",
        "run.progress=false",
    )
    assert cfg.ipm.name == "mc"  # composed by the defaults list, but its plugin is not allowed
    pipeline = Pipeline.from_config(cfg)
    assert pipeline.plugins.registry.kinds() == ["dataset", "enhance"]
    assert pipeline.run()["timing"]["frames"] == 2


def test_detector_and_descriptor_values_are_checked(toy_plugins):
    cfg = _toy_config(pipeline=["dataset", "detector"], detector={"name": "hu_window", "threshold": 1.5})
    with pytest.raises(ConfigError, match=r"detector.threshold: Input should be less than 1"):
        Pipeline.from_config(cfg, plugins=toy_plugins)
    cfg = _toy_config(pipeline=["dataset", "detector"], detector={"name": "hu_window", "max_track_views": 1})
    with pytest.raises(ConfigError, match=r"detector.max_track_views: Input should be greater than or equal to 2"):
        Pipeline.from_config(cfg, plugins=toy_plugins)
    cfg = _toy_config(pipeline=["dataset", "descriptor"], descriptor={"name": "polar_context", "num_sectors": 2})
    with pytest.raises(ConfigError, match=r"descriptor.num_sectors: Input should be greater than or equal to 4"):
        Pipeline.from_config(cfg, plugins=toy_plugins)


def test_a_config_that_is_not_a_mapping(toy_plugins):
    with pytest.raises(ConfigError, match=r"a configuration is a mapping .*got \['dataset'\]"):
        Pipeline.from_config(["dataset"], plugins=toy_plugins)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"a configuration is a mapping"):
        parse_config("pipeline: [dataset]")  # type: ignore[arg-type]


def test_a_json_config_file_round_trip_keeps_the_refusals(toy_plugins, tmp_path: Path):
    """A config shipped as a file (JSON here, YAML alike) goes through the same checks."""
    path = tmp_path / "deploy.json"
    path.write_text(json.dumps(_toy_config(enhance={"name": "none", **CANARY})))
    with pytest.raises(ConfigError, match=r"enhance._target_"):
        Pipeline.from_config(json.loads(path.read_text()), plugins=toy_plugins)
