"""Property-based and hand-made garbage for every file reader: a clear error naming the file (and line), never a crash.

Trajectories (TUM, KITTI, EuRoC CSV, KITTI times), calibrations (folder YAML, KITTI calib.txt,
EuRoC sensor.yaml, ROS CameraInfo fields, image headers) and the folder format's truth.json.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.calibration_io import (
    calibration_from_camera_info,
    image_size,
    read_euroc_sensor_yaml,
    read_kitti_calib,
)
from sgf_pipeline.errors import DataError
from sgf_pipeline.folder_format import read_calibration_yaml, read_truth_json, truth_from_dict
from sgf_pipeline.geometry import pose_from_xyz_rpy
from sgf_pipeline.trajectory import (
    Trajectory,
    TrajectoryError,
    read_euroc_csv,
    read_kitti,
    read_times,
    read_trajectory,
    write_trajectory,
)
from sgf_pipeline.truth import SequenceTruth

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# -- strategies -------------------------------------------------------------------------------

TOKENS = st.sampled_from(
    ["0", "1", "-1", "0.5", "1e-320", "1e20", "1e999", "-inf", "nan", "NaN", "18446744073709551616", "abc", "0x1f", ""]
)
NUMBERS = st.one_of(TOKENS, st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers().map(str))


def _line(separator: str) -> st.SearchStrategy[str]:
    return st.lists(NUMBERS, min_size=0, max_size=14).map(separator.join)


TEXT = st.one_of(
    st.lists(st.one_of(_line(" "), _line(","), _line("\t"), st.just("# comment")), max_size=8).map("\n".join),
    st.text(max_size=300),
)
BYTES = st.one_of(TEXT.map(lambda t: t.encode("utf-8", "surrogatepass")), st.binary(max_size=300))


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def _expect_clear(error: Exception, path: Path, content: bytes) -> None:
    """The message names the file; a ``file:N:`` prefix points at a line that exists."""
    message = str(error)
    assert str(path) in message, message
    found = re.search(re.escape(str(path)) + r":(\d+):", message)
    if found:
        assert 1 <= int(found.group(1)) <= content.count(b"\n") + 1, message


def _check_trajectory(trajectory: Trajectory) -> None:
    """What every trajectory a reader returns satisfies."""
    assert len(trajectory) >= 1
    assert np.all(np.isfinite(trajectory.poses)) and np.all(np.isfinite(trajectory.timestamps))
    assert np.all(np.diff(trajectory.timestamps) > 0)
    rotations = trajectory.poses[:, :3, :3]
    assert np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=2e-3)


# -- trajectories -----------------------------------------------------------------------------


@FUZZ
@given(content=BYTES, name=st.sampled_from(["t.tum", "t.kitti", "t.csv", "t.txt"]))
def test_any_trajectory_file_gives_a_trajectory_or_a_trajectory_error(work: Path, content: bytes, name: str):
    path = work / name
    path.write_bytes(content)
    for read in (lambda: read_trajectory(path), lambda: read_times(path)):
        try:
            result = read()
        except TrajectoryError as exc:
            _expect_clear(exc, path, content)
        else:
            if isinstance(result, Trajectory):
                _check_trajectory(result)
            else:
                assert np.all(np.isfinite(result)) and np.all(np.diff(result) > 0)


@FUZZ
@given(
    content=st.lists(_line(","), min_size=1, max_size=6).map("\n".join),
    duplicates=st.sampled_from(["error", "drop"]),
)
def test_any_euroc_csv_gives_a_trajectory_or_a_trajectory_error(work: Path, content: str, duplicates: str):
    path = work / "data.csv"
    path.write_text(content)
    try:
        _check_trajectory(read_euroc_csv(path, duplicates))  # type: ignore[arg-type]
    except TrajectoryError as exc:
        _expect_clear(exc, path, content.encode())


unit_quaternions = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)


@FUZZ
@given(
    start=st.floats(0.0, 2e9),
    steps=st.lists(st.floats(1e-3, 10.0), min_size=1, max_size=12),
    positions=st.lists(st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3), min_size=13, max_size=13),
    quaternions=st.lists(unit_quaternions, min_size=13, max_size=13),
    fmt=st.sampled_from(["tum", "kitti", "euroc"]),
)
def test_written_trajectories_read_back(work: Path, start, steps, positions, quaternions, fmt):
    from sgf_pipeline.geometry import rotation_from_quaternion

    stamps = start + np.concatenate([[0.0], np.cumsum(steps)])
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    for i in range(len(stamps)):
        poses[i, :3, :3] = rotation_from_quaternion(np.asarray(quaternions[i]))
        poses[i, :3, 3] = positions[i]
    trajectory = Trajectory(stamps, poses)
    path, times = work / f"round.{fmt}", work / "round_times.txt"
    write_trajectory(path, trajectory, fmt, times if fmt == "kitti" else None)
    back = read_trajectory(path, fmt, times if fmt == "kitti" else None)
    np.testing.assert_allclose(back.poses, trajectory.poses, atol=1e-7)
    np.testing.assert_allclose(back.timestamps, trajectory.timestamps, atol=2e-6 * max(1.0, start / 1e9))


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("a.tum", b"0 0 0 0 0 0 0 1\n\xff\xfe 1 2\n", r"a.tum:2: not a text file"),
        ("b.csv", b"#t\n\x89PNG\r\n", r"b.csv:2: not a text file"),
        ("c.csv", b"1e30,0,0,0,1,0,0,0\n", r"c.csv:1: timestamp '1e30' ns is out of range"),
        ("d.csv", b"inf,0,0,0,1,0,0,0\n", r"d.csv:1: timestamp 'inf' is not a finite time in ns"),
        ("e.csv", b"99999999999999999999,0,0,0,1,0,0,0\n", r"e.csv:1: timestamp .* ns is out of range"),
        ("f.tum", b"0 0 0 0 0 0 0 0\n", r"f.tum:1: non-finite pose \(NaN or inf\) or zero-length quaternion"),
        ("g.tum", b"0 0 0 0 1e200 1e200 1e200 1e200\n", r"g.tum:1: .*zero-length quaternion"),
        ("h.tum", b"0 0 0 0 0 0 0 1\n1 inf 0 0 0 0 0 1\n", r"h.tum:2: non-finite pose"),
        ("i.kitti", b"1 1 1 0 1 1 1 0 1 1 1 0\n", r"i.kitti:1: the pose's 3x3 block is not a rotation"),
        ("j.kitti", b"1 0 0 0 0 1 0 0 0 0 -1 0\n", r"j.kitti:1: .*not a rotation .*det R = -1"),
        ("k.kitti", b"1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", r"k.kitti:2: a KITTI pose .* got 11"),
        # line numbers count newlines only: Python's splitlines() also breaks at \x1c-\x1e, \x85, \u2028
        ("l.tum", b"0 0 0 0 0 0 0 1\x1e\n1 2\n", r"l.tum:2: a TUM .* got 2"),
        ("m.tum", b"0 0 0 0 0 0 0 1\r\n1 0 0 0 0 0 0 1\r1 2\n", r"m.tum:2: a TUM .* got 10"),
    ],
)
def test_hand_made_bad_trajectories(tmp_path: Path, name: str, content: bytes, message: str):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(TrajectoryError, match=message):
        read_trajectory(path)


def test_kitti_rotations_of_real_files_pass_the_rotation_check(shared_data: Path):
    for name in ("KITTI_00_gt.txt", "KITTI_00_ORB.txt"):
        assert len(read_kitti(shared_data / "evo" / name)) == 4541


def test_a_trajectory_that_cannot_be_read_names_the_reason(tmp_path: Path):
    folder = tmp_path / "a.tum"
    folder.mkdir()
    with pytest.raises(TrajectoryError, match=r"TUM .* file not found: .*a.tum"):
        read_trajectory(folder)


# -- calibrations -----------------------------------------------------------------------------

SCALAR = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-5, 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.sampled_from(["pinhole", "radtan", "equidistant", "plumb_bob", "omni", "none"]),
)
VALUE = st.recursive(
    SCALAR,
    lambda inner: st.one_of(
        st.lists(inner, max_size=17), st.dictionaries(st.sampled_from(["rows", "cols", "data", "x"]), inner, max_size=3)
    ),
    max_leaves=24,
)
EUROC_KEYS = [
    "intrinsics",
    "resolution",
    "camera_model",
    "distortion_model",
    "distortion_coefficients",
    "T_BS",
    "rate_hz",
]
GOOD_EUROC = {"intrinsics": [300.0, 300.0, 160.0, 120.0], "resolution": [320, 240], "camera_model": "pinhole"}


@FUZZ
@given(fields=st.fixed_dictionaries({}, optional=dict.fromkeys(EUROC_KEYS, VALUE)))
def test_any_euroc_sensor_yaml_gives_a_camera_or_a_data_error(work: Path, fields: dict):
    path = work / "sensor.yaml"
    path.write_text(yaml.safe_dump({**GOOD_EUROC, **fields}))
    try:
        camera = read_euroc_sensor_yaml(path)
    except DataError as exc:
        assert str(path) in str(exc)
    else:
        assert np.all(np.isfinite(camera.camera_to_body)) and camera.camera_to_body.shape == (4, 4)
        assert camera.intrinsics.fx > 0 and camera.intrinsics.width > 0
        assert camera.rate_hz is None or (math.isfinite(camera.rate_hz) and camera.rate_hz > 0)
        assert all(math.isfinite(c) for c in camera.distortion.coefficients)


@FUZZ
@given(fields=st.fixed_dictionaries({}, optional=dict.fromkeys(["intrinsics", "distortion", "camera_to_base"], VALUE)))
def test_any_calibration_yaml_gives_a_calibration_or_a_data_error(work: Path, fields: dict):
    path = work / "calibration.yaml"
    path.write_text(yaml.safe_dump(fields))
    try:
        calibration = read_calibration_yaml(path)
    except DataError as exc:
        assert str(path) in str(exc)
    else:
        assert isinstance(calibration, Calibration) and np.isfinite(calibration.height)


@FUZZ
@given(content=BYTES)
def test_any_kitti_calib_gives_matrices_or_a_data_error(work: Path, content: bytes):
    path = work / "calib.txt"
    path.write_bytes(b"P0: " + content)
    try:
        matrices = read_kitti_calib(path)
    except DataError as exc:
        _expect_clear(exc, path, content)
    else:
        assert matrices and all(m.shape == (3, 4) and np.all(np.isfinite(m)) for m in matrices.values())


@FUZZ
@given(
    width=st.integers(-2, 5000),
    height=st.integers(-2, 5000),
    k=st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=12),
    d=st.one_of(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=9), st.text(max_size=4)),
    model=st.sampled_from(["plumb_bob", "rational_polynomial", "equidistant", "", "double_sphere", "PINHOLE"]),
    translation=st.floats(allow_nan=True, allow_infinity=True),
)
def test_any_camera_info_gives_a_calibration_or_a_data_error(width, height, k, d, model, translation):
    mount = pose_from_xyz_rpy(0.1, 0.0, 0.8, 0.0, 0.3, 0.0)
    mount[2, 3] = translation
    try:
        calibration = calibration_from_camera_info(width, height, k, d, model, mount, "/camera/camera_info")
    except DataError as exc:
        assert str(exc).startswith("/camera/camera_info: ")
    else:
        assert calibration.intrinsics.width == width and np.isfinite(calibration.camera_to_base_matrix).all()


@FUZZ
@given(
    magic=st.sampled_from([b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", b"\xff\xd8", b"\xff\xd8\xff\xc0\x00\x11\x08", b""]),
    tail=st.binary(max_size=40),
)
def test_any_image_header_gives_a_size_or_a_data_error(work: Path, magic: bytes, tail: bytes):
    path = work / "frame.png"
    path.write_bytes(magic + tail)
    try:
        width, height = image_size(path)
    except DataError as exc:
        assert str(path) in str(exc)
    else:
        assert width > 0 and height > 0


@pytest.mark.parametrize(
    ("reader", "content", "message"),
    [
        (read_calibration_yaml, b"intrinsics: \xff\xfe\n", r"calibration.yaml:1: not a text file"),
        (read_calibration_yaml, b"intrinsics: [1, 2\n", r"calibration.yaml:\d+: not valid YAML"),
        (read_calibration_yaml, b"[" * 5000 + b"]" * 5000, r"not valid YAML: nested too deeply"),
        (read_calibration_yaml, b"!!python/object/apply:os.system ['true']\n", r"not valid YAML: could not determine"),
        (
            read_calibration_yaml,
            b"intrinsics: {fx: 1, fy: 1, cx: .nan, cy: 0, width: 4, height: 4}\ncamera_to_base: []\n",
            r"intrinsics.cx\n.*finite number",
        ),
        (read_euroc_sensor_yaml, b"\x00\xff", r"sensor.yaml:1: not a text file"),
        (
            read_euroc_sensor_yaml,
            b"intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\nT_BS: {rows: 3, cols: 4, data: []}\n",
            r"T_BS must be a finite 4x4 matrix",
        ),
        (
            read_euroc_sensor_yaml,
            b"intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\nrate_hz: fast\n",
            r"rate_hz must be a positive number",
        ),
        (
            read_euroc_sensor_yaml,
            b"intrinsics: [1, 1, 1]\nresolution: [4, 4]\n",
            r"intrinsics must be a list of 4 numbers",
        ),
        (read_euroc_sensor_yaml, b"intrinsics: [1, 1, 1, 1]\nresolution: [4.5, 4]\n", r"resolution must hold whole"),
        (
            read_euroc_sensor_yaml,
            b"intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\ndistortion_model: radtan\ndistortion_coefficients: abc\n",
            r"distortion coefficients must be a list of numbers",
        ),
        (read_kitti_calib, b"P0: 1 0 nan 0 0 1 0 0 0 0 1 0\n", r"calib.txt:1: P0 holds a non-finite number"),
        (read_kitti_calib, b"\x89PNG\r\n\x1a\n", r"calib.txt:1: not a text file"),
    ],
)
def test_hand_made_bad_calibrations(tmp_path: Path, reader, content: bytes, message: str):
    name = {read_calibration_yaml: "calibration.yaml", read_euroc_sensor_yaml: "sensor.yaml"}.get(reader, "calib.txt")
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(DataError, match=re.compile(message, re.DOTALL)):
        reader(path)


def test_image_headers_cut_short_or_of_size_zero(tmp_path: Path):
    import struct

    path = tmp_path / "x.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00")  # cut inside the size
    with pytest.raises(DataError, match=r"x.png: not an image that can be read"):
        image_size(path)
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + struct.pack(">II", 0, 0) + b"\x08\x02\x00\x00\x00")
    with pytest.raises(DataError, match=r"x.png: the image header gives a size of 0x0 px"):
        image_size(path)
    path.write_bytes(b"\xff\xd8\xff\xc0\x00\x11\x08\x00")  # a JPEG frame header cut short
    with pytest.raises(DataError, match=r"not an image that can be read"):
        image_size(path)


def test_camera_info_with_a_pose_that_is_not_rigid():
    mount = np.eye(4)
    mount[:3, :3] *= 2.0
    k = [400.0, 0.0, 320.0, 0.0, 400.0, 240.0, 0.0, 0.0, 1.0]
    with pytest.raises(DataError, match=r"/cam/info: camera_to_base must be a rigid transform"):
        calibration_from_camera_info(640, 480, k, [], "plumb_bob", mount, "/cam/info")
    with pytest.raises(DataError, match=r"/cam/info: K must hold 9 numbers, got \['a'"):
        calibration_from_camera_info(640, 480, ["a"] * 9, [], "plumb_bob", np.eye(4), "/cam/info")  # type: ignore[list-item]


# -- truth.json -------------------------------------------------------------------------------

MARKING = st.fixed_dictionaries(
    {},
    optional={
        "instance_id": st.one_of(st.integers(-2, 4), VALUE),
        "design": st.one_of(st.just("arrow"), VALUE),
        "category": st.sampled_from(["standard", "custom", "other"]),
        "symmetric": st.one_of(st.booleans(), VALUE),
        "pose": st.one_of(st.lists(st.floats(allow_nan=True), min_size=3, max_size=3), VALUE),
        "size": st.one_of(st.lists(st.floats(-1, 5), min_size=2, max_size=2), VALUE),
    },
)
PASS = st.fixed_dictionaries(
    {},
    optional={
        "instance_id": st.one_of(st.integers(-1, 4), VALUE),
        "number": st.one_of(st.integers(-1, 3), VALUE),
        "start_frame": st.integers(-2, 50),
        "end_frame": st.integers(-2, 50),
        "heading": st.one_of(st.floats(allow_nan=True), VALUE),
    },
)
REVISIT = st.fixed_dictionaries(
    {},
    optional={k: st.one_of(st.integers(-1, 4), VALUE) for k in ("instance_id", "first", "second", "reverse")},
)
TRUTH = st.one_of(
    VALUE,
    st.fixed_dictionaries(
        {},
        optional={
            "markings": st.one_of(st.lists(MARKING, max_size=3), VALUE),
            "passes": st.one_of(st.lists(PASS, max_size=3), VALUE),
            "revisits": st.one_of(st.lists(REVISIT, max_size=2), VALUE),
        },
    ),
)


@settings(max_examples=400, deadline=None)
@given(data=TRUTH)
def test_any_truth_data_gives_a_checked_truth_or_a_data_error(data):
    try:
        truth = truth_from_dict(data, "truth.json")
    except DataError as exc:
        assert str(exc).startswith("truth.json")
    else:
        assert isinstance(truth, SequenceTruth)
        for marking in truth.markings.values():
            assert marking.instance_id >= 1 and marking.category in ("standard", "custom")
            assert all(math.isfinite(v) for v in (*marking.pose, *marking.size))
        for p in truth.passes:
            assert p.instance_id in truth.markings and 0 <= p.start_frame <= p.end_frame
        for r in truth.revisits:
            assert r.first in truth.passes and r.second in truth.passes


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ("[1, 2]", r"truth.json: must be a mapping with markings, passes and revisits, got list"),
        ('{"markings": {}}', r"truth.json markings: must be a list, got dict"),
        ('{"marks": []}', r"unknown key\(s\) \['marks'\]"),
        (
            '{"markings": [{"instance_id": 1, "design": "a", "category": "standard", "symmetric": false, '
            '"pose": [0, NaN, 0], "size": [1, 1]}]}',
            r"markings\[0\].pose\[1\]: must be a finite number, got nan",
        ),
        (
            '{"markings": [{"instance_id": true, "design": "a", "category": "standard", "symmetric": false, '
            '"pose": [0, 0, 0], "size": [1, 1]}]}',
            r"markings\[0\].instance_id: must be an integer >= 1, got True",
        ),
        (
            '{"passes": [{"instance_id": 3, "number": 0, "start_frame": 0, "end_frame": 5, "heading": 0}]}',
            r"passes\[0\].instance_id: marking 3 is not in markings",
        ),
        ('{"markings": [{"instance_id": 1}]}', r"markings\[0\]: missing \['category', 'design'"),
        ("{", r"truth.json:1: not valid JSON"),
        ("[" * 100_000, r"not valid JSON: nested too deeply"),
    ],
)
def test_hand_made_bad_truth_files(tmp_path: Path, data: str, message: str):
    path = tmp_path / "truth.json"
    path.write_text(data)
    with pytest.raises(DataError, match=message):
        read_truth_json(path)


def test_truth_written_by_the_project_reads_back(tmp_path: Path):
    from sgf_pipeline.folder_format import truth_to_dict
    from sgf_pipeline.truth import MarkingPass, MarkingTruth, RevisitPair

    a = MarkingPass(1, 0, 3, 9, 0.1)
    b = MarkingPass(1, 1, 40, 48, 3.1)
    truth = SequenceTruth(
        markings={1: MarkingTruth(1, "arrow", "standard", False, (1.0, 2.0, 0.5), (1.6, 0.6))},
        passes=[a, b],
        revisits=[RevisitPair(1, a, b, True)],
    )
    (tmp_path / "truth.json").write_text(json.dumps(truth_to_dict(truth)))
    back = read_truth_json(tmp_path / "truth.json")
    assert back.markings == truth.markings and back.passes == truth.passes
    assert back.revisits == truth.revisits
