"""What the runner shares with stages over one sequence: calibration, ground truth, results."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sgf_pipeline.calibration import Calibration
    from sgf_pipeline.trajectory import Trajectory
    from sgf_pipeline.truth import SequenceTruth


@dataclass
class RunContext:
    """The sequence-wide context given to ``begin`` and ``finalize`` of every stage.

    ``metrics`` entries are merged into ``metrics.json``; ``trajectories`` named ``sgf`` (and any
    other name) are written as ``trajectory_<name>.tum``; ``artifacts`` carries objects for
    reports (loop list, selected SGFs) between stages and observers; ``report_sections`` are
    Markdown sections appended to the run's ``report.md``.
    """

    run_dir: Path | None
    sequence: str = ""
    rate_hz: float | None = None
    calibration: Calibration | None = None
    truth: SequenceTruth | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    artifacts: dict[str, Any] = field(default_factory=dict)
    report_sections: list[str] = field(default_factory=list)

    def path(self, name: str) -> Path | None:
        """Path of a file in the run directory, or ``None`` when the run writes no files."""
        return None if self.run_dir is None else self.run_dir / name
