"""The stage cache's folder: entries written whole, read back frame by frame, bounded in size."""

from __future__ import annotations

import io
import json
import logging
import os
import queue
import shutil
import threading
import time
import uuid
import zipfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zstandard

from sgf_pipeline.cache.codec import NotCacheableError, decode, encode
from sgf_pipeline.cache.keys import file_hash
from sgf_pipeline.config import RunOptions
from sgf_pipeline.errors import CacheError, DataError

log = logging.getLogger("sgf_pipeline")

#: Environment variable: the folder of sgf-pipeline's caches (:func:`caches_root`).
CACHE_ENV = "SGF_PIPELINE_CACHE"
#: Environment variable: ``off`` turns the stage cache off for every run (a test suite, a shared machine).
STAGE_CACHE_ENV = "SGF_PIPELINE_STAGE_CACHE"
_OFF = ("off", "0", "false", "no")
_MANIFEST = "manifest.json"
_RECORDS = "records.jsonl"
_ARRAYS = "arrays.zip"
_EFFECTS = "effects.json"


def cache_dir(options: RunOptions) -> Path | None:
    """The stage cache's folder for a run, or ``None`` when the cache is off.

    ``run.cache=false`` or ``$SGF_PIPELINE_STAGE_CACHE=off`` turns it off; ``run.cache_dir`` names the
    folder; else it is ``stages/`` in :func:`caches_root`.
    """
    if not options.cache or os.environ.get(STAGE_CACHE_ENV, "").strip().lower() in _OFF:
        return None
    if options.cache_dir:
        return Path(options.cache_dir).expanduser()
    return default_cache_dir()


def caches_root() -> Path:
    """Where sgf-pipeline keeps its caches: ``$SGF_PIPELINE_CACHE``, else ``$XDG_CACHE_HOME/sgf_pipeline``.

    (``~/.cache/sgf_pipeline`` when ``XDG_CACHE_HOME`` is unset.) The stage cache's entries are in
    ``stages/``, the saliency networks' ONNX exports in ``onnx/``.
    """
    env = os.environ.get(CACHE_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(xdg) if xdg else Path.home() / ".cache") / "sgf_pipeline"


def default_cache_dir() -> Path:
    """The stage cache's folder when ``run.cache_dir`` is unset."""
    return caches_root() / "stages"


class EntryWriter:
    """An entry being filled during a run, in a temporary folder until :meth:`commit`."""

    def __init__(self, root: Path, kind: str, key: str, components: Mapping[str, Any]) -> None:
        self.final = root / kind / key
        self.tmp = root / kind / f".tmp-{key}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.tmp.mkdir(parents=True)
        self.kind = kind
        self.key = key
        self.components = dict(components)
        self.effects: dict[str, Any] = {}
        self.frames = 0
        self._arrays = _ArrayWriter(self.tmp / _ARRAYS)
        self._records = (self.tmp / _RECORDS).open("w", encoding="utf-8")
        self._count = 0
        self.broken: str | None = None

    def _sink(self, array: np.ndarray) -> str:
        name = f"{self._count}.npy.zst"
        self._count += 1
        self._arrays.put(name, array)
        return name

    def add(self, frame_index: int, value: Any, inputs: Mapping[int, str] | None = None) -> None:
        """Write one frame's output (``inputs``: ids of the stage's input values, by input name)."""
        if self.broken:
            return
        try:
            data = encode(value, self._sink, inputs)
        except NotCacheableError as exc:
            self.broken = str(exc)
            return
        self._records.write(json.dumps({"i": frame_index, "v": data}) + "\n")
        self.frames += 1

    def record_effects(self, phase: str, changes: Mapping[str, Any]) -> None:
        """Keep what the stage changed in the run context at ``begin`` or ``finalize``."""
        if self.broken:
            return
        try:
            self.effects[phase] = encode(dict(changes), self._sink)
        except NotCacheableError as exc:
            self.broken = f"its {phase} left {exc}"

    def commit(self, extra: Mapping[str, Any] | None = None) -> Path | None:
        """Close the files, write the manifest and move the entry into place; ``None`` when it was not kept."""
        self._close()
        self.broken = self.broken or self._arrays.error
        if self.broken:
            log.warning("stage cache: %s=%s is not cached: %s", self.kind, self.components.get("stage"), self.broken)
            self.abort()
            return None
        (self.tmp / _EFFECTS).write_text(json.dumps(self.effects), encoding="utf-8")
        files = {name: file_hash(self.tmp / name) for name in (_RECORDS, _ARRAYS, _EFFECTS)}
        size = sum((self.tmp / name).stat().st_size for name in files)
        manifest = {
            "key": self.key,
            "kind": self.kind,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime()),
            "frames": self.frames,
            "bytes": size,
            "sha256": files,
            "components": self.components,
            **dict(extra or {}),
        }
        (self.tmp / _MANIFEST).write_text(json.dumps(manifest, indent=1, default=str), encoding="utf-8")
        try:
            os.rename(self.tmp, self.final)
        except OSError:  # another job filled the same key first: keep its entry
            self.abort()
            return self.final if (self.final / _MANIFEST).is_file() else None
        return self.final

    def abort(self) -> None:
        """Forget the entry (a run that did not finish)."""
        self._close()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def _close(self) -> None:
        if not self._records.closed:
            self._records.close()
        self._arrays.close()


class _ArrayWriter:
    """Arrays written into a zip by a thread of its own, so that a run's next stages go on meanwhile.

    Each array is an ``.npy`` member compressed with zstd (level 1: a BEV in about half a millisecond),
    copied when queued (a later stage may change it in place); the queue is bounded.
    """

    def __init__(self, path: Path) -> None:
        self._zip = zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED)
        self._compressor = zstandard.ZstdCompressor(level=1)
        self._queue: queue.Queue[tuple[str, np.ndarray] | None] = queue.Queue(maxsize=64)
        self.error: str | None = None
        self._thread = threading.Thread(target=self._work, name="sgf-cache-writer", daemon=True)
        self._thread.start()

    def put(self, name: str, array: np.ndarray) -> None:
        """Queue an array under ``name``."""
        self._queue.put((name, np.array(array, copy=True, order="C")))

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            if self.error:
                continue
            name, array = item
            try:
                buffer = io.BytesIO()
                np.lib.format.write_array(buffer, array, allow_pickle=False)
                self._zip.writestr(name, self._compressor.compress(buffer.getbuffer()))
            except Exception as exc:  # a full disk: the entry is not kept, the run goes on
                self.error = f"its arrays could not be written ({exc})"

    def close(self) -> None:
        """Write what is queued and close the zip (a no-op when closed)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        if self._zip.fp is not None:
            self._zip.close()


class Entry:
    """A whole entry read back frame by frame."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.manifest: dict[str, Any] = json.loads((folder / _MANIFEST).read_text(encoding="utf-8"))
        for name, digest in self.manifest["sha256"].items():
            if file_hash(folder / name) != digest:
                raise DataError(f"{name} does not match its checksum")
        self.effects: dict[str, Any] = json.loads((folder / _EFFECTS).read_text(encoding="utf-8"))
        self._zip = zipfile.ZipFile(folder / _ARRAYS)
        self._decompressor = zstandard.ZstdDecompressor()
        self._records = (folder / _RECORDS).open(encoding="utf-8")
        os.utime(folder / _MANIFEST)  # used now: the last to be evicted

    def _source(self, name: str) -> np.ndarray:
        raw = self._decompressor.decompress(self._zip.read(name))
        return np.lib.format.read_array(io.BytesIO(raw), allow_pickle=False)

    def next(self, frame_index: int, inputs: Mapping[str, Any] | None = None) -> Any:
        """The output of the next frame, which must be ``frame_index``."""
        line = self._records.readline()
        if not line:
            raise CacheError(f"the cached {self.folder} ends before frame {frame_index}; clear it with sgf-cache")
        record = json.loads(line)
        if record["i"] != frame_index:
            raise CacheError(
                f"the cached {self.folder} holds frame {record['i']} where the run has frame {frame_index}: the stage "
                "is not a pure function of its key; clear the entry with `sgf-cache action=clear` and set "
                "`cacheable = False` on the stage"
            )
        return decode(record["v"], self._source, inputs)

    def records(self) -> Iterator[Any]:
        """Every record's value in order (the dataset's keyframes)."""
        for line in self._records:
            yield json.loads(line)["v"]

    def changes(self, phase: str, inputs: Mapping[str, Any] | None = None) -> dict[str, Any] | None:
        """What the stage put into the run context at ``begin`` or ``finalize``."""
        data = self.effects.get(phase)
        return None if data is None else decode(data, self._source, inputs)

    def decode(self, data: Any, inputs: Mapping[str, Any] | None = None) -> Any:
        """A value of a record read with :meth:`records`."""
        return decode(data, self._source, inputs)

    def close(self) -> None:
        """Close the entry's files."""
        self._records.close()
        self._zip.close()


@dataclass(frozen=True)
class EntryInfo:
    """One entry as ``sgf-cache`` lists it."""

    kind: str
    key: str
    stage: str
    frames: int
    bytes: int
    created: str
    last_used: float
    folder: Path


class StageCache:
    """The cache's folder: entries by stage kind and key, bounded in size."""

    def __init__(self, root: Path, max_bytes: int) -> None:
        self.root = Path(root)
        self.max_bytes = max_bytes
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CacheError(
                f"the stage cache's folder {self.root} cannot be made ({exc}); set run.cache_dir to a writable "
                f"folder, or turn the cache off with run.cache=false"
            ) from None

    def lookup(self, kind: str, key: str) -> Entry | None:
        """The whole entry for ``key``, or ``None``; a damaged entry is removed with a warning."""
        folder = self.root / kind / key
        if not (folder / _MANIFEST).is_file():
            return None
        try:
            return Entry(folder)
        except Exception as exc:
            log.warning("stage cache: the entry %s is damaged (%s); it is recomputed", folder, exc)
            self._remove(folder)
            return None

    def contains(self, kind: str, key: str) -> bool:
        """Whether a whole entry for ``key`` is in the cache (not checked)."""
        return (self.root / kind / key / _MANIFEST).is_file()

    def writer(self, kind: str, key: str, components: Mapping[str, Any]) -> EntryWriter:
        """A new entry to fill."""
        return EntryWriter(self.root, kind, key, components)

    def entries(self) -> list[EntryInfo]:
        """Every whole entry, least recently used first."""
        found = []
        for manifest in self.root.glob(f"*/*/{_MANIFEST}"):
            try:
                data = json.loads(manifest.read_text(encoding="utf-8"))
                used = manifest.stat().st_mtime
            except (OSError, ValueError):
                continue
            found.append(
                EntryInfo(
                    data.get("kind", manifest.parent.parent.name),
                    manifest.parent.name,
                    str(data.get("components", {}).get("stage", "?")),
                    int(data.get("frames", 0)),
                    int(data.get("bytes", 0)),
                    str(data.get("created", "")),
                    used,
                    manifest.parent,
                )
            )
        return sorted(found, key=lambda e: e.last_used)

    def evict(self) -> list[EntryInfo]:
        """Remove the least recently used entries until the cache holds at most ``max_bytes``; the removed."""
        entries = self.entries()
        total = sum(e.bytes for e in entries)
        removed = []
        for entry in entries:
            if total <= self.max_bytes:
                break
            self._remove(entry.folder)
            total -= entry.bytes
            removed.append(entry)
        self._remove_stale_temporaries()
        return removed

    def clear(self, kind: str | None = None) -> list[EntryInfo]:
        """Remove every entry (of one stage kind); the removed."""
        removed = [e for e in self.entries() if kind is None or e.kind == kind]
        for entry in removed:
            self._remove(entry.folder)
        return removed

    def _remove(self, folder: Path) -> None:
        trash = folder.parent / f".tmp-removed-{folder.name}-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(folder, trash)  # readers never see half an entry
        except OSError:
            return
        shutil.rmtree(trash, ignore_errors=True)

    def _remove_stale_temporaries(self, age_s: float = 86400.0) -> None:
        now = time.time()
        for tmp in self.root.glob("*/.tmp-*"):
            try:
                if now - tmp.stat().st_mtime > age_s:
                    shutil.rmtree(tmp, ignore_errors=True)
            except OSError:
                continue
