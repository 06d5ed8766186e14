"""SGF maps (format ``sgf-map``, version 1): a run's SGF groups, saved to localize later runs (eq. 11).

A map holds every SGF group of a run with its member views: each view's metric ground points
(in the base frame of the frame it was selected on), polar descriptor, and the optimized
map-frame pose of that frame, plus the camera calibration the run used. It is one
safetensors file: arrays as tensors (no pickle), and a JSON header in the safetensors
metadata (``format``, ``version``, ``header``). The header records the sequence, the
calibration, the groups and a SHA-256 of the tensors, so a damaged file is refused.

Tensors (V views, G groups, P points in all; ``Nr x Ns`` descriptor bins):

- ``view_group`` (V,) int64, ``view_frame`` (V,) int64, ``view_track`` (V,) int64,
  ``view_instance`` (V,) int64 (-1 = unknown), ``view_timestamp`` (V,) float64
- ``view_pose`` (V, 4, 4) float64: optimized pose of the view's frame in the map frame
- ``view_ground_truth`` (V, 4, 4) float64 and ``view_has_ground_truth`` (V,) uint8
- ``view_centroid`` (V, 2), ``view_matrix`` (V, Nr, Ns), ``view_ring_key`` (V, Nr) float64
- ``view_grid`` (V, 5) float64: BEV grid (resolution, x_min, x_max, y_min, y_max)
- ``view_hu`` (V, 7), ``view_saliency`` (V,), ``view_views`` (V,) int64
- ``view_point_offset`` (V + 1,) int64 and ``points`` (P, 2) float64: view ``k`` owns
  ``points[offset[k]:offset[k + 1]]``
- ``group_id`` (G,) int64, ``group_symmetric`` (G,) uint8

A prior map reaches the loop stage as :class:`MapDescriptor` objects (``MapView.descriptor()``):
SGF descriptors whose frame index and pose are the map's, so a match against one is an
inter-session factor ("SGF pairs observed in different sequences", eq. 11).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.errors import DataError
from sgf_pipeline.io import atomic_write_bytes
from sgf_pipeline.types import BevGrid, GroupAssignment, SalientGroundFeature, SgfDescriptor

FORMAT = "sgf-map"
VERSION = 1

_VIEW_TENSORS = (
    "view_group",
    "view_frame",
    "view_track",
    "view_instance",
    "view_timestamp",
    "view_pose",
    "view_ground_truth",
    "view_has_ground_truth",
    "view_centroid",
    "view_matrix",
    "view_ring_key",
    "view_grid",
    "view_hu",
    "view_saliency",
    "view_views",
)


@dataclass(frozen=True)
class MapDescriptor(SgfDescriptor):
    """An SGF descriptor from a prior map: ``sgf.frame_index`` is the map's frame, ``map_pose`` its pose there."""

    map_pose: np.ndarray
    ground_truth: np.ndarray | None = None


@dataclass(frozen=True)
class MapView:
    """One member of an SGF group: a selected SGF, its points and the optimized pose it was seen from."""

    group_id: int
    frame_index: int
    timestamp: float
    pose: np.ndarray
    points: np.ndarray
    centroid: np.ndarray
    matrix: np.ndarray
    ring_key: np.ndarray
    grid: BevGrid
    track_id: int = -1
    instance_id: int | None = None
    ground_truth: np.ndarray | None = None
    hu: np.ndarray = field(default_factory=lambda: np.zeros(7))
    saliency: float = 0.0
    views: int = 1

    def descriptor(self) -> MapDescriptor:
        """The view as an SGF descriptor of the prior map (BEV pixels are not stored: empty)."""
        sgf = SalientGroundFeature(
            track_id=self.track_id,
            frame_index=self.frame_index,
            timestamp=self.timestamp,
            odometry=self.pose,
            pixels=np.zeros((0, 2), dtype=np.int64),
            grid=self.grid,
            saliency=self.saliency,
            hu=self.hu,
            views=self.views,
            instance_id=self.instance_id,
        )
        return MapDescriptor(
            sgf=sgf,
            points=self.points,
            centroid=self.centroid,
            matrix=self.matrix,
            ring_key=self.ring_key,
            map_pose=self.pose,
            ground_truth=self.ground_truth,
        )


@dataclass(frozen=True)
class MapGroup:
    """An SGF group of the map: its members and whether it is symmetric (never a loop factor)."""

    group_id: int
    symmetric: bool
    views: tuple[MapView, ...]


@dataclass(frozen=True)
class SgfMap:
    """The SGF groups of a run in its optimized map frame, with the calibration they were made with."""

    groups: tuple[MapGroup, ...]
    calibration: Calibration | None = None
    sequence: str = ""
    created: str = ""
    map_id: str = ""

    @property
    def views(self) -> list[MapView]:
        """Every view of every group, in group order."""
        return [v for g in self.groups for v in g.views]

    @property
    def frame_poses(self) -> dict[int, np.ndarray]:
        """The map-frame pose of every frame that a view was selected on."""
        return {v.frame_index: v.pose for v in self.views}

    def descriptors(self) -> list[MapDescriptor]:
        """Every view as a :class:`MapDescriptor` (what the association seeds its prior groups with)."""
        return [v.descriptor() for v in self.views]

    def check_calibration(self, calibration: Calibration | None, tolerance: float = 1e-6) -> None:
        """Refuse a run whose camera calibration differs from the map's, naming what differs."""
        if calibration is None or self.calibration is None:
            return
        problems = []
        a, b = self.calibration.intrinsics, calibration.intrinsics
        for name in ("fx", "fy", "cx", "cy", "width", "height"):
            va, vb = float(getattr(a, name)), float(getattr(b, name))
            if abs(va - vb) > tolerance * max(1.0, abs(va)):
                problems.append(f"intrinsics.{name}: map {va:g}, run {vb:g}")
        diff = np.abs(self.calibration.camera_to_base_matrix - calibration.camera_to_base_matrix).max()
        if diff > tolerance:
            problems.append(f"camera_to_base differs by up to {diff:.3g}")
        if self.calibration.distortion != calibration.distortion:
            problems.append("distortion differs")
        if problems:
            raise DataError(
                f"the SGF map of {self.sequence or 'another run'} was made with another camera calibration "
                f"({'; '.join(problems)}); build a map with this robot's calibration, or localize a run of "
                "the robot the map was made with"
            )


def build_map(
    assignments: Iterable[GroupAssignment],
    poses: Mapping[int, np.ndarray],
    calibration: Calibration | None = None,
    sequence: str = "",
    ground_truth: Mapping[int, np.ndarray] | None = None,
    group_of: Mapping[tuple[int, int], int] | None = None,
) -> SgfMap:
    """The map of a run: its group assignments (the SGF of each) seen from the optimized ``poses``.

    ``group_of`` maps an SGF's ``(frame_index, track_id)`` to its final group where the association
    regrouped it after assigning it (a group split at the end of the run).
    """
    members: dict[int, list[MapView]] = {}
    symmetric: dict[int, bool] = {}
    for a in assignments:
        d = a.descriptor
        if isinstance(d, MapDescriptor):
            continue
        frame = d.sgf.frame_index
        group_id = a.group_id if group_of is None else group_of.get((frame, d.sgf.track_id), a.group_id)
        if frame not in poses:
            raise DataError(f"no optimized pose for frame {frame} (SGF of group {group_id}); cannot build the map")
        gt = None if ground_truth is None else ground_truth.get(frame)
        members.setdefault(group_id, []).append(
            MapView(
                group_id=group_id,
                frame_index=frame,
                timestamp=d.sgf.timestamp,
                pose=np.asarray(poses[frame], dtype=np.float64),
                points=np.asarray(d.points, dtype=np.float64).reshape(-1, 2),
                centroid=np.asarray(d.centroid, dtype=np.float64).reshape(2),
                matrix=np.asarray(d.matrix, dtype=np.float64),
                ring_key=np.asarray(d.ring_key, dtype=np.float64).reshape(-1),
                grid=d.sgf.grid,
                track_id=d.sgf.track_id,
                instance_id=d.sgf.instance_id,
                ground_truth=None if gt is None else np.asarray(gt, dtype=np.float64),
                hu=np.asarray(d.sgf.hu, dtype=np.float64).reshape(-1),
                saliency=float(d.sgf.saliency),
                views=int(d.sgf.views),
            )
        )
        symmetric[group_id] = symmetric.get(group_id, False) or a.symmetric
    groups = tuple(MapGroup(gid, symmetric[gid], tuple(views)) for gid, views in sorted(members.items()))
    return SgfMap(groups=groups, calibration=calibration, sequence=sequence)


def _tensors(sgf_map: SgfMap) -> dict[str, np.ndarray]:
    """The map's arrays, as stored in the file."""
    views = sgf_map.views
    if not views:
        raise DataError("the SGF map has no views; nothing to save")
    shape = views[0].matrix.shape
    for v in views:
        if v.matrix.shape != shape:
            raise DataError(f"descriptors of different shapes in one map: {shape} and {v.matrix.shape}")
    counts = np.array([len(v.points) for v in views], dtype=np.int64)
    eye = np.eye(4)
    return {
        "view_group": np.array([v.group_id for v in views], dtype=np.int64),
        "view_frame": np.array([v.frame_index for v in views], dtype=np.int64),
        "view_track": np.array([v.track_id for v in views], dtype=np.int64),
        "view_instance": np.array([-1 if v.instance_id is None else v.instance_id for v in views], dtype=np.int64),
        "view_timestamp": np.array([v.timestamp for v in views], dtype=np.float64),
        "view_pose": np.stack([v.pose for v in views]).astype(np.float64),
        "view_ground_truth": np.stack([eye if v.ground_truth is None else v.ground_truth for v in views]),
        "view_has_ground_truth": np.array([v.ground_truth is not None for v in views], dtype=np.uint8),
        "view_centroid": np.stack([v.centroid for v in views]).astype(np.float64),
        "view_matrix": np.stack([v.matrix for v in views]).astype(np.float64),
        "view_ring_key": np.stack([v.ring_key for v in views]).astype(np.float64),
        "view_grid": np.array(
            [[v.grid.resolution, v.grid.x_min, v.grid.x_max, v.grid.y_min, v.grid.y_max] for v in views],
            dtype=np.float64,
        ),
        "view_hu": np.stack([np.resize(v.hu, 7) for v in views]).astype(np.float64),
        "view_saliency": np.array([v.saliency for v in views], dtype=np.float64),
        "view_views": np.array([v.views for v in views], dtype=np.int64),
        "view_point_offset": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "points": np.concatenate([v.points for v in views]).astype(np.float64).reshape(-1, 2),
        "group_id": np.array([g.group_id for g in sgf_map.groups], dtype=np.int64),
        "group_symmetric": np.array([g.symmetric for g in sgf_map.groups], dtype=np.uint8),
    }


def _digest(tensors: Mapping[str, np.ndarray]) -> str:
    """SHA-256 over the tensors' names, dtypes, shapes and bytes."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        arr = np.ascontiguousarray(tensors[name])
        h.update(f"{name}:{arr.dtype.str}:{arr.shape}".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def save_map(path: str | os.PathLike[str], sgf_map: SgfMap) -> str:
    """Write the map atomically as one safetensors file; returns its id (the SHA-256 of its tensors)."""
    from safetensors.numpy import save

    from sgf_pipeline.folder_format import calibration_to_dict

    tensors = {k: np.ascontiguousarray(v) for k, v in _tensors(sgf_map).items()}
    digest = _digest(tensors)
    header = {
        "sequence": sgf_map.sequence,
        "created": sgf_map.created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "sha256": digest,
        "calibration": None if sgf_map.calibration is None else calibration_to_dict(sgf_map.calibration),
        "groups": len(sgf_map.groups),
        "views": len(sgf_map.views),
        "descriptor_shape": list(sgf_map.views[0].matrix.shape),
    }
    metadata = {"format": FORMAT, "version": str(VERSION), "header": json.dumps(header)}
    atomic_write_bytes(path, save(tensors, metadata=metadata))
    return digest


def _read(path: Path) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    """The metadata and tensors of a safetensors file, with a clear error when it is not one."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="np") as fh:
            metadata = dict(fh.metadata() or {})
            tensors = {name: fh.get_tensor(name) for name in fh.keys()}  # noqa: SIM118 (safe_open is not a dict)
    except Exception as exc:
        raise DataError(f"{path} is not a readable SGF map (corrupt or not a safetensors file): {exc}") from None
    return metadata, tensors


def _check_tensors(path: Path, tensors: dict[str, np.ndarray]) -> None:
    """Refuse missing tensors and inconsistent shapes."""
    required = (*_VIEW_TENSORS, "view_point_offset", "points", "group_id", "group_symmetric")
    missing = [n for n in required if n not in tensors]
    if missing:
        raise DataError(f"{path}: SGF map lacks tensor(s) {missing}")
    n = len(tensors["view_group"])
    for name in _VIEW_TENSORS:
        if tensors[name].shape[:1] != (n,):
            raise DataError(f"{path}: tensor {name} has {tensors[name].shape[:1]} rows for {n} views")
    expected = {
        "view_pose": (n, 4, 4),
        "view_ground_truth": (n, 4, 4),
        "view_centroid": (n, 2),
        "view_grid": (n, 5),
        "view_hu": (n, 7),
        "view_point_offset": (n + 1,),
    }
    for name, shape in expected.items():
        if tensors[name].shape != shape:
            raise DataError(f"{path}: tensor {name} has shape {tensors[name].shape}, expected {shape}")
    if tensors["view_matrix"].ndim != 3 or tensors["view_ring_key"].shape != (n, tensors["view_matrix"].shape[1]):
        raise DataError(f"{path}: descriptor tensors have inconsistent shapes")
    offsets, points = tensors["view_point_offset"], tensors["points"]
    if points.ndim != 2 or points.shape[1] != 2:
        raise DataError(f"{path}: tensor points has shape {points.shape}, expected (P, 2)")
    if offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != len(points):
        raise DataError(f"{path}: view_point_offset does not partition the {len(points)} points")
    for name, arr in tensors.items():
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise DataError(f"{path}: tensor {name} holds non-finite values")
    rot = tensors["view_pose"][:, :3, :3]
    if n and not np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-6):
        raise DataError(f"{path}: a view pose is not a rigid transform")
    unknown = set(tensors["view_group"].tolist()) - set(tensors["group_id"].tolist())
    if unknown:
        raise DataError(f"{path}: views refer to group(s) {sorted(unknown)[:5]} that the map does not list")


def load_map(path: str | os.PathLike[str], calibration: Calibration | None = None) -> SgfMap:
    """Read and validate an SGF map; with ``calibration``, refuse a map made with another camera."""
    p = Path(path)
    if not p.is_file():
        raise DataError(f"SGF map not found: {p} (a run writes sgf_map.safetensors into its output directory)")
    metadata, tensors = _read(p)
    if metadata.get("format") != FORMAT:
        raise DataError(f"{p} is not an SGF map (format {metadata.get('format')!r}, expected {FORMAT!r})")
    if metadata.get("version") != str(VERSION):
        raise DataError(
            f"{p} is an SGF map of version {metadata.get('version')!r}; this sgf-pipeline reads version {VERSION}. "
            "Rebuild the map with this version (run the mapping sequence again)"
        )
    try:
        header: dict[str, Any] = json.loads(metadata["header"])
    except (KeyError, json.JSONDecodeError) as exc:
        raise DataError(f"{p}: the SGF map header is missing or not JSON: {exc}") from None
    _check_tensors(p, tensors)
    digest = _digest(tensors)
    if header.get("sha256") != digest:
        raise DataError(f"{p}: the SGF map is corrupt (its tensors do not match the checksum in its header)")
    map_calibration = None
    if header.get("calibration") is not None:
        try:
            map_calibration = Calibration.model_validate(header["calibration"])
        except Exception as exc:
            raise DataError(f"{p}: the SGF map's calibration is invalid: {exc}") from None
    symmetric = dict(zip(tensors["group_id"].tolist(), tensors["group_symmetric"].astype(bool).tolist(), strict=True))
    members: dict[int, list[MapView]] = {gid: [] for gid in symmetric}
    offsets = tensors["view_point_offset"]
    for k in range(len(tensors["view_group"])):
        grid = tensors["view_grid"][k]
        instance = int(tensors["view_instance"][k])
        view = MapView(
            group_id=int(tensors["view_group"][k]),
            frame_index=int(tensors["view_frame"][k]),
            timestamp=float(tensors["view_timestamp"][k]),
            pose=tensors["view_pose"][k].copy(),
            points=tensors["points"][offsets[k] : offsets[k + 1]].copy(),
            centroid=tensors["view_centroid"][k].copy(),
            matrix=tensors["view_matrix"][k].copy(),
            ring_key=tensors["view_ring_key"][k].copy(),
            grid=BevGrid(*(float(x) for x in grid)),
            track_id=int(tensors["view_track"][k]),
            instance_id=None if instance < 0 else instance,
            ground_truth=tensors["view_ground_truth"][k].copy() if tensors["view_has_ground_truth"][k] else None,
            hu=tensors["view_hu"][k].copy(),
            saliency=float(tensors["view_saliency"][k]),
            views=int(tensors["view_views"][k]),
        )
        members[view.group_id].append(view)
    groups = tuple(MapGroup(gid, symmetric[gid], tuple(views)) for gid, views in members.items())
    sgf_map = SgfMap(
        groups=groups,
        calibration=map_calibration,
        sequence=str(header.get("sequence", "")),
        created=str(header.get("created", "")),
        map_id=digest,
    )
    sgf_map.check_calibration(calibration)
    return sgf_map
