"""``sgf-cache``: show or clear the stage cache (:mod:`sgf_pipeline.cache`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

from sgf_pipeline.cache import EntryInfo, StageCache, default_cache_dir
from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir
from sgf_pipeline.errors import ConfigError

#: The values of ``action=``.
ACTIONS = ("show", "clear")


def _size(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"  # pragma: no cover - the loop returns


def listing(root: Path, entries: list[EntryInfo]) -> str:
    """The entries, most recently used first, with their total."""
    if not entries:
        return f"the stage cache in {root} is empty"
    rows = [("kind", "stage", "key", "frames", "size", "last used")]
    for e in sorted(entries, key=lambda e: -e.last_used):
        used = time.strftime("%Y-%m-%d %H:%M", time.localtime(e.last_used))
        rows.append((e.kind, e.stage, e.key[:12], str(e.frames), _size(e.bytes), used))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    total = sum(e.bytes for e in entries)
    lines.append(f"{len(entries)} entries, {_size(total)} in {root}")
    return "\n".join(lines)


@hydra.main(config_path=str(config_dir()), config_name="sgf_cache", version_base="1.3")
@friendly_errors
def _app(cfg: DictConfig) -> None:
    action = str(cfg.action)
    if action not in ACTIONS:
        raise ConfigError(f"action={action}: choose one of {', '.join(ACTIONS)} (`sgf-cache clear` clears)")
    root = Path(str(cfg.dir)).expanduser() if cfg.get("dir") else default_cache_dir()
    kind = str(cfg.kind) if cfg.get("kind") else None
    if not root.is_dir():
        print(f"the stage cache in {root} is empty")
        return
    cache = StageCache(root, max_bytes=0)
    if action == "clear":
        removed = cache.clear(kind)
        print(f"removed {len(removed)} entries ({_size(sum(e.bytes for e in removed))}) from {root}")
        return
    print(listing(root, [e for e in cache.entries() if kind is None or e.kind == kind]))


def main() -> None:
    """Accept ``sgf-cache clear`` and ``sgf-cache show`` as well as ``action=...``."""
    args = sys.argv[1:]
    if args and args[0] in ACTIONS:
        sys.argv = [sys.argv[0], f"action={args[0]}", *args[1:]]
    console(_app)()


if __name__ == "__main__":
    main()
