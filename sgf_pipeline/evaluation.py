"""Trajectory error metrics computed with evo's library (evo's conventions, not a re-implementation)."""

from __future__ import annotations

import logging
from typing import Literal

from sgf_pipeline.trajectory import Trajectory

Alignment = Literal["none", "se3", "sim3"]

# evo logs every result table at INFO; the project reports its own numbers.
logging.getLogger("evo").setLevel(logging.WARNING)


def _to_evo(trajectory: Trajectory):  # type: ignore[no-untyped-def]
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(trajectory.poses), timestamps=trajectory.timestamps.copy())


def ate_rmse(
    reference: Trajectory, estimate: Trajectory, align: Alignment = "se3", max_time_diff: float = 0.01
) -> float:
    """RMSE of the absolute translation error (evo APE, translation part) after alignment.

    Poses are associated by timestamp with evo's ``associate_trajectories``; ``se3`` is evo's
    ``-a`` (Umeyama, rigid) and ``sim3`` its ``-as``.
    """
    from evo.core import metrics, sync
    from evo.main_ape import ape

    ref, est = sync.associate_trajectories(_to_evo(reference), _to_evo(estimate), max_diff=max_time_diff)
    result = ape(
        ref,
        est,
        metrics.PoseRelation.translation_part,
        align=align in ("se3", "sim3"),
        correct_scale=align == "sim3",
    )
    return float(result.stats["rmse"])


def aligned_positions(reference: Trajectory | None, estimate: Trajectory, max_time_diff: float = 0.01):  # type: ignore[no-untyped-def]
    """(N, 3) positions of ``estimate`` after SE(3) Umeyama alignment to ``reference`` (for plots)."""
    import numpy as np
    from evo.core import sync

    if reference is None or len(reference) < 3:
        return estimate.positions
    try:
        ref, est = sync.associate_trajectories(_to_evo(reference), _to_evo(estimate), max_diff=max_time_diff)
        est.align(ref, correct_scale=False)
    except Exception:
        return estimate.positions
    return np.asarray(est.positions_xyz)
