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

A script's main paths may also come first, without their keys (``sgf-eval REF EST``):
:func:`positional_overrides` turns them into ``key=value`` overrides before Hydra reads the
command line. A closed standard output (``sgf-bag-info BAG | head -1``) ends the script quietly.
Hydra's ``--experimental-rerun`` option is refused: it loads a pickle, and no pickle is ever loaded.
"""

from __future__ import annotations

import difflib
import functools
import logging
import os
import re
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn, TypeVar

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


def unknown_key(exc: BaseException) -> str | None:
    """Hydra's refusal of an override of a key the config does not have, with the closest known keys.

    Hydra's own advice (``+key=value`` appends the key) only moves the error to the config's
    validation; a misspelt key wants the right spelling. None for any other error.
    """
    cause = exc.__cause__
    if not str(exc).startswith("Could not override") or cause is None:
        return None
    parent, leaf = getattr(cause, "parent_node", None), getattr(cause, "key", None)
    full = getattr(cause, "full_key", "")
    if parent is None or leaf is None or not full or not hasattr(parent, "keys"):
        return None
    known = [str(k) for k in parent if str(k) != "hydra"]
    group = str(full).rsplit(".", 1)[0] if "." in str(full) else ""
    prefix = f"{group}." if group else ""
    close = difflib.get_close_matches(str(leaf), known, n=3, cutoff=0.6)
    guess = f"; did you mean {' or '.join(prefix + c for c in close)}?" if close else ""
    where = f"keys of {group}" if group else "top-level keys"
    return f"{full}: no such key{guess} ({where}: {', '.join(known) or 'none'})"


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

        from sgf_pipeline.config import describe_omegaconf_error

        try:
            return func(*args, **kwargs)
        except BrokenPipeError:  # before Hydra reports the job as failed
            _quiet_closed_pipe()
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


def hydra_value(value: str) -> str:
    """A string as a Hydra override takes it: plain when it is a simple word or path, else quoted.

    Words Hydra would read as another type (``true``, ``null``, ``1.5``) are quoted too.
    """
    try:
        float(value)
        other_type = True
    except ValueError:
        other_type = value.lower() in ("true", "false", "null")
    if re.fullmatch(r"[\w./+\-@%:]+", value) and not other_type:
        return value
    # Hydra's quoted strings: backslashes before a quote or at the end are doubled, then quotes escaped
    escaped = re.sub(r"(\\+)(?='|$)", lambda m: m.group(1) * 2, value).replace("'", "\\'")
    return f"'{escaped}'"


def positional_overrides(args: Sequence[str], keys: Sequence[str], usage: str) -> list[str]:
    """``args`` with the leading ones that are neither ``key=value`` nor a flag given as overrides of ``keys``.

    ``sgf-eval ref.txt est.txt align=sim3`` reads as ``reference=ref.txt estimate=est.txt align=sim3``.
    More leading paths than ``keys``, or a key given both ways, is a :class:`ConfigError` citing ``usage``.
    """
    args = list(args)
    count = 0
    while count < len(args) and "=" not in args[count] and not args[count].startswith("-"):
        count += 1
    if count > len(keys):
        extra = " ".join(args[len(keys) : count])
        raise ConfigError(f"too many paths ({extra!r} left over): {usage}; other options are key=value (see --help)")
    named = {a.split("=", 1)[0].lstrip("+~") for a in args[count:] if "=" in a}
    overrides = []
    for key, value in zip(keys, args[:count], strict=False):
        if key in named:
            raise ConfigError(f"{key} is given twice, as the path {value!r} and as {key}=...; give it once: {usage}")
        overrides.append(f"{key}={hydra_value(value)}")
    return overrides + args[count:]


def _quiet_closed_pipe() -> NoReturn:
    """End the process at once and quietly: a reader of standard output (``| head``) closed it."""
    try:  # further writes (the interpreter's final flush) go nowhere instead of raising again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # pragma: no cover - no file descriptor to replace
        pass
    os._exit(0)


def console(app: Callable[[], Any], positional: Sequence[str] = (), usage: str = "") -> Callable[[], None]:
    """The entry point of a console script around a Hydra app (see the module docstring for exit statuses).

    ``positional`` names the keys of the paths that may come first without their keys, in order.
    """

    @functools.wraps(app)
    def main() -> None:
        try:
            try:
                _main()
            finally:
                sys.stdout.flush()  # here, where a closed pipe is caught, not at the interpreter's exit
        except BrokenPipeError:
            _quiet_closed_pipe()

    def _main() -> None:
        if positional:
            try:
                sys.argv[1:] = positional_overrides(sys.argv[1:], positional, usage)
            except ConfigError as exc:
                print(f"error: {one_paragraph(exc)}", file=sys.stderr)
                sys.exit(EXIT_USAGE)
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
            print(f"error: {unknown_key(exc) or one_paragraph(exc)}", file=sys.stderr)
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
