"""Trajectory error metrics computed with evo's library (evo's conventions, not a re-implementation).

``ate`` is evo's APE on the translation part (``evo_ape ... [-a | -as]``), ``rpe`` evo's RPE
(``evo_rpe ... --delta D --delta_unit f|m|d|r [-a | -as]``). Both first pair the poses by
timestamp with evo's ``associate_trajectories`` (nearest stamp within ``max_time_diff``); KITTI
files read without a times file carry their row numbers as timestamps and so pair row by row,
as ``evo_ape kitti`` does. Only ``evo.core`` and ``evo.main_ape``/``evo.main_rpe`` are imported:
they write no settings file.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from sgf_pipeline.errors import DataError
from sgf_pipeline.trajectory import Trajectory

Alignment = Literal["none", "se3", "sim3"]
DeltaUnit = Literal["frames", "meters", "degrees", "radians"]
RpeRelation = Literal["translation", "rotation"]
ALIGNMENTS: tuple[Alignment, ...] = ("none", "se3", "sim3")


@dataclass(frozen=True)
class ErrorStatistics:
    """Summary of a per-pose error, as evo reports it (``pairs``: poses or pose pairs compared)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    pairs: int

    def as_dict(self) -> dict[str, Any]:
        """Plain-data form for JSON."""
        return asdict(self)


# evo logs every result table at INFO; the project reports its own numbers.
logging.getLogger("evo").setLevel(logging.WARNING)


def _to_evo(trajectory: Trajectory):  # type: ignore[no-untyped-def]
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(trajectory.poses), timestamps=trajectory.timestamps.copy())


def _associate(reference: Trajectory, estimate: Trajectory, max_time_diff: float):  # type: ignore[no-untyped-def]
    from evo.core import sync

    try:
        return sync.associate_trajectories(_to_evo(reference), _to_evo(estimate), max_diff=max_time_diff)
    except sync.SyncException as exc:
        raise DataError(
            f"no poses of the two trajectories are within {max_time_diff} s of each other ({exc}). Reference "
            f"spans t={reference.timestamps[0]:.3f}..{reference.timestamps[-1]:.3f} s, estimate "
            f"t={estimate.timestamps[0]:.3f}..{estimate.timestamps[-1]:.3f} s: are both in the same clock "
            "(a KITTI file without its times file is timed by row number)?"
        ) from None


def _degenerate(align: str, exc: Exception) -> DataError:
    """The error for a trajectory whose shape leaves the alignment undetermined."""
    return DataError(
        f"{align} alignment is not possible ({exc}): the associated positions lie on one point or one line "
        "(a robot standing still or driving straight), which leaves the rotation undetermined; use align=none"
    )


def _check_alignment(align: str, pairs: int) -> None:
    if align not in ALIGNMENTS:
        raise DataError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    if align != "none" and pairs < 3:
        raise DataError(f"{align} alignment needs at least 3 associated poses, got {pairs}")


def _statistics(result: Any, pairs: int) -> ErrorStatistics:
    s = result.stats
    return ErrorStatistics(
        rmse=float(s["rmse"]),
        mean=float(s["mean"]),
        median=float(s["median"]),
        std=float(s["std"]),
        min=float(s["min"]),
        max=float(s["max"]),
        sse=float(s["sse"]),
        pairs=pairs,
    )


def ate(
    reference: Trajectory, estimate: Trajectory, align: Alignment = "se3", max_time_diff: float = 0.01
) -> ErrorStatistics:
    """Absolute trajectory error: evo's APE of the translation part after ``none``/``se3``/``sim3`` alignment."""
    from evo.core import metrics
    from evo.core.geometry import GeometryException
    from evo.main_ape import ape

    ref, est = _associate(reference, estimate, max_time_diff)
    _check_alignment(align, ref.num_poses)
    try:
        result = ape(
            ref,
            est,
            metrics.PoseRelation.translation_part,
            align=align != "none",
            correct_scale=align == "sim3",
        )
    except GeometryException as exc:
        raise _degenerate(align, exc) from None
    return _statistics(result, ref.num_poses)


def ate_rmse(
    reference: Trajectory, estimate: Trajectory, align: Alignment = "se3", max_time_diff: float = 0.01
) -> float:
    """RMSE of the absolute translation error (evo APE, translation part) after alignment.

    Poses are associated by timestamp with evo's ``associate_trajectories``; ``se3`` is evo's
    ``-a`` (Umeyama, rigid) and ``sim3`` its ``-as``.
    """
    return ate(reference, estimate, align, max_time_diff).rmse


def rpe(
    reference: Trajectory,
    estimate: Trajectory,
    delta: float = 1.0,
    delta_unit: DeltaUnit = "frames",
    relation: RpeRelation = "translation",
    align: Alignment = "none",
    all_pairs: bool = False,
    max_time_diff: float = 0.01,
) -> ErrorStatistics:
    """Relative pose error (evo's RPE): ``translation`` in m or ``rotation`` angle in degrees per ``delta``."""
    from evo.core import metrics
    from evo.core.filters import FilterException
    from evo.core.geometry import GeometryException
    from evo.core.units import Unit
    from evo.main_rpe import rpe as evo_rpe

    units = {"frames": Unit.frames, "meters": Unit.meters, "degrees": Unit.degrees, "radians": Unit.radians}
    relations = {
        "translation": metrics.PoseRelation.translation_part,
        "rotation": metrics.PoseRelation.rotation_angle_deg,
    }
    if delta_unit not in units:
        raise DataError(f"unknown RPE delta unit {delta_unit!r}; choose one of {', '.join(units)}")
    if relation not in relations:
        raise DataError(f"unknown RPE relation {relation!r}; choose one of {', '.join(relations)}")
    if delta <= 0 or (delta_unit == "frames" and float(delta) != int(delta)):
        raise DataError(f"RPE delta must be positive (and whole for frames), got {delta!r}")
    ref, est = _associate(reference, estimate, max_time_diff)
    _check_alignment(align, ref.num_poses)
    try:
        result = evo_rpe(
            ref,
            est,
            relations[relation],
            delta=int(delta) if delta_unit == "frames" else float(delta),
            delta_unit=units[delta_unit],
            all_pairs=all_pairs,
            align=align != "none",
            correct_scale=align == "sim3",
        )
    except FilterException as exc:
        raise DataError(f"RPE: {exc}") from None
    except GeometryException as exc:
        raise _degenerate(align, exc) from None
    return _statistics(result, len(result.np_arrays["error_array"]))


def aligned_positions(reference: Trajectory | None, estimate: Trajectory, max_time_diff: float = 0.01) -> np.ndarray:
    """(N, 3) positions of ``estimate`` after SE(3) Umeyama alignment to ``reference`` (for plots)."""
    from evo.core import sync

    if reference is None or len(reference) < 3:
        return estimate.positions
    try:
        ref, est = sync.associate_trajectories(_to_evo(reference), _to_evo(estimate), max_diff=max_time_diff)
        est.align(ref, correct_scale=False)
    except Exception:
        return estimate.positions
    return np.asarray(est.positions_xyz)
