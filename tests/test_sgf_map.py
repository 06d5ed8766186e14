"""The SGF map format: round trip, MapDescriptor, and clear errors for bad files."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
from backend_world import CALIBRATION, OracleAssociation, make_world

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.errors import DataError
from sgf_pipeline.sgf_map import FORMAT, MapDescriptor, SgfMap, build_map, load_map, save_map
from sgf_pipeline.types import GroupAssignment


@pytest.fixture(scope="module")
def run() -> tuple[list[GroupAssignment], dict[int, np.ndarray], dict[int, np.ndarray]]:
    world = make_world(seed=3, laps=1.0, reverse_lap=True)
    assoc = OracleAssociation(world)
    assignments = [a for f in world.frames for a in (assoc.assign(f) or _empty()).items]
    poses = {f.index: f.odometry for f in world.frames}
    gt = {f.index: f.ground_truth for f in world.frames if f.ground_truth is not None}
    return assignments, poses, gt


def _empty():  # type: ignore[no-untyped-def]
    from sgf_pipeline.types import GroupAssignments

    return GroupAssignments()


@pytest.fixture()
def saved(tmp_path: Path, run) -> tuple[Path, SgfMap]:  # type: ignore[no-untyped-def]
    assignments, poses, gt = run
    sgf_map = build_map(assignments, poses, calibration=CALIBRATION, sequence="toy", ground_truth=gt)
    path = tmp_path / "sgf_map.safetensors"
    save_map(path, sgf_map)
    return path, sgf_map


def test_round_trip_keeps_groups_views_points_and_poses(saved, run) -> None:  # type: ignore[no-untyped-def]
    path, built = saved
    assignments, poses, _ = run
    loaded = load_map(path, calibration=CALIBRATION)
    assert loaded.sequence == "toy"
    assert len(loaded.map_id) == 64
    assert [g.group_id for g in loaded.groups] == [g.group_id for g in built.groups]
    assert [g.symmetric for g in loaded.groups] == [g.symmetric for g in built.groups]
    assert any(g.symmetric for g in loaded.groups)  # the manhole's group
    assert len(loaded.views) == len(assignments) == len(built.views)
    for a, b in zip(built.views, loaded.views, strict=True):
        assert (a.group_id, a.frame_index, a.instance_id) == (b.group_id, b.frame_index, b.instance_id)
        assert a.track_id == b.track_id
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.matrix, b.matrix)
        np.testing.assert_array_equal(a.pose, poses[a.frame_index])
        np.testing.assert_array_equal(b.pose, poses[a.frame_index])
        assert b.ground_truth is not None
        assert b.grid == a.grid
    assert loaded.calibration == CALIBRATION


def test_views_become_map_descriptors_at_their_map_poses(saved) -> None:  # type: ignore[no-untyped-def]
    path, _ = saved
    loaded = load_map(path)
    descriptors = loaded.descriptors()
    assert all(isinstance(d, MapDescriptor) for d in descriptors)
    d = descriptors[0]
    view = loaded.views[0]
    assert d.sgf.frame_index == view.frame_index
    np.testing.assert_array_equal(d.map_pose, view.pose)
    np.testing.assert_array_equal(d.sgf.odometry, view.pose)
    np.testing.assert_array_equal(d.points, view.points)
    assert loaded.frame_poses[view.frame_index] is view.pose


def test_a_missing_map_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="SGF map not found"):
        load_map(tmp_path / "nope.safetensors")


def test_a_file_that_is_not_safetensors_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "map.safetensors"
    path.write_bytes(b"\x00garbage that is not a map")
    with pytest.raises(DataError, match="not a readable SGF map"):
        load_map(path)


def test_a_truncated_map_is_refused(saved) -> None:  # type: ignore[no-untyped-def]
    path, _ = saved
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])
    with pytest.raises(DataError, match="not a readable SGF map"):
        load_map(path)


def test_a_flipped_byte_is_caught_by_the_checksum(saved) -> None:  # type: ignore[no-untyped-def]
    path, _ = saved
    data = bytearray(path.read_bytes())
    data[-9] ^= 0x40  # inside the last tensor's bytes
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"corrupt \(its tensors do not match the checksum"):
        load_map(path)


def _rewrite_metadata(path: Path, **changes: str) -> None:
    """Rewrite a safetensors header's metadata in place (the tensor bytes are kept)."""
    data = path.read_bytes()
    (size,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + size])
    header["__metadata__"].update(changes)
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + data[8 + size :])


def test_another_format_is_refused(saved) -> None:  # type: ignore[no-untyped-def]
    path, _ = saved
    _rewrite_metadata(path, format="weights")
    with pytest.raises(DataError, match=f"not an SGF map .*expected '{FORMAT}'"):
        load_map(path)


def test_a_newer_version_is_refused_with_what_to_do(saved) -> None:  # type: ignore[no-untyped-def]
    path, _ = saved
    _rewrite_metadata(path, version="2")
    with pytest.raises(DataError, match="version '2'; this sgf-pipeline reads version 1"):
        load_map(path)


def test_a_map_of_another_camera_is_refused(saved) -> None:  # type: ignore[no-untyped-def]
    path, _ = saved
    other = Calibration.from_mounting(
        Intrinsics(fx=410.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480), height=0.8, tilt=0.35
    )
    with pytest.raises(DataError, match=r"another camera calibration \(intrinsics.fx: map 400, run 410\)"):
        load_map(path, calibration=other)
    lower = Calibration.from_mounting(CALIBRATION.intrinsics, height=0.7, tilt=math.radians(20))
    with pytest.raises(DataError, match="camera_to_base differs"):
        load_map(path, calibration=lower)


def test_build_map_needs_a_pose_for_every_view(run) -> None:  # type: ignore[no-untyped-def]
    assignments, poses, _ = run
    some = {k: v for k, v in poses.items() if k != assignments[0].descriptor.sgf.frame_index}
    with pytest.raises(DataError, match=f"no optimized pose for frame {assignments[0].descriptor.sgf.frame_index}"):
        build_map(assignments, some)


def test_build_map_puts_views_into_the_groups_the_association_regrouped_them_into(run) -> None:  # type: ignore[no-untyped-def]
    assignments, poses, _ = run
    plain = build_map(assignments, poses)
    big = max(plain.groups, key=lambda g: len(g.views))
    moved = big.views[-1]
    new_id = max(g.group_id for g in plain.groups) + 1
    regrouped = build_map(assignments, poses, group_of={(moved.frame_index, moved.track_id): new_id})
    by_id = {g.group_id: g for g in regrouped.groups}
    assert [(v.frame_index, v.group_id) for v in by_id[new_id].views] == [(moved.frame_index, new_id)]
    assert len(by_id[big.group_id].views) == len(big.views) - 1
    assert len(regrouped.views) == len(plain.views)


def test_an_empty_map_is_not_saved(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no views"):
        save_map(tmp_path / "m.safetensors", SgfMap(groups=()))
    assert not (tmp_path / "m.safetensors").exists()
