"""Shared fixtures: the real data folder, isolated homes for evo and ray, and toy stages."""

from __future__ import annotations

import os
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


@pytest.fixture(autouse=True)
def _isolated_home(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """evo writes ~/.evo and ray its session files: keep both inside the test's temporary folder."""
    home = tmp_path_factory.mktemp("home")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("RAY_TMPDIR", str(home / "ray"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
