"""Shared plumbing of the console scripts: one clear paragraph and exit status 2 instead of a traceback.

Every console script is a Hydra app wrapped twice:

* :func:`friendly_errors` around the task function turns an OmegaConf error met while reading the
  config into a :class:`~sgf_pipeline.errors.ConfigError`, and in a sweep logs the failed job (its
  number, overrides and directory) before the sweep goes on to the next job;
* :func:`console` around the whole app (the entry point) prints ``error: <one paragraph>`` and exits
  with :data:`EXIT_USAGE` for anything a user can act on: the project's errors, Hydra's (an unknown
  key or config group, an override that does not parse) and OmegaConf's. SIGINT and SIGTERM exit
  with 130 and 143 after the run has recorded itself. Any other exception is a bug and keeps its
  traceback. ``SGF_PIPELINE_TRACEBACK=1`` (or ``HYDRA_FULL_ERROR=1``) shows every traceback.

Hydra's ``--experimental-rerun`` option is refused: it loads a pickle, and no pickle is ever loaded.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import sys
from collections.abc import Callable
from typing import Any, TypeVar

from sgf_pipeline.errors import ConfigError, SgfError

F = TypeVar("F", bound=Callable[..., Any])
log = logging.getLogger("sgf_pipeline")

#: Exit status of a usage, configuration or data error (the message says what to fix).
EXIT_USAGE = 2
#: Exit status after SIGINT (Ctrl-C) and after SIGTERM: 128 + the signal number, as shells report it.
EXIT_INTERRUPTED = 128 + signal.SIGINT
EXIT_TERMINATED = 128 + signal.SIGTERM
TRACEBACK_ENV = "SGF_PIPELINE_TRACEBACK"
#: Hydra options that are refused: ``--experimental-rerun`` unpickles a file.
REFUSED_OPTIONS = ("--experimental-rerun",)


class Terminated(KeyboardInterrupt):
    """SIGTERM, turned into an interrupt so that the run records itself and leaves no half file."""


def raise_terminated(signum: int, frame: Any) -> None:
    """Signal handler: raise :class:`Terminated` in the main thread."""
    raise Terminated(f"signal {signum}")


def one_paragraph(exc: BaseException) -> str:
    """An exception's message as one paragraph: no blank lines, no config search path, no traceback hint."""
    text = str(exc)
    cause = exc.__cause__
    if cause is not None and type(cause).__module__.startswith("omegaconf"):
        text += "\n" + str(cause)
    lines: list[str] = []
    skipping = False
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("Config search path"):
            skipping = True  # Hydra's list of providers follows, one per line
            continue
        if skipping and line.startswith("provider="):
            continue
        skipping = False
        if line and not line.startswith("Set the environment variable HYDRA_FULL_ERROR"):
            lines.append(line)
    return "\n  ".join(lines) or type(exc).__name__


def _failed_job() -> str | None:
    """``job N (overrides) in DIR`` when running inside a Hydra multirun, else None."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if not HydraConfig.initialized():
            return None
        hydra_cfg = HydraConfig.get()
        if hydra_cfg.mode != RunMode.MULTIRUN:
            return None
        overrides = " ".join(hydra_cfg.overrides.task) or "no overrides"
        return f"job {hydra_cfg.job.num} ({overrides}) in {hydra_cfg.runtime.output_dir}"
    except Exception:  # pragma: no cover - only a label for the log line
        return None


def friendly_errors(func: F) -> F:
    """Task-level wrapper: a project or OmegaConf error ends a single run with one paragraph and status 2.

    Inside a sweep the error is logged with the job's number, overrides and directory and raised
    again, so that Hydra goes on with the other jobs and reports the failure at the end.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from omegaconf.errors import OmegaConfBaseException

        from sgf_pipeline.runner import describe_omegaconf_error

        try:
            return func(*args, **kwargs)
        except (SgfError, OmegaConfBaseException) as exc:
            error = exc if isinstance(exc, SgfError) else ConfigError(describe_omegaconf_error(exc))
            job = _failed_job()
            if job is None and not _full_tracebacks():
                print(f"error: {one_paragraph(error)}", file=sys.stderr)
                sys.exit(EXIT_USAGE)
            if job is not None:
                log.error("%s failed: %s", job, one_paragraph(error))
            if error is exc:
                raise
            raise error from None

    return wrapper  # type: ignore[return-value]


def _full_tracebacks() -> bool:
    """Whether the user asked for tracebacks (``SGF_PIPELINE_TRACEBACK=1``)."""
    return bool(os.environ.get(TRACEBACK_ENV))


def console(app: Callable[[], Any]) -> Callable[[], None]:
    """The entry point of a console script around a Hydra app (see the module docstring for exit statuses)."""

    @functools.wraps(app)
    def main() -> None:
        refused = [a for a in sys.argv[1:] if a.split("=", 1)[0] in REFUSED_OPTIONS]
        if refused:
            print(
                f"error: {refused[0].split('=', 1)[0]} is not supported: it loads a pickle file, and sgf-pipeline "
                "never loads one. Rerun with the overrides saved in the run's .hydra/overrides.yaml instead",
                file=sys.stderr,
            )
            sys.exit(EXIT_USAGE)
        if _full_tracebacks() or os.environ.get("HYDRA_FULL_ERROR") == "1":
            os.environ[TRACEBACK_ENV] = "1"  # the task wrapper re-raises too
            app()
            return
        from hydra.errors import HydraException
        from omegaconf.errors import OmegaConfBaseException

        os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra re-raises; the errors are printed here, once
        try:
            app()
        except (SgfError, HydraException, OmegaConfBaseException) as exc:
            print(f"error: {one_paragraph(exc)}", file=sys.stderr)
            sys.exit(EXIT_USAGE)
        except KeyboardInterrupt as exc:
            name, status = ("SIGTERM", EXIT_TERMINATED) if isinstance(exc, Terminated) else ("SIGINT", EXIT_INTERRUPTED)
            print(
                f"interrupted ({name}): a run directory being written keeps failure.json, its "
                "trajectory_*.partial.tum files and the SGF map so far; no file is left half-written",
                file=sys.stderr,
            )
            sys.exit(status)
        finally:
            os.environ.pop("HYDRA_FULL_ERROR", None)

    return main
