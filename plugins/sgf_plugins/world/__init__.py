"""The synthetic campus world: the embedded default data of sgf-pipeline, with exact ground truth.

``build_world(preset, seed, scale, **overrides)`` gives a :class:`CampusWorld` that renders any
robot pose (``render(pose, night=True, ...)``), knows the orthographic marking layout under any
pose (``marking_layout``), drives the preset's route (``frames()``) and holds its ground truth
(``truth``). The four presets are registered as ``dataset`` variants by
:mod:`sgf_plugins.world.dataset`.
"""

from sgf_plugins.world.designs import DESIGNS, HELD_OUT_FAMILIES, MarkingDesign, allowed_designs, families
from sgf_plugins.world.presets import PRESETS, Preset
from sgf_plugins.world.render import RenderConditions, RenderLayers
from sgf_plugins.world.terrain import Terrain
from sgf_plugins.world.world import CampusWorld, WorldParams, build_world, world_params

__all__ = [
    "DESIGNS",
    "HELD_OUT_FAMILIES",
    "PRESETS",
    "CampusWorld",
    "MarkingDesign",
    "Preset",
    "RenderConditions",
    "RenderLayers",
    "Terrain",
    "WorldParams",
    "allowed_designs",
    "build_world",
    "families",
    "world_params",
]
