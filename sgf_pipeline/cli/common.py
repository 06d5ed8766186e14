"""Shared plumbing of the console scripts: clear errors instead of tracebacks."""

from __future__ import annotations

import functools
import logging
import os
import sys
from collections.abc import Callable
from typing import Any, TypeVar

from sgf_pipeline.errors import SgfError

F = TypeVar("F", bound=Callable[..., Any])
log = logging.getLogger("sgf_pipeline")


def friendly_errors(func: F) -> F:
    """Turn the project's own errors into one clear message and exit status 2 (no traceback).

    Set ``SGF_PIPELINE_TRACEBACK=1`` to see the full traceback.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except SgfError as exc:
            if os.environ.get("SGF_PIPELINE_TRACEBACK"):
                raise
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)

    return wrapper  # type: ignore[return-value]
