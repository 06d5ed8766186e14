"""IPM stages (paper Sec. III-A, eq. 1-4): ``ipm=plain`` and the motion-compensated ``ipm=mc`` and its extensions."""

from __future__ import annotations

from sgf_pipeline import StageRegistry, hookimpl
from sgf_plugins.ipm.geometry import (
    compensated_ground_point,
    mc_pixel_to_ground,
    metric_image_coordinates,
    roll_compensation,
)
from sgf_plugins.ipm.reference import PoseQueue, ReferenceAttitude
from sgf_plugins.ipm.stages import (
    HindsightMotionCompensatedIPM,
    HindsightMotionCompensatedIpmParams,
    InversePerspectiveMapping,
    IpmParams,
    MotionCompensatedIPM,
    MotionCompensatedIpmParams,
    PlaneMotionCompensatedIPM,
    PlaneMotionCompensatedIpmParams,
)

__all__ = [
    "HindsightMotionCompensatedIPM",
    "HindsightMotionCompensatedIpmParams",
    "InversePerspectiveMapping",
    "IpmParams",
    "MotionCompensatedIPM",
    "MotionCompensatedIpmParams",
    "PlaneMotionCompensatedIPM",
    "PlaneMotionCompensatedIpmParams",
    "PoseQueue",
    "ReferenceAttitude",
    "compensated_ground_point",
    "mc_pixel_to_ground",
    "metric_image_coordinates",
    "roll_compensation",
    "sgf_register_stages",
]


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register plain IPM, MC-IPM, and MC-IPM with the ground plane from two views or from the path driven next."""
    registry.add(InversePerspectiveMapping)
    registry.add(MotionCompensatedIPM)
    registry.add(PlaneMotionCompensatedIPM)
    registry.add(HindsightMotionCompensatedIPM)
