"""The configuration folder: every option of every group validates against its registered variant or observer."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from sgf_experiments import CONF as EXPERIMENTS_CONF

from sgf_pipeline import Pipeline, load_plugins
from sgf_pipeline.config import RESERVED_KEYS, config_dir

CONF = config_dir()
APP_CONFIGS = {"config", "sgf_plugins"}
#: groups that are no stage
NON_STAGE_GROUPS = {"local", "hydra"}


def stage_options() -> list[tuple[str, Path]]:
    return [
        (group.name, path)
        for group in sorted(CONF.iterdir())
        if group.is_dir() and group.name not in NON_STAGE_GROUPS and not group.name.startswith("_")
        for path in sorted(group.glob("*.yaml"))
    ]


@pytest.fixture(scope="module")
def plugins():
    return load_plugins()


@pytest.mark.parametrize(("kind", "path"), stage_options(), ids=lambda v: getattr(v, "stem", v))
def test_each_option_validates_against_its_variant(plugins, kind: str, path: Path):
    with initialize_config_dir(str(CONF), version_base="1.3"):  # composed: a preset extends its base
        node = OmegaConf.to_container(compose("config", overrides=[f"{kind}={path.stem}"])[kind], resolve=True)
    assert isinstance(node, dict) and "name" in node, f"{path} needs a `name` key"
    observer = plugins.observer_options.get(kind)  # an observer's node (viz), else a stage variant's
    if observer is not None:
        params, model = node, observer
    else:
        params = {k: v for k, v in node.items() if k not in RESERVED_KEYS}
        model = plugins.registry.get(kind, node["name"]).params_model
    validated = model.model_validate(params)
    for key, value in params.items():
        assert getattr(validated, key) == value or isinstance(value, (list, dict)), (path, key)
    first_line = path.read_text().splitlines()[0]
    assert first_line.startswith("#"), f"{path} should start with a comment saying what it is"


def test_the_default_config_builds_a_valid_pipeline():
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config")
    pipeline = Pipeline.from_config(cfg)
    assert pipeline.order[0].kind == "dataset"
    assert [n.kind for n in pipeline.order] == list(cfg.pipeline) or set(n.kind for n in pipeline.order) == set(
        cfg.pipeline
    )


@pytest.mark.parametrize("name", sorted(p.stem for p in (EXPERIMENTS_CONF / "experiment").glob("*.yaml")))
def test_each_experiment_composes(name: str):
    text = (EXPERIMENTS_CONF / "experiment" / f"{name}.yaml").read_text()
    app = "sgf_sod_eval" if "# app: sgf-sod-eval" in text else "config"
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(app, overrides=[f"+experiment={name}"], return_hydra_config=True)
    if app == "config":
        assert "pipeline" in cfg
        if cfg.hydra.mode is None:  # one configuration, named by its tag (the paper as printed)
            assert not cfg.hydra.sweeper.params and cfg.run.tag
            return
        assert cfg.hydra.mode.name == "MULTIRUN"
        assert cfg.hydra.sweeper.params, "an experiment sweeps something"
        for key in cfg.hydra.sweeper.params:
            if key.startswith("+"):  # a config group added per job (conf/perturbation)
                assert (EXPERIMENTS_CONF / key[1:]).is_dir(), key
                continue
            assert key.split(".")[0] in cfg or key.split(".")[0] in cfg.pipeline
    else:
        assert list(cfg.models) == ["selfreformer", "u2net", "u2netp", "ldf", "classical"]


def test_conf_is_inside_the_package_and_the_wheel(tmp_path: Path):
    assert (Path(__file__).resolve().parents[1] / "sgf_pipeline" / "conf" / "config.yaml").is_file()
    root = Path(__file__).resolve().parents[1]
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(tmp_path),
            str(root),
        ],
        check=True,
        capture_output=True,
    )
    wheel = next(tmp_path.glob("sgf_pipeline-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for conf_file in CONF.rglob("*.yaml"):
        rel = conf_file.relative_to(CONF)
        if rel.parts[0] == "local":
            continue
        assert f"sgf_pipeline/conf/{rel.as_posix()}" in names
    assert "sgf_pipeline/conf/.sgf_pipeline_conf" in names
    assert "hydra_plugins/sgf_pipeline_searchpath/searchpath.py" in names
    assert any(n.startswith("sgf_plugins/") for n in names)
    for conf_file in EXPERIMENTS_CONF.rglob("*.yaml"):
        assert f"sgf_experiments/conf/{conf_file.relative_to(EXPERIMENTS_CONF).as_posix()}" in names


def test_design_weights_are_set_from_the_command_line():
    """A preset's ``design_weights: null`` takes a whole dict from an override (an empty dict would refuse new keys)."""
    from sgf_plugins.world.params import WorldParams

    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["dataset=campus_delivery", "dataset.design_weights={random_shape:8}"])
    node = OmegaConf.to_container(cfg.dataset, resolve=True)
    assert isinstance(node, dict)
    params = WorldParams.model_validate({k: v for k, v in node.items() if k not in RESERVED_KEYS})
    assert params.design_weights == {"random_shape": 8.0}


CAMPUS_PRESETS = ("campus_delivery", "campus_large_loop", "campus_large_loop_night", "campus_reverse_slope")


def composed_dataset(name: str) -> dict[str, object]:
    with initialize_config_dir(str(CONF), version_base="1.3"):
        node = OmegaConf.to_container(compose("config", overrides=[f"dataset={name}"]).dataset, resolve=True)
    assert isinstance(node, dict)
    return {str(k): v for k, v in node.items()}


def test_the_campus_presets_differ_in_their_route_and_the_night_alone():
    nodes = {name: composed_dataset(name) for name in CAMPUS_PRESETS}
    delivery = nodes["campus_delivery"]
    changed = {name: {k for k, v in node.items() if delivery[k] != v} for name, node in nodes.items()}
    assert changed == {
        "campus_delivery": set(),
        "campus_large_loop": {"name"},
        "campus_large_loop_night": {"name", "night"},
        "campus_reverse_slope": {"name"},
    }
