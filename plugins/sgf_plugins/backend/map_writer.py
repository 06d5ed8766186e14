"""The run's SGF map file (``sgf_map.safetensors``), written by the back-end.

The map holds the groups the loop stage settled on (``Settlement.assignments``), each view at its
frame's pose in the back-end's estimate. That estimate is final only once the back-end has
finished, so the back-end writes the map, every variant alike: ``backend=none`` places the views
at the odometry's poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sgf_pipeline import RunContext
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.sgf_map import SgfMap, build_map, save_map
from sgf_pipeline.stage import Settlement
from sgf_pipeline.types import PoseEstimate


def write_sgf_map(
    context: RunContext,
    settlement: Settlement,
    estimate: PoseEstimate,
    file_name: str,
    calibration: Calibration | None,
    ground_truth: dict[int, np.ndarray],
) -> SgfMap | None:
    """Write the settlement's groups at the estimate's poses into the run directory; the map, or None if none."""
    if context.run_dir is None or not settlement.assignments:
        return None
    # a run stopped between the loop stage and the back-end has assignments of a frame without a pose yet
    assignments = [
        a
        for a in settlement.assignments
        if getattr(a.descriptor, "sgf", None) is None or a.descriptor.sgf.frame_index in estimate.poses
    ]
    sgf_map = build_map(
        assignments,
        estimate.poses,
        calibration=calibration,
        sequence=context.sequence,
        ground_truth=ground_truth,
        group_of=settlement.group_of,
    )
    path = Path(context.run_dir) / file_name
    map_id = save_map(path, sgf_map)
    context.artifacts["sgf_map"] = {"path": str(path), "map_id": map_id}
    return sgf_map
