"""What a run shows of itself: its stage nodes, what observers see, the read-only view its files come from."""

from __future__ import annotations

import resource
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sgf_pipeline.context import RunContext
from sgf_pipeline.stage import Dataset, InputSpec, Stage
from sgf_pipeline.variants import VariantInfo

if TYPE_CHECKING:
    import pluggy

    from sgf_pipeline.config import RunOptions
    from sgf_pipeline.trajectory import Trajectory


@dataclass
class StageNode:
    """A configured stage in the graph: its variant, instance and wired inputs."""

    kind: str
    name: str
    variant: VariantInfo
    stage: Stage | Dataset
    output: str
    inputs: list[tuple[InputSpec, str]] = field(default_factory=list)

    @property
    def label(self) -> str:
        """``kind=name`` for messages."""
        return f"{self.kind}={self.name}"


@dataclass
class RunInfo:
    """What observers see of a run: stages in order, counts, the output directory and their own options.

    ``context`` is the context the stages share (at the end it holds their trajectories and artifacts);
    ``observer_options`` the validated config nodes the observers declare (``sgf_observer_options``).
    """

    run_dir: Path | None
    stages: list[StageNode]
    sequence: str
    total_frames: int
    frames_seen: int = 0
    frames_processed: int = 0
    dataset_seconds: float = 0.0
    work_seconds: float = 0.0
    first_timestamp: float | None = None
    last_timestamp: float | None = None
    options: Any = None
    context: RunContext | None = None
    observer_options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RunView:
    """A pipeline's run as its output files are written from (``Pipeline.view()``).

    ``recorded`` holds the trajectories the runner records frame by frame (``odometry`` and ``gt``,
    when the run has them); ``dropped`` the frames the runner refused (``Pipeline.drop_report()``).
    """

    info: RunInfo
    options: RunOptions
    run_dir: Path | None
    effective_config: Mapping[str, Any] | None
    context: RunContext
    hooks: pluggy.HookRelay
    dropped: dict[str, Any]
    recorded: dict[str, Trajectory]


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
