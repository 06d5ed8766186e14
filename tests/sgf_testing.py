"""Helpers shared by the test modules (imported by name; conftest.py holds only fixtures)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_cli(
    script: str, *args: str, env: dict[str, str] | None = None, cwd: Path | None = None, timeout: float = 600
) -> subprocess.CompletedProcess[str]:
    """Run a console script of this environment and capture its output."""
    import sys

    exe = Path(sys.executable).parent / script
    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.run([str(exe), *args], capture_output=True, text=True, env=full_env, cwd=cwd, timeout=timeout)


def conf_node(option: str) -> dict:
    """The node Hydra composes for ``<group>/<option>`` (``detector/hu_window``) in the default run, as plain data."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from sgf_pipeline.config import config_dir

    group, name = option.removesuffix(".yaml").split("/")
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        node = OmegaConf.to_container(compose("config", overrides=[f"{group}={name}"])[group], resolve=True)
    assert isinstance(node, dict)
    return node
