"""The directory a run writes into: refused when it holds another run's files, locked while the run writes."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import IO

from sgf_pipeline.errors import ConfigError

log = logging.getLogger("sgf_pipeline")

#: Files of a finished run that the runner writes (plus ``trajectory_*.tum``); cleared before an overwrite.
RUN_FILES = ("metrics.json", "report.md", "trajectory.png", "loops.csv", "config.yaml", "failure.json")
#: The lock a running pipeline holds on its run directory (a second run into it is refused); removed when it ends.
LOCK_FILE = ".sgf-run.lock"
#: What a run that did not finish leaves: its record and the results it had so far (``*.partial.*``).
FAILURE_FILE = "failure.json"
PARTIAL_PATTERN = "*.partial.*"


class RunDirectory:
    """A run's output directory; with ``overwrite``, a finished or interrupted run found there is replaced."""

    def __init__(self, path: Path, overwrite: bool) -> None:
        self.path = path
        self.overwrite = overwrite
        self._lock: IO[str] | None = None
        self.check_earlier_run()

    def interrupted_files(self) -> list[Path]:
        """The record and partial results of a run that failed or was interrupted here (empty when none)."""
        found = sorted(self.path.glob(PARTIAL_PATTERN))
        if (self.path / FAILURE_FILE).exists():
            found.insert(0, self.path / FAILURE_FILE)
        return found

    def check_earlier_run(self) -> None:
        """Refuse a directory that holds a finished or an interrupted run, unless it may be overwritten."""
        if self.overwrite:
            return
        if (self.path / "metrics.json").exists():
            raise ConfigError(
                f"{self.path} already holds a finished run (metrics.json); choose another output "
                "directory (hydra.run.dir=...) or pass run.overwrite=true to replace it"
            )
        kept = self.interrupted_files()
        if kept:
            names = ", ".join(p.name for p in kept[:4]) + (f" and {len(kept) - 4} more" if len(kept) > 4 else "")
            raise ConfigError(
                f"{self.path} holds a run that did not finish ({names}); its files are kept. Choose another output "
                "directory (hydra.run.dir=...), or pass run.overwrite=true to replace them"
            )

    def claim(self) -> None:
        """Lock the run directory for this run, and clear what an earlier run left there when allowed."""
        run_dir = self.path
        run_dir.mkdir(parents=True, exist_ok=True)
        self._lock = _lock_directory(run_dir)
        try:
            self.check_earlier_run()  # again, under the lock: another run may have finished meanwhile
        except ConfigError:
            self.release()
            raise
        if (run_dir / "metrics.json").exists():  # run.overwrite=true: the old run's files go first
            log.warning("run.overwrite=true: replacing the finished run in %s", run_dir)
            stale = [run_dir / n for n in RUN_FILES] + sorted(run_dir.glob("trajectory_*.tum"))
        elif self.interrupted_files():
            log.warning("run.overwrite=true: replacing the record of a run that did not finish in %s", run_dir)
            stale = self.interrupted_files()
        else:
            stale = []
        for path in stale:  # metrics.json first: the directory stops claiming a finished run at once
            path.unlink(missing_ok=True)

    def release(self) -> None:
        """Unlock the directory and remove the lock file (a no-op when it is not locked)."""
        if self._lock is not None:
            try:  # removed while still held: a process that opened it meanwhile sees it gone and retries
                (self.path / LOCK_FILE).unlink(missing_ok=True)
            except OSError as exc:  # pragma: no cover - a read-only directory: the lock is still released
                log.warning("cannot remove %s: %s", self.path / LOCK_FILE, exc)
            self._lock.close()
            self._lock = None


def _lock_directory(run_dir: Path) -> IO[str] | None:
    """An exclusive lock on ``run_dir`` held while this process runs (released when it exits, even killed)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not a POSIX system: no lock
        return None
    path = run_dir / LOCK_FILE
    while True:
        handle = open(path, "a+")  # noqa: SIM115  (held open for the run's duration)
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
        try:
            current = os.stat(path)
        except FileNotFoundError:
            current = None
        if current is not None and current.st_ino == os.fstat(handle.fileno()).st_ino:
            break
        handle.close()  # the run that held it ended and removed it in between: lock the new file
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle
