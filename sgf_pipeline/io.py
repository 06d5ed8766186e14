"""File helpers: atomic writes (a reader sees the old file or the whole new one) and guarded reads of text and YAML."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import re
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sgf_pipeline.errors import DataError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    # The name is chosen before the file exists, so an interrupt at any point (even between creating
    # the file and learning its name) leaves nothing behind: the finally clause knows what to remove.
    tmp_path = target.parent / f".{target.name}.{os.getpid()}.{secrets.token_hex(6)}.part"
    ours = True
    try:
        try:
            fd = os.open(tmp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies
        except FileExistsError:  # pragma: no cover - a clash of 48 random bits: another writer's file
            ours = False
            raise
        os.close(fd)
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, target)
        _fsync_dir(target.parent)
    finally:
        if ours and tmp_path.exists():
            tmp_path.unlink()


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (a robot may lose power right after a run)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover - directories that cannot be opened (some network file systems)
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - file systems without directory fsync
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write bytes atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write text (UTF-8) atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def atomic_write_json(path: str | os.PathLike[str], data: Any) -> None:
    """Write JSON atomically; numpy values become plain numbers, NaN and infinities become null."""
    atomic_write_text(path, json.dumps(_jsonable(data), indent=2, sort_keys=False) + "\n")


def read_text(path: str | os.PathLike[str], what: str = "file") -> str:
    """A UTF-8 text file's content, carriage returns kept; a missing, unreadable or binary file gives a DataError."""
    p = Path(path)
    try:
        return p.read_bytes().decode("utf-8")  # no newline translation: a line ends at "\n" only, as in grep -n
    except FileNotFoundError:
        raise DataError(f"{what} not found: {p}") from None
    except UnicodeDecodeError as exc:
        line = p.read_bytes()[: exc.start].count(b"\n") + 1
        raise DataError(f"{p}:{line}: not a text file (byte {exc.start} is not UTF-8); is it the right file?") from None
    except OSError as exc:
        raise DataError(f"{p}: cannot be read: {exc.strerror or exc}") from None


#: OpenCV's FileStorage header (``%YAML:1.0``, which YAML parsers refuse as a directive).
_OPENCV_HEADER = re.compile(r"\ufeff?%YAML:\d+\.\d+[ \t]*\r?")


@functools.cache
def _opencv_loader() -> Any:
    """``yaml.safe_load``'s loader, plus OpenCV's ``!!opencv-matrix`` tag read as a plain mapping."""
    import yaml

    class OpenCvLoader(yaml.SafeLoader):
        """Safe loading of an OpenCV FileStorage YAML file."""

    def matrix(loader: yaml.SafeLoader, node: yaml.Node) -> Any:
        if not isinstance(node, yaml.MappingNode):
            raise yaml.constructor.ConstructorError(None, None, "an opencv-matrix must be a mapping", node.start_mark)
        return loader.construct_mapping(node, deep=True)

    OpenCvLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    return OpenCvLoader


def read_yaml(path: str | os.PathLike[str], what: str = "YAML file") -> Any:
    """A YAML file parsed with ``yaml.safe_load`` (no Python tags); any problem gives a :class:`DataError`.

    A file written by OpenCV (EuRoC's ``sensor.yaml``) is read too: its ``%YAML:1.0`` first line
    and its ``!!opencv-matrix`` tags (mappings of ``rows``, ``cols``, ``dt``, ``data``).
    """
    import yaml

    p = Path(path)
    text = read_text(p, what)
    first, _, rest = text.partition("\n")
    opencv = _OPENCV_HEADER.fullmatch(first) is not None
    try:
        if opencv:
            loader = _opencv_loader()("#" + first.lstrip("\ufeff") + "\n" + rest)  # the header as a comment
            try:
                return loader.get_single_data()
            finally:
                loader.dispose()
        return yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        where = f":{exc.problem_mark.line + 1}" if exc.problem_mark is not None else ""
        detail = ", ".join(str(part) for part in (exc.context, exc.problem) if part) or type(exc).__name__
        raise DataError(f"{p}{where}: not valid YAML: {' '.join(detail.split())}") from None
    except yaml.YAMLError as exc:
        raise DataError(f"{p}: not valid YAML: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise DataError(f"{p}: not valid YAML: nested too deeply") from None


def describe_dir(path: Path, limit: int = 15) -> str:
    """``it holds: a, b/, c`` for error messages about a missing file in ``path``."""
    if not path.is_dir():
        parent = path.parent
        while not parent.is_dir() and parent != parent.parent:
            parent = parent.parent
        return f"{path} does not exist ({parent} holds: {_listing(parent, limit)})"
    return f"{path} holds: {_listing(path, limit)}"


def _listing(path: Path, limit: int) -> str:
    try:
        entries = sorted(path.iterdir())
    except OSError:
        return "(unreadable)"
    if not entries:
        return "nothing (empty folder)"
    names = [e.name + ("/" if e.is_dir() else "") for e in entries[:limit]]
    more = f" and {len(entries) - limit} more" if len(entries) > limit else ""
    return ", ".join(names) + more
