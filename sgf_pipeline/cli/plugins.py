"""``sgf-plugins``: list the registered stage kinds, variants, parameters and their packages.

``format=markdown`` writes the configuration reference (``docs/configuration.md``): the runner's
options, then every stage kind, variant and parameter, then the observers' config nodes.
"""

from __future__ import annotations

import json
from typing import Any

import hydra
import yaml
from omegaconf import DictConfig
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import PluginOptions, RunOptions, config_dir
from sgf_pipeline.errors import ConfigError
from sgf_pipeline.registry import LoadedPlugins, describe_params, load_plugins

#: The values of ``format=``.
FORMATS = ("text", "json", "markdown")
#: How the configuration reference is regenerated.
REGENERATE = "sgf-plugins format=markdown > docs/configuration.md"


def listing(kind: str | None = None, as_json: bool = False, markdown: bool = False) -> str:
    """Text (or JSON, or the Markdown configuration reference) listing of every registered variant."""
    loaded = load_plugins()
    registry = loaded.registry
    if kind and kind not in registry.kinds():
        known = ", ".join(registry.kinds())
        raise ConfigError(f"kind={kind}: no plugin registers stages of that kind; registered: {known}")
    kinds = [kind] if kind else registry.kinds()
    entries: list[dict[str, Any]] = []
    for k in kinds:
        for v in registry.variants(k):
            entries.append(
                {
                    "kind": v.kind,
                    "name": v.name,
                    "class": f"{v.cls.__module__}.{v.cls.__qualname__}",
                    "plugin": v.plugin,
                    "distribution": v.distribution,
                    "doc": (v.cls.__doc__ or "").strip().splitlines()[0] if v.cls.__doc__ else "",
                    "inputs": {s.parameter: s.describe() for s in v.signature.inputs},
                    "output": v.cls.output,
                    "params": [
                        {"name": n, "type": t, "default": d, "description": desc}
                        for n, t, d, desc in describe_params(v.params_model)
                    ],
                }
            )
    if as_json:
        return json.dumps(entries, indent=2, default=str)
    if markdown:
        return render_markdown(entries, loaded, whole=kind is None)
    lines = []
    current = None
    for e in entries:
        if e["kind"] != current:
            current = e["kind"]
            lines.append(f"\n[{current}]")
        source = e["plugin"] + (f" ({e['distribution']})" if e["distribution"] else "")
        lines.append(f"  {e['kind']}={e['name']}  -> {e['output']}  from {source}")
        if e["doc"]:
            lines.append(f"      {e['doc']}")
        if e["inputs"]:
            lines.append("      inputs: " + ", ".join(f"{k}: {t}" for k, t in e["inputs"].items()))
        for p in e["params"]:
            desc = f"  # {p['description']}" if p["description"] else ""
            lines.append(f"      {p['name']}: {p['type']} = {p['default']!r}{desc}")
    plugins = sorted(name for name, _ in loaded.manager.list_name_plugin() if not name.startswith("sgf."))
    lines.insert(0, "plugins loaded: " + (", ".join(plugins) or "none"))
    return "\n".join(lines).rstrip() + "\n"


def _cell(text: str) -> str:
    """Text for a Markdown table cell: pipes escaped, on one line."""
    return " ".join(text.replace("|", "\\|").split())


def _value(value: Any) -> str:
    """A default as a config file spells it (``null``, ``true``, ``[]``) in code style; without one, ``required``."""
    return "required" if value is PydanticUndefined else "`" + _cell(json.dumps(value, default=str)) + "`"


def _param_table(rows: list[dict[str, Any]], prefix: str) -> list[str]:
    if not rows:
        return ["No parameters.", ""]
    lines = ["| key | type | default | description |", "|---|---|---|---|"]
    for p in rows:
        lines.append(
            f"| `{prefix}{p['name']}` | `{_cell(p['type'])}` | {_value(p['default'])} | {_cell(p['description'])} |"
        )
    return [*lines, ""]


def _options(model: type[BaseModel]) -> list[dict[str, Any]]:
    return [{"name": n, "type": t, "default": d, "description": desc} for n, t, d, desc in describe_params(model)]


def _presets(kind: str, entries: list[dict[str, Any]]) -> list[str]:
    """The files of ``conf/<kind>/`` that are no variant's own: a variant with other settings (``enhance=auto``)."""
    variants = {e["name"] for e in entries if e["kind"] == kind}
    lines = []
    for path in sorted((config_dir() / kind).glob("*.yaml")):
        node = yaml.safe_load(path.read_text())
        if path.stem in variants or not isinstance(node, dict):
            continue
        variant = next((d for d in node.get("defaults", []) if isinstance(d, str) and d != "_self_"), None)
        lines.append(f"- `{kind}={path.stem}`: `{kind}={variant}` with the settings of `conf/{kind}/{path.name}`")
    return [*lines, ""] if lines else []


def render_markdown(entries: list[dict[str, Any]], loaded: LoadedPlugins, whole: bool = True) -> str:
    """The configuration reference in Markdown: runner options, each stage kind and variant, observer nodes."""
    lines = [
        "# Configuration reference",
        "",
        "Every key a run's configuration takes, with its type, default and meaning. A stage kind is a config",
        "group: `sgf-run <kind>=<variant>` chooses a variant and `sgf-run <kind>.<key>=<value>` sets one of",
        "its parameters; a parameter group's keys take dots (`<kind>.<group>.<key>=<value>`). Each default is",
        "written once, in the variant's Params; `conf/<kind>/` holds only presets, a variant with other settings.",
        "",
        f"This file is generated from the installed plugins: `{REGENERATE}`.",
        "",
    ]
    if whole:
        lines += ["## Runner", "", "### `run`", "", *_param_table(_options(RunOptions), "run.")]
        lines += ["### `plugins`", "", *_param_table(_options(PluginOptions), "plugins.")]
    current = None
    for e in entries:
        if e["kind"] != current:
            current = e["kind"]
            variants = ", ".join(f"`{x['name']}`" for x in entries if x["kind"] == current)
            lines += [f"## `{current}`", "", f"Variants: {variants}.", "", *_presets(current, entries)]
        lines += [f"### `{e['kind']}={e['name']}`", ""]
        if e["doc"]:
            lines += [e["doc"], ""]
        inputs = ", ".join(f"`{k}` ({_cell(t)})" for k, t in e["inputs"].items()) or "none"
        lines += [f"Inputs: {inputs}. Output: `{e['output']}`. From plugin `{e['plugin']}`.", ""]
        lines += _param_table(e["params"], f"{e['kind']}.")
    if whole and loaded.observer_options:
        lines += ["## Observers", "", "Config nodes that observer plugins read beside the stage nodes.", ""]
        for name, model in sorted(loaded.observer_options.items()):
            doc = (model.__doc__ or "").strip().splitlines()
            lines += [f"### `{name}`", "", *([doc[0], ""] if doc else []), *_param_table(_options(model), f"{name}.")]
    return "\n".join(lines).rstrip() + "\n"


@hydra.main(config_path=str(config_dir()), config_name="sgf_plugins", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Print the registered plugins."""
    fmt = cfg.get("format")
    if fmt not in FORMATS:
        raise ConfigError(f"format={fmt}: choose one of {', '.join(FORMATS)}")
    print(listing(cfg.get("kind"), as_json=fmt == "json", markdown=fmt == "markdown"), end="")


#: The ``sgf-plugins`` console script.
main = console(app)

if __name__ == "__main__":
    main()
