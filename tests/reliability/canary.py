"""A module no configuration may ever import: importing it (or calling ``fire``) leaves a mark."""

from __future__ import annotations

import os

IMPORTED = True
os.environ["SGF_CANARY_IMPORTED"] = "1"


def fire(*args: object, **kwargs: object) -> None:
    """What a `_target_` would call."""
    os.environ["SGF_CANARY_FIRED"] = "1"
