"""IPM stages (paper Sec. III-A, eq. 1-4): ``ipm=plain`` and the motion-compensated ``ipm=mc`` and its extensions."""

from __future__ import annotations

from sgf_pipeline import StageRegistry, hookimpl
from sgf_plugins.ipm.geometry import (
    bev_to_image_homography,
    compensated_ground_point,
    ground_to_image_homography,
    mc_pixel_to_ground,
    metric_image_coordinates,
    roll_compensation,
    visible_mask,
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
    "bev_to_image_homography",
    "compensated_ground_point",
    "ground_to_image_homography",
    "mc_pixel_to_ground",
    "metric_image_coordinates",
    "roll_compensation",
    "sgf_register_stages",
    "visible_mask",
]


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register plain IPM, MC-IPM, and MC-IPM with the ground plane from two views or from the path driven next."""
    registry.add(InversePerspectiveMapping)
    registry.add(MotionCompensatedIPM)
    registry.add(PlaneMotionCompensatedIPM)
    registry.add(HindsightMotionCompensatedIPM)
