"""The stage cache's keys: everything that can change a stage's outputs, and which stages are cacheable."""

from __future__ import annotations

import ast
import functools
import hashlib
import json
import platform
import sys
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

from sgf_pipeline.config import RunOptions
from sgf_pipeline.run_info import StageNode
from sgf_pipeline.stage import Stage

#: Version of the entry format; part of every key.
FORMAT = 2
#: Distributions whose versions are part of every key (their numerics make the outputs).
LIBRARIES = ("numpy", "torch", "opencv-python-headless", "kornia", "scipy", "onnxruntime", "pydantic")
#: Files at most this large are identified by their content's hash, larger ones by size and time.
HASHED_FILE_BYTES = 256 * 1024 * 1024


def digest(data: Any) -> str:
    """The key of a key's components: a hash of their JSON."""
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:32]


def file_hash(path: Path) -> str:
    """SHA-256 of a file's content."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def path_identity(path: Path) -> str:
    """A file's content hash (size and time when large); a folder's listing of names, sizes and times."""
    if path.is_file():
        stat = path.stat()
        if stat.st_size <= HASHED_FILE_BYTES:
            return file_hash(path)
        return f"{stat.st_size}:{stat.st_mtime_ns}"
    rows = []
    for item in sorted(path.rglob("*")):
        if item.is_file():
            stat = item.stat()
            rows.append(f"{item.relative_to(path)}:{stat.st_size}:{stat.st_mtime_ns}")
    return hashlib.sha256("\n".join(rows).encode()).hexdigest()


def param_paths(params: Any, prefix: str = "") -> dict[str, str]:
    """Identity of every parameter that names an existing file or folder (a dataset's recording, a weights file)."""
    found: dict[str, str] = {}
    if isinstance(params, Mapping):
        for key, value in params.items():
            found.update(param_paths(value, f"{prefix}{key}."))
    elif isinstance(params, (list, tuple)):
        for i, value in enumerate(params):
            found.update(param_paths(value, f"{prefix}{i}."))
    elif isinstance(params, str) and params and len(params) < 4096:
        try:
            path = Path(params).expanduser()
            if path.exists():
                found[prefix.rstrip(".")] = path_identity(path)
        except OSError:
            pass
    return found


@functools.cache
def library_versions() -> dict[str, str | None]:
    """Versions of the numeric libraries, Python and the processor architecture."""
    versions: dict[str, str | None] = {"python": platform.python_version(), "machine": platform.machine()}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def _module_path(name: str) -> Path | None:
    """The source file of a module of an imported top-level package, found without importing it."""
    top, *rest = name.split(".")
    package = sys.modules.get(top)
    origin = getattr(package, "__file__", None)
    if not origin:
        return None
    base = Path(origin).parent.joinpath(*rest)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imported_names(path: Path, module: str) -> set[str]:
    """Modules a source file imports anywhere in it, absolute and relative (``from M import x`` as M.x too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            names.add(target)
            names.update(f"{target}.{alias.name}" for alias in node.names)
    return names


@functools.cache
def code_fingerprint(module: str) -> str:
    """Hash of the source of ``module`` and of every module of its top-level package that it imports, transitively."""
    top = module.split(".")[0]
    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen or name.split(".")[0] != top:
            continue
        path = _module_path(name)
        if path is None:
            continue
        seen[name] = path
        todo.extend(_imported_names(path, name))
    h = hashlib.sha256()
    for name in sorted(seen):
        h.update(name.encode() + b"\0" + seen[name].read_bytes() + b"\0")
    return h.hexdigest()[:32]


@functools.cache
def core_fingerprint() -> str:
    """Hash of every source file of the core (``sgf_pipeline``)."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:32]


def _params_of(node: StageNode) -> dict[str, Any]:
    params = node.stage.params
    return params.model_dump(mode="json") if hasattr(params, "model_dump") else {}


def _node_components(node: StageNode) -> dict[str, Any]:
    """What any stage's outputs depend on: its variant, parameters and the files they name, identity, code."""
    stage = node.stage
    params = _params_of(node)
    return {
        "format": FORMAT,
        "stage": node.label,
        "params": params,
        "paths": param_paths(params),
        "identity": stage.cache_identity(),
        "code": code_fingerprint(type(stage).__module__),
        "core": core_fingerprint(),
        "libraries": library_versions(),
    }


def dataset_components(node: StageNode, options: RunOptions, read_ahead: float) -> dict[str, Any]:
    """What the dataset's keyframes depend on: the dataset, its files and code, the runner's keyframe options."""
    runner = {
        "keyframe_distance": options.keyframe_distance,
        "keyframe_angle": options.keyframe_angle,
        "max_frames": options.max_frames,
        "read_ahead": read_ahead,
        "read_ahead_seconds": options.read_ahead_seconds if read_ahead > 0.0 else None,
    }
    return {**_node_components(node), "runner": runner}


def stage_components(node: StageNode, input_keys: Mapping[str, str | None]) -> dict[str, Any]:
    """What a cacheable stage's outputs depend on: its variant, parameters, code, identity and inputs' keys."""
    return {**_node_components(node), "inputs": dict(input_keys)}


def cacheable_nodes(order: list[StageNode]) -> list[StageNode]:
    """The stages after the dataset whose outputs depend only on the dataset and the stages before them."""
    produced = {n.output for n in order}
    pure = {order[0].output}
    nodes: list[StageNode] = []
    for node in order[1:]:
        stage = node.stage
        if not isinstance(stage, Stage) or not type(stage).cacheable:
            continue
        hands_on = any(getattr(type(stage), m) is not getattr(Stage, m) for m in ("settle", "conclude", "partial"))
        if hands_on or any(spec.previous for spec, _ in node.inputs):
            continue
        if all(source in pure or source not in produced for _, source in node.inputs):
            pure.add(node.output)
            nodes.append(node)
    return nodes
