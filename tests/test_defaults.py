"""Each default is written once: a variant's YAML holds every key of its Params, each at the Params default.

The pydantic ``Params`` model is where a default is decided; ``conf/<kind>/<variant>.yaml`` repeats
every key so that ``<kind>.<key>=<value>`` overrides work in Hydra's struct mode. These tests prove
the two agree, key by key and into nested parameter groups (``loop.gate.sigma_yaw_deg``).
"""

from __future__ import annotations

from typing import Any

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from pydantic import BaseModel, Field, ValidationError
from pydantic_core import PydanticUndefined

from sgf_pipeline import StageParams, load_plugins
from sgf_pipeline.config import RESERVED_KEYS, config_dir, format_validation_error
from sgf_pipeline.registry import describe_params

CONF = config_dir()


def disagreements(
    model: type[BaseModel], node: dict[str, Any], validated: BaseModel, defaults: dict[str, Any], prefix: str
) -> list[str]:
    """Where a config node and a model's defaults differ: keys missing or unknown, values not the default."""
    found = [f"{prefix}{key}: in the YAML but not a parameter" for key in sorted(set(node) - set(model.model_fields))]
    for key in model.model_fields:
        where = prefix + key
        default = defaults[key]
        if key not in node:
            found.append(f"{where}: missing from the YAML (Params default {default!r})")
            continue
        value = getattr(validated, key)
        if isinstance(default, BaseModel) and isinstance(value, BaseModel) and isinstance(node[key], dict):
            inner = {name: getattr(default, name) for name in type(default).model_fields}
            found += disagreements(type(default), node[key], value, inner, where + ".")
        elif default is not PydanticUndefined and value != default:
            found.append(f"{where}: the YAML says {node[key]!r}, the Params default is {default!r}")
    return found


def node_disagreements(model: type[BaseModel], node: dict[str, Any], prefix: str) -> list[str]:
    """:func:`disagreements` of a whole stage node against its Params model's defaults."""
    defaults = {key: info.get_default(call_default_factory=True) for key, info in model.model_fields.items()}
    return disagreements(model, node, model.model_validate(node), defaults, prefix)


def variants_with_yaml() -> list[tuple[str, str]]:
    """``(kind, name)`` of every registered variant that has ``conf/<kind>/<name>.yaml``."""
    registry = load_plugins().registry
    return [(v.kind, v.name) for v in registry if (CONF / v.kind / f"{v.name}.yaml").is_file()]


VARIANTS = variants_with_yaml()


@pytest.fixture(scope="module")
def plugins():
    return load_plugins()


def test_every_stage_kind_has_variants_with_yaml():
    assert {"dataset", "ipm", "loop", "association", "backend"} <= {kind for kind, _ in VARIANTS}


@pytest.mark.parametrize(("kind", "name"), VARIANTS, ids=[f"{k}={n}" for k, n in VARIANTS])
def test_the_yaml_of_a_variant_holds_its_params_defaults(plugins, kind: str, name: str):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=[f"{kind}={name}"])
    node = OmegaConf.to_container(cfg[kind], resolve=True)
    assert isinstance(node, dict) and node["name"] == name
    params = {str(k): v for k, v in node.items() if k not in RESERVED_KEYS}
    found = node_disagreements(plugins.registry.get(kind, name).params_model, params, f"{kind}.")
    assert not found, f"conf/{kind}/{name}.yaml and the Params of {kind}={name} disagree:\n  " + "\n  ".join(found)


class Gate(BaseModel):
    sigma_yaw_deg: float = 2.0
    probability: float = 0.99


class Nested(StageParams):
    icp_iterations: int = 30
    gate: Gate = Field(default_factory=Gate)


def test_nested_parameter_groups_are_compared_key_by_key():
    agreeing = {"icp_iterations": 30, "gate": {"sigma_yaw_deg": 2.0, "probability": 0.99}}
    assert node_disagreements(Nested, agreeing, "loop.") == []
    off = {"icp_iterations": 30, "gate": {"sigma_yaw_deg": 3.0}}
    assert node_disagreements(Nested, off, "loop.") == [
        "loop.gate.sigma_yaw_deg: the YAML says 3.0, the Params default is 2.0",
        "loop.gate.probability: missing from the YAML (Params default 0.99)",
    ]
    unknown = {"icp_iterations": 31, "gate": {"sigma_yaw_deg": 2.0, "probability": 0.99}, "extra": 1}
    with pytest.raises(ValueError, match="extra"):  # StageParams refuses unknown keys before any comparison
        node_disagreements(Nested, unknown, "loop.")


def test_sgf_plugins_describes_nested_parameters_by_their_override_keys():
    rows = describe_params(Nested)
    assert [(key, default) for key, _, default, _ in rows] == [
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
