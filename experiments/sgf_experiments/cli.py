"""``sgf-report DIR``: turn a run or multirun directory into the paper's tables, CSV and figures."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from sgf_experiments.report import report_path, write_report
from sgf_pipeline.cli.common import console, friendly_errors
from sgf_pipeline.errors import ConfigError

#: The command line with the directory given as a path.
USAGE = "sgf-report DIR [out=OTHER_DIR]"


@hydra.main(config_path=str(Path(__file__).resolve().parent / "conf"), config_name="sgf_report", version_base="1.3")
@friendly_errors
def _app(cfg: DictConfig) -> None:
    if not cfg.get("dir"):
        raise ConfigError(f"which runs? pass a run or multirun directory: {USAGE} (or dir=DIR)")
    root = Path(str(cfg.dir))
    out = Path(str(cfg.out)) if cfg.get("out") else root
    report = report_path(out)  # beside a run's own report.md, never over it
    write_report(root, out)
    print(report.read_text(), end="")
    print(f"\nwrote {report}, {out / 'runs.csv'}, {out / 'tables.json'}")


#: The ``sgf-report`` console script: ``sgf-report DIR`` or ``sgf-report dir=DIR``.
main = console(_app, positional=("dir",), usage=USAGE)


if __name__ == "__main__":
    main()
