"""Each default is written once, in a variant's pydantic Params; ``conf/`` states only what differs.

Hydra composes ``<kind>=<variant>`` from the Params defaults (the ``sgf-defaults://`` config source),
so ``<kind>.<key>=<value>`` overrides work in Hydra's struct mode with no YAML; a preset in ``conf/``
(``enhance=auto``, ``ipm=mc_ahead``) names its variant and the keys it changes.
"""

from __future__ import annotations

from typing import Any

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from pydantic import BaseModel, Field, ValidationError

from sgf_pipeline import StageParams, load_plugins
from sgf_pipeline.config import (
    CONFIG_VALUE,
    RESERVED_KEYS,
    RunOptions,
    config_dir,
    defaults_node,
    format_validation_error,
)
from sgf_pipeline.registry import describe_params

CONF = config_dir()
VARIANTS = [(v.kind, v.name) for v in load_plugins().registry]
PRESETS = sorted(p for p in CONF.glob("*/*.yaml"))


@pytest.fixture(scope="module")
def plugins():
    return load_plugins()


def composed(*overrides: str) -> dict[str, Any]:
    with initialize_config_dir(str(CONF), version_base="1.3"):
        node = OmegaConf.to_container(compose("config", overrides=list(overrides)), resolve=True)
    assert isinstance(node, dict)
    return node


def changed(node: dict[str, Any], defaults: dict[str, Any], prefix: str) -> list[str]:
    """The keys of ``node`` that repeat their default (or name no parameter), into parameter groups."""
    found = []
    for key, value in node.items():
        if key not in defaults:
            found.append(f"{prefix}{key}: no such parameter")
        elif isinstance(value, dict) and isinstance(defaults[key], dict):
            found += changed(value, defaults[key], f"{prefix}{key}.")
        elif value == defaults[key]:
            found.append(f"{prefix}{key}: repeats the default {value!r}")
    return found


@pytest.mark.parametrize(("kind", "name"), VARIANTS, ids=[f"{k}={n}" for k, n in VARIANTS])
def test_a_variant_composes_to_its_params_defaults(plugins, kind: str, name: str):
    extra = ["dataset.path=/data"] if kind == "dataset" and not name.startswith("campus") else []
    node = composed(f"{kind}={name}", *extra)[kind]
    assert node.pop("name") == name
    model = plugins.registry.get(kind, name).params_model
    assert list(node) == list(model.model_fields)  # every key, in the Params' order
    if extra:
        node.pop("path")
    else:
        assert model.model_validate(node) == model()
    assert not (CONF / kind / f"{name}.yaml").exists(), "a variant's own YAML would repeat its defaults"


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: f"{p.parent.name}={p.stem}")
def test_a_preset_names_its_variant_and_only_the_keys_it_changes(plugins, path):
    raw = yaml.safe_load(path.read_text())
    assert raw.pop("defaults")[-1] == "_self_"
    kind = path.parent.name
    node = composed(f"{kind}={path.stem}")[kind]
    model = plugins.registry.get(kind, node["name"]).params_model
    assert path.read_text().startswith("#")  # says what the preset is for
    assert raw and not changed(raw, defaults_node(model), f"{kind}.")
    assert model.model_validate({k: v for k, v in node.items() if k not in RESERVED_KEYS})


def test_the_default_config_states_only_what_differs_from_the_runners_defaults():
    raw = yaml.safe_load((CONF / "config.yaml").read_text())
    assert not changed(raw["run"], defaults_node(RunOptions), "run.")
    assert "plugins" not in raw  # all at their defaults
    run = composed()["run"]
    assert RunOptions.model_validate(run) == RunOptions(keyframe_distance=raw["run"]["keyframe_distance"])


def test_every_parameter_says_what_it_is(plugins):
    missing = [
        f"{v.kind}={v.name}: {key}"
        for v in plugins.registry
        for key, _, _, description in describe_params(v.params_model)
        if not description
    ]
    assert not missing, "parameters without a description (sgf-plugins shows it):\n  " + "\n  ".join(missing)


def test_an_observer_node_composes_to_its_options_defaults(plugins):
    for node_name, model in plugins.observer_options.items():
        name = model.model_fields["name"].default
        assert composed(f"{node_name}={name}")[node_name] == model().model_dump(mode="json")


def test_the_prior_map_key_reaches_the_association_and_the_back_ends():
    for backend in ("isam2", "gtsam_lm"):
        node = composed(f"backend={backend}", "map.prior=/maps/campus.safetensors")
        assert node["association"]["prior_map"] == node["backend"]["prior_map"] == "/maps/campus.safetensors"
    assert composed()["backend"]["prior_map"] is None


class Gate(BaseModel):
    sigma_yaw_deg: float = 2.0
    probability: float = 0.99


class Nested(StageParams):
    icp_iterations: int = 30
    gate: Gate = Field(default_factory=Gate)
    wide: Gate = Field(default_factory=lambda: Gate(sigma_yaw_deg=5.0))
    required: float
    prior: str | None = Field(None, json_schema_extra={CONFIG_VALUE: "${oc.select:map.prior,null}"})


def test_a_defaults_node_holds_groups_factories_required_keys_and_wired_values():
    assert defaults_node(Nested) == {
        "icp_iterations": 30,
        "gate": {"sigma_yaw_deg": 2.0, "probability": 0.99},
        "wide": {"sigma_yaw_deg": 5.0, "probability": 0.99},
        "required": "???",
        "prior": "${oc.select:map.prior,null}",
    }


def test_sgf_plugins_describes_nested_parameters_by_their_override_keys():
    rows = describe_params(Nested)
    assert [(key, default) for key, _, default, _ in rows][:3] == [
        ("icp_iterations", 30),
        ("gate.sigma_yaw_deg", 2.0),
        ("gate.probability", 0.99),
    ]


def test_a_config_error_inside_a_parameter_group_names_the_dotted_key_and_the_groups_parameters():
    class Strict(StageParams):
        gate: StrictGate = Field(default_factory=lambda: StrictGate())

    with pytest.raises(ValidationError) as wrong_type:
        Strict.model_validate({"gate": {"sigma_yaw_deg": "wide"}})
    assert format_validation_error("loop", Strict, wrong_type.value).endswith("; expected float")
    assert format_validation_error("loop", Strict, wrong_type.value).startswith("loop.gate.sigma_yaw_deg: ")
    with pytest.raises(ValidationError) as unknown:
        Strict.model_validate({"gate": {"sigma_yaw": 2.0}})
    assert format_validation_error("loop", Strict, unknown.value) == (
        "loop.gate.sigma_yaw: unknown parameter (parameters of loop.gate: sigma_yaw_deg, probability)"
    )
    with pytest.raises(ValidationError) as flat:
        Strict.model_validate({"gates": {}})
    assert format_validation_error("loop", Strict, flat.value) == (
        "loop.gates: unknown parameter (parameters of this variant: gate)"
    )


class StrictGate(StageParams):
    sigma_yaw_deg: float = 2.0
    probability: float = 0.99
