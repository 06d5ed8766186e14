"""Fixtures of the synthetic campus world tests: small worlds built once per session."""

from __future__ import annotations

import pytest
from sgf_plugins.world import CampusWorld, build_world


@pytest.fixture(scope="session")
def delivery() -> CampusWorld:
    """The default preset, full size (its drive and truth are cheap; frames render lazily)."""
    return build_world("campus_delivery", seed=0)


@pytest.fixture(scope="session")
def flat_world() -> CampusWorld:
    """A campus whose ground is the plane z = 0 (for homography checks), without people."""
    return build_world("campus_delivery", seed=3, flat_ground=True, occluders=False, sensor_noise=False)
