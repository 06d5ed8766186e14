"""The synthetic campus world: the embedded default data of sgf-pipeline, with exact ground truth.

``build_world(preset, seed, scale, **overrides)`` gives a :class:`CampusWorld` that renders any
robot pose (``render(pose, night=True, ...)``), knows the orthographic marking layout under any
pose (``marking_layout``), drives the preset's route (``frames()``) and holds its ground truth
(``truth``). The four presets are registered as ``dataset`` variants by
:mod:`sgf_plugins.world.dataset`. Names are imported on first use, so that loading the plugin
(``sgf-plugins``) does not import the renderer.

The campus is a :class:`~sgf_plugins.world.layout.CampusLayout` (``layout``) laid out by
``layout_generator`` with ``marking_placement`` and ``agent_placement``. Its markings are the
``designs`` of the library, drawn on a ``canvas`` by ``road_markings`` and ``campus_markings``
and rasterised by ``marking_raster``.

The camera (:mod:`~sgf_plugins.world.render`) composes its collaborators: the rays on the
terrain (``raycast``), the ground's tile mosaics and grain (``ground``, tiles from ``texture``
with ``paving``, ``clutter`` and ``ground_shadows`` under the ``sun``), ``sky`` and light, the
people and vehicles in front of it (``occluders``), what stands above the ground (``scenery``:
``buildings``, ``trees``, ``lamps``, ``pedestrians``, ``vehicles``) and the ``sensor``; a
frame's ``conditions`` say how it is rendered.
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sgf_plugins.world.conditions import RenderConditions
    from sgf_plugins.world.designs import DESIGNS, HELD_OUT_FAMILIES, MarkingDesign, allowed_designs, families
    from sgf_plugins.world.params import NightWorldParams, WorldParams
    from sgf_plugins.world.presets import PRESETS, Preset
    from sgf_plugins.world.render import RenderLayers
    from sgf_plugins.world.terrain import Terrain
    from sgf_plugins.world.world import CampusWorld, build_world, world_params

_WHERE = {
    "DESIGNS": "designs",
    "HELD_OUT_FAMILIES": "designs",
    "MarkingDesign": "designs",
    "allowed_designs": "designs",
    "families": "designs",
    "NightWorldParams": "params",
    "WorldParams": "params",
    "PRESETS": "presets",
    "Preset": "presets",
    "RenderConditions": "conditions",
    "RenderLayers": "render",
    "Terrain": "terrain",
    "CampusWorld": "world",
    "build_world": "world",
    "world_params": "world",
}

__all__ = [
    "DESIGNS",
    "HELD_OUT_FAMILIES",
    "PRESETS",
    "CampusWorld",
    "MarkingDesign",
    "NightWorldParams",
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


def __getattr__(name: str) -> Any:
    """Import a public name of the package from its module on first use."""
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_module(_WHERE[name]), name)
    globals()[name] = value
    return value


def _module(name: str) -> ModuleType:
    """The submodule ``name``, imported on demand (a fixed set: nothing named by data is imported)."""
    if name == "conditions":
        from sgf_plugins.world import conditions

        return conditions
    if name == "designs":
        from sgf_plugins.world import designs

        return designs
    if name == "params":
        from sgf_plugins.world import params

        return params
    if name == "presets":
        from sgf_plugins.world import presets

        return presets
    if name == "render":
        from sgf_plugins.world import render

        return render
    if name == "terrain":
        from sgf_plugins.world import terrain

        return terrain
    from sgf_plugins.world import world

    return world
