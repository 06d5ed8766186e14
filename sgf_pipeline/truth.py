"""A sequence's ground truth: its marking instances, the robot's passes over them and the revisit pairs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class MarkingTruth:
    """A ground-truth marking instance of a synthetic world (pose: world x, y, yaw; size: length, width in m)."""

    instance_id: int
    design: str
    category: Literal["standard", "custom"]
    symmetric: bool
    pose: tuple[float, float, float]
    size: tuple[float, float]


PASS_SLACK_FRAMES = 5
"""Frames before or after a pass whose views still count as that pass's (``SequenceTruth.drive_by``): a selected
view can show a marking a frame or two before the ground truth has it wholly in view."""


@dataclass(frozen=True)
class MarkingPass:
    """One pass of the robot over a marking: the frames over which the marking is wholly in view."""

    instance_id: int
    number: int
    start_frame: int
    end_frame: int
    heading: float

    def contains(self, frame_index: int) -> bool:
        """Whether a frame belongs to this pass."""
        return self.start_frame <= frame_index <= self.end_frame


@dataclass(frozen=True)
class RevisitPair:
    """Two consecutive passes over the same marking instance (Table 3: loop pairs)."""

    instance_id: int
    first: MarkingPass
    second: MarkingPass
    reverse: bool


@dataclass
class SequenceTruth:
    """What a dataset knows exactly: the marking table, each marking's passes, the revisit pairs."""

    markings: dict[int, MarkingTruth] = field(default_factory=dict)
    passes: list[MarkingPass] = field(default_factory=list)
    revisits: list[RevisitPair] = field(default_factory=list)

    def pass_of(self, instance_id: int, frame_index: int) -> MarkingPass | None:
        """The pass of ``instance_id`` that ``frame_index`` belongs to, if any."""
        return self.drive_by(instance_id, frame_index, slack=0)

    def drive_by(self, instance_id: int, frame_index: int, slack: int = PASS_SLACK_FRAMES) -> MarkingPass | None:
        """The pass a view of ``instance_id`` at ``frame_index`` comes from.

        That is the pass holding the frame, else the nearest one at most ``slack`` frames away (a view
        taken just before the marking is wholly in view).
        """
        best: tuple[int, MarkingPass] | None = None
        for p in self.passes:
            if p.instance_id != instance_id:
                continue
            gap = max(p.start_frame - frame_index, frame_index - p.end_frame, 0)
            if gap <= slack and (best is None or gap < best[0]):
                best = (gap, p)
        return None if best is None else best[1]

    @property
    def on_path(self) -> set[int]:
        """Instances wholly in view at least once: the SGFs that should be detected (Table 3)."""
        return {p.instance_id for p in self.passes}
