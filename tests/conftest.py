"""Shared fixtures: the real data folder, isolated homes for evo and ray, and toy stages."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (override with $SGF_SHARED_DATA); under CI=true a missing folder fails."""
    path = Path(os.environ.get("SGF_SHARED_DATA", ROOT.parent / "shared" / "data"))
    if not path.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"the real test data folder {path} is missing (set SGF_SHARED_DATA)")
        pytest.skip(f"real test data folder {path} not found")
    return path


@pytest.fixture(scope="session", autouse=True)
def _onnx_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """One ONNX export cache for the session (the default runtime exports each network once), not the user's.

    The stage cache is off unless a test turns it on: a test's run computes what it asserts on.
    """
    os.environ["SGF_PIPELINE_CACHE"] = str(tmp_path_factory.mktemp("sgf_cache"))
    os.environ["SGF_PIPELINE_STAGE_CACHE"] = "off"


@pytest.fixture(autouse=True)
def _isolated_home(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """evo writes ~/.evo: keep it inside the test's temporary folder (ray's folder is set per test)."""
    home = tmp_path_factory.mktemp("home")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def toy_plugin_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The throwaway third-party plugin of tests/thirdparty_plugin, pip-installed into a temporary folder.

    Put the returned folder on PYTHONPATH of a subprocess to make the plugin visible to it; the
    project and its virtual environment are not changed.
    """
    import importlib.util
    import shutil
    import sys

    work = tmp_path_factory.mktemp("toy_plugin")
    src = work / "src_pkg"
    shutil.copytree(ROOT / "tests" / "thirdparty_plugin", src)
    site = work / "site"
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "install",
        "-q",
        "--no-deps",
        "--disable-pip-version-check",
        "--target",
        str(site),
        str(src),
    ]
    if importlib.util.find_spec("setuptools") is not None:
        cmd.insert(4, "--no-build-isolation")
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return site
