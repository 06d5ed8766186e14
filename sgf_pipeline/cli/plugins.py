"""``sgf-plugins``: list the registered stage kinds, variants, parameters and their packages."""

from __future__ import annotations

import json
from typing import Any

import hydra
from omegaconf import DictConfig

from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir
from sgf_pipeline.errors import ConfigError
from sgf_pipeline.registry import describe_params, load_plugins


def listing(kind: str | None = None, as_json: bool = False) -> str:
    """Text (or JSON) listing of every registered variant."""
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


@hydra.main(config_path=str(config_dir()), config_name="sgf_plugins", version_base="1.3")
@friendly_errors
def app(cfg: DictConfig) -> None:
    """Print the registered plugins."""
    print(listing(cfg.get("kind"), cfg.get("format") == "json"), end="")


#: The ``sgf-plugins`` console script.
main = console(app)

if __name__ == "__main__":
    main()
