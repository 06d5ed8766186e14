"""``sgf-report DIR``: turn a run or multirun directory into the paper's tables, CSV and figures."""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.config import config_dir
from sgf_pipeline.errors import ConfigError
from sgf_pipeline.report import write_report


@hydra.main(config_path=str(config_dir()), config_name="sgf_report", version_base="1.3")
@friendly_errors
def _app(cfg: DictConfig) -> None:
    if not cfg.get("dir"):
        raise ConfigError("which runs? pass a run or multirun directory: `sgf-report outputs/multirun/<time>`")
    root = Path(str(cfg.dir))
    out = Path(str(cfg.out)) if cfg.get("out") else root
    write_report(root, out)
    print((out / "report.md").read_text(), end="")
    print(f"\nwrote {out / 'report.md'}, {out / 'runs.csv'}, {out / 'tables.json'}")


def main() -> None:
    """Accept ``sgf-report DIR`` as well as ``sgf-report dir=DIR``."""
    args = sys.argv[1:]
    if args and "=" not in args[0] and not args[0].startswith("-"):
        sys.argv = [sys.argv[0], f"dir={args[0]}", *args[1:]]
    console(_app)()


if __name__ == "__main__":
    main()
