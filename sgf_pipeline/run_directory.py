"""The directory a run writes into: refused when it holds a finished run, locked while the run writes."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import IO

from sgf_pipeline.errors import ConfigError

log = logging.getLogger("sgf_pipeline")

#: Files of a finished run that the runner writes (plus ``trajectory_*.tum``); cleared before an overwrite.
RUN_FILES = ("metrics.json", "report.md", "trajectory.png", "loops.csv", "config.yaml", "failure.json")
#: The lock a running pipeline holds on its run directory (a second run into it is refused).
LOCK_FILE = ".sgf-run.lock"


class RunDirectory:
    """A run's output directory; with ``overwrite``, a finished run found there is replaced."""

    def __init__(self, path: Path, overwrite: bool) -> None:
        self.path = path
        self.overwrite = overwrite
        self._lock: IO[str] | None = None
        self.check_finished_run()

    def check_finished_run(self) -> None:
        """Refuse a directory that holds a finished run, unless it may be overwritten."""
        if (self.path / "metrics.json").exists() and not self.overwrite:
            raise ConfigError(
                f"{self.path} already holds a finished run (metrics.json); choose another output "
                "directory (hydra.run.dir=...) or pass run.overwrite=true to replace it"
            )

    def claim(self) -> None:
        """Lock the run directory for this run, and clear what an earlier run left there when allowed."""
        run_dir = self.path
        run_dir.mkdir(parents=True, exist_ok=True)
        self._lock = _lock_directory(run_dir)
        try:
            self.check_finished_run()  # again, under the lock: another run may have finished meanwhile
        except ConfigError:
            self.release()
            raise
        if (run_dir / "metrics.json").exists():  # run.overwrite=true: the old run's files go first
            log.warning("run.overwrite=true: replacing the finished run in %s", run_dir)
            stale = [run_dir / n for n in RUN_FILES] + sorted(run_dir.glob("trajectory_*.tum"))
        elif (run_dir / "failure.json").exists():
            log.warning("%s holds the record of a failed run (failure.json); a new run replaces it", run_dir)
            stale = [run_dir / "failure.json", *sorted(run_dir.glob("trajectory_*.partial.tum"))]
            stale += sorted(run_dir.glob("*.partial.safetensors"))
        else:
            stale = []
        for path in stale:  # metrics.json first: the directory stops claiming a finished run at once
            path.unlink(missing_ok=True)

    def release(self) -> None:
        """Unlock the directory (a no-op when it is not locked)."""
        if self._lock is not None:
            self._lock.close()
            self._lock = None


def _lock_directory(run_dir: Path) -> IO[str] | None:
    """An exclusive lock on ``run_dir`` held while this process runs (released when it exits, even killed)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not a POSIX system: no lock
        return None
    handle = open(run_dir / LOCK_FILE, "a+")  # noqa: SIM115  (held open for the run's duration)
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        holder = handle.read().strip() or "?"
        handle.close()
        raise ConfigError(
            f"another run (process {holder}) is writing into {run_dir}; wait for it to end or choose another "
            "output directory (hydra.run.dir=...)"
        ) from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle
