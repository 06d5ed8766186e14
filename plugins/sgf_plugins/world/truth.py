"""Exact ground truth of a drive: which markings are wholly in view when, their passes and revisits (Table 3)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.geometry import wrap_angle
from sgf_pipeline.truth import MarkingPass, MarkingTruth, RevisitPair, SequenceTruth
from sgf_pipeline.types import BevGrid
from sgf_plugins.world.layout import MarkingInstance
from sgf_plugins.world.terrain import Terrain


def marking_points(marking: MarkingInstance, terrain: Terrain) -> np.ndarray:
    """World 3-D points (N, 3) of a marking's outline (its mask's convex hull), lying on the ground."""
    xy = marking.local_to_world(marking.outline)
    return np.column_stack([xy, terrain.height(xy[:, 0], xy[:, 1])])


def wholly_visible(points: np.ndarray, poses: np.ndarray, calibration: Calibration, grid: BevGrid) -> np.ndarray:
    """Per pose (F,), whether every world point (N, 3) lies in the visibility region of that pose.

    The visibility region is the IPM's: ground points whose base-frame ``x`` and ``y`` are inside
    the BEV grid, that project inside the camera image (in front of it), and whose pixel is below
    the horizon of the base plane (the ray from the camera goes down in the base frame).
    """
    rot = poses[:, :3, :3]
    trans = poses[:, :3, 3]
    local = np.einsum("fji,fnj->fni", rot, points[None, :, :] - trans[:, None, :])
    inside = (
        (local[..., 0] >= grid.x_min)
        & (local[..., 0] <= grid.x_max)
        & (local[..., 1] >= grid.y_min)
        & (local[..., 1] <= grid.y_max)
    )
    cam = calibration.camera_to_base_matrix
    below = local[..., 2] < cam[2, 3]
    pc = (local - cam[:3, 3]) @ cam[:3, :3]
    intr = calibration.intrinsics
    z = pc[..., 2]
    front = z > 0.05
    zs = np.where(front, z, 1.0)
    u = intr.fx * pc[..., 0] / zs + intr.cx
    v = intr.fy * pc[..., 1] / zs + intr.cy
    in_image = front & (u >= -0.5) & (u <= intr.width - 0.5) & (v >= -0.5) & (v <= intr.height - 0.5)
    return np.all(inside & below & in_image, axis=1)


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs ``(start, end)`` (inclusive) of True in a boolean array."""
    if not flags.any():
        return []
    d = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def _mean_heading(yaws: np.ndarray) -> float:
    return float(math.atan2(np.sin(yaws).mean(), np.cos(yaws).mean()))


def sequence_truth(
    markings: Sequence[MarkingInstance],
    terrain: Terrain,
    poses: np.ndarray,
    calibration: Calibration,
    grid: BevGrid,
    merge_gap: int = 0,
) -> SequenceTruth:
    """The marking table, every marking's passes and the revisit pairs of a drive.

    A pass is a maximal run of frames in which the marking lies wholly inside the visibility
    region; runs of one drive-by split by a short gap (a bump pitching the view away) are joined
    when at most ``merge_gap`` frames apart and driven in the same direction. Revisit pairs are
    consecutive passes of one marking; reverse when the headings differ by more than 90 degrees.
    """
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    tree = cKDTree(poses[:, :2, 3])
    reach = math.hypot(max(abs(grid.x_min), abs(grid.x_max)), max(abs(grid.y_min), abs(grid.y_max)))
    table: dict[int, MarkingTruth] = {}
    passes: list[MarkingPass] = []
    revisits: list[RevisitPair] = []
    for m in markings:
        table[m.instance_id] = MarkingTruth(
            instance_id=m.instance_id,
            design=m.design.name,
            category=m.design.category,
            symmetric=m.design.symmetric,
            pose=(float(m.x), float(m.y), float(m.yaw)),
            size=(float(m.length), float(m.width)),
        )
        near = np.asarray(sorted(tree.query_ball_point([m.x, m.y], reach + m.radius)), dtype=np.int64)
        if near.size == 0:
            continue
        pts = marking_points(m, terrain)
        ok = wholly_visible(pts, poses[near], calibration, grid)
        flags = np.zeros(len(poses), bool)
        flags[near[ok]] = True
        runs = _runs(flags)
        merged: list[tuple[int, int]] = []
        for start, end in runs:
            if merged:
                p0, p1 = merged[-1]
                same_way = (
                    abs(wrap_angle(_mean_heading(yaw[p0 : p1 + 1]) - _mean_heading(yaw[start : end + 1]))) < math.pi / 2
                )
                if start - p1 - 1 <= merge_gap and same_way:
                    merged[-1] = (p0, end)
                    continue
            merged.append((start, end))
        mine = [
            MarkingPass(m.instance_id, k + 1, s, e, _mean_heading(yaw[s : e + 1])) for k, (s, e) in enumerate(merged)
        ]
        passes.extend(mine)
        for a, b in itertools.pairwise(mine):
            revisits.append(RevisitPair(m.instance_id, a, b, abs(wrap_angle(b.heading - a.heading)) > math.pi / 2))
    passes.sort(key=lambda p: (p.start_frame, p.instance_id))
    revisits.sort(key=lambda r: (r.second.start_frame, r.instance_id))
    return SequenceTruth(markings=table, passes=passes, revisits=revisits)
