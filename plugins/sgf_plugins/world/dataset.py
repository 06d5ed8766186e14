"""The campus presets as ``dataset`` variants: ``campus_delivery`` (the default), ``campus_large_loop``...

Each variant streams its world's frames (every 10 Hz frame, image and ids rendered lazily in
one pass) and fills the run context with the calibration, the frame rate and the exact ground
truth (marking table, passes, revisit pairs) before the first frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, ClassVar

from sgf_pipeline import Dataset, StageRegistry, hookimpl
from sgf_pipeline.context import RunContext
from sgf_pipeline.types import Frame
from sgf_plugins.world.params import NightWorldParams, WorldParams
from sgf_plugins.world.presets import PRESETS

if TYPE_CHECKING:
    from sgf_plugins.world.world import CampusWorld


class CampusDataset(Dataset):
    """A synthetic campus sequence rendered on the fly, with exact ground truth."""

    preset: ClassVar[str]
    Params = WorldParams

    def __init__(self, params: WorldParams) -> None:
        super().__init__(params)
        self.world_params = params
        self._world: CampusWorld | None = None

    @property
    def world(self) -> CampusWorld:
        """The world (built on first use: layout, terrain, drive)."""
        if self._world is None:
            from sgf_plugins.world.world import CampusWorld

            self._world = CampusWorld(PRESETS[self.preset], self.world_params)
        return self._world

    def __len__(self) -> int:
        """Number of camera frames of the drive."""
        return len(self.world)

    def begin(self, context: RunContext) -> None:
        """Put the calibration, frame rate, sequence name and ground truth into the run context."""
        world = self.world
        context.calibration = world.calibration
        context.rate_hz = world.params.rate_hz
        context.sequence = self.preset
        context.truth = world.truth

    def frames(self) -> Iterator[Frame]:
        """Every frame of the drive in time order."""
        return self.world.frames()


class CampusDelivery(CampusDataset):
    """Seq. Delivery: home, out to a drop-off, a stop, and back home (the default sequence)."""

    name = "campus_delivery"
    preset = "campus_delivery"


class CampusLargeLoop(CampusDataset):
    """Seq. Large loop: about 2.7 km around the campus, forward revisits and a reverse stretch."""

    name = "campus_large_loop"
    preset = "campus_large_loop"


class CampusReverseSlope(CampusDataset):
    """Seq. Reverse+Slope: over the hills and back the same way (reverse revisits only)."""

    name = "campus_reverse_slope"
    preset = "campus_reverse_slope"


class CampusLargeLoopNight(CampusDataset):
    """Seq. Large loop (Night): the large loop after dark."""

    name = "campus_large_loop_night"
    preset = "campus_large_loop_night"
    Params = NightWorldParams


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the four campus presets."""
    for cls in (CampusDelivery, CampusLargeLoop, CampusReverseSlope, CampusLargeLoopNight):
        registry.add(cls)
