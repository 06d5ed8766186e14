"""TUM, KITTI and EuRoC CSV trajectories: round trips, evo reads what we write, clear errors on bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sgf_pipeline.geometry import pose_from_xyz_rpy
from sgf_pipeline.trajectory import (
    Trajectory,
    TrajectoryError,
    detect_format,
    read_euroc_csv,
    read_kitti,
    read_trajectory,
    read_tum,
    write_euroc_csv,
    write_kitti,
    write_trajectory,
)


def _trajectory(n: int = 20) -> Trajectory:
    ts = 1403636579.758555 + 0.05 * np.arange(n)
    poses = np.stack(
        [pose_from_xyz_rpy(0.3 * i, np.sin(i), 0.01 * i, 0.1 * np.cos(i), 0.05 * i, 0.2 * i) for i in range(n)]
    )
    return Trajectory(ts, poses)


@pytest.mark.parametrize("fmt", ["tum", "kitti", "euroc"])
def test_round_trip(tmp_path: Path, fmt: str):
    traj = _trajectory()
    path = tmp_path / f"traj.{ {'tum': 'tum', 'kitti': 'txt', 'euroc': 'csv'}[fmt] }"
    times = tmp_path / "times.txt" if fmt == "kitti" else None
    write_trajectory(path, traj, fmt, times)  # type: ignore[arg-type]
    assert detect_format(path) == fmt
    back = read_trajectory(path, "auto", times)
    np.testing.assert_allclose(back.poses, traj.poses, atol=2e-8)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)


def test_evo_reads_what_we_write(tmp_path: Path):
    from evo.tools import file_interface

    traj = _trajectory()
    write_trajectory(tmp_path / "t.tum", traj, "tum")
    write_kitti(tmp_path / "t.kitti", traj)
    write_euroc_csv(tmp_path / "t.csv", traj)
    tum = file_interface.read_tum_trajectory_file(tmp_path / "t.tum")
    kitti = file_interface.read_kitti_poses_file(tmp_path / "t.kitti")
    euroc = file_interface.read_euroc_csv_trajectory(tmp_path / "t.csv")
    for evo_traj in (tum, kitti, euroc):
        np.testing.assert_allclose(np.stack(evo_traj.poses_se3), traj.poses, atol=2e-8)
    np.testing.assert_allclose(tum.timestamps, traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(euroc.timestamps, traj.timestamps, atol=1e-6)


def test_reads_evo_test_files(shared_data: Path):
    evo = shared_data / "evo"
    kitti = read_kitti(evo / "KITTI_00_gt.txt")
    assert len(kitti) == 4541
    assert kitti.timestamps[:3].tolist() == [0.0, 1.0, 2.0]  # row numbers without a times file
    assert kitti.poses[1, 2, 3] == pytest.approx(0.8586941)
    tum = read_tum(evo / "freiburg1_xyz-rgbdslam.txt")
    assert tum.timestamps[0] == pytest.approx(1305031102.160407)
    assert tum.positions[0] == pytest.approx([1.344379, 0.627206, 1.661754])


def test_euroc_csv_with_velocity_and_bias_columns(tmp_path: Path):
    path = tmp_path / "data.csv"
    path.write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
        "v_RS_R_x [m s^-1], v_RS_R_y, v_RS_R_z, b_w_RS_S_x, b_w_RS_S_y, b_w_RS_S_z, "
        "b_a_RS_S_x, b_a_RS_S_y, b_a_RS_S_z\n"
        "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,"
        "-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
        "1403636580843555328,4.688177,-1.786770,0.787350,0.534640,-0.152990,-0.826976,-0.082863,"
        "-0.029272,0.033992,0.804771,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
    )
    traj = read_euroc_csv(path)
    assert traj.timestamps[0] == pytest.approx(1403636580.838555648, abs=1e-6)
    assert traj.timestamps[1] - traj.timestamps[0] == pytest.approx(0.004999680, abs=1e-7)
    q = np.array([-0.153029, -0.827383, -0.082152, 0.534108])
    from sgf_pipeline.geometry import rotation_from_quaternion

    np.testing.assert_allclose(traj.poses[0, :3, :3], rotation_from_quaternion(q), atol=1e-12)


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("a.tum", "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", r"a.tum:2: a TUM .* line has 8 fields, got 7"),
        (
            "b.tum",
            "0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n",
            r"b.tum:2: non-finite pose \(NaN or inf\) or zero-length quaternion on line\(s\) \[2\]",
        ),
        (
            "c.tum",
            "# c\n0 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n",
            r"c.tum:4: timestamp 1.0 is out of order",
        ),
        (
            "d.tum",
            "0 0 0 0 0 0 0 1\n0 0 0 0 0 0 0 1\n",
            r"d.tum:2: timestamp 0.0 is duplicated .*duplicates=drop .*duplicates=keep",
        ),
        ("e.txt", "1 0 0 0 0 1 0 0 0 0 1\n", r"e.txt: cannot tell the format from a line of 11 fields"),
        ("f.tum", "", r"f.tum: no poses"),
        ("g.csv", "#t,x\n1,2,3\n", r"g.csv:2: an EuRoC state line has at least 8 comma-separated fields"),
    ],
)
def test_bad_trajectory_files(tmp_path: Path, name: str, text: str, message: str):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=message):
        read_trajectory(path)


def test_kitti_times_must_match_and_duplicates_can_be_dropped(tmp_path: Path):
    traj = _trajectory(5)
    write_kitti(tmp_path / "p.txt", traj, tmp_path / "times.txt")
    (tmp_path / "short.txt").write_text("0\n1\n")
    with pytest.raises(TrajectoryError, match=r"has 5 poses but the times .* have 2"):
        read_kitti(tmp_path / "p.txt", tmp_path / "short.txt")
    with pytest.raises(TrajectoryError, match="not found"):
        read_trajectory(tmp_path / "missing.tum")
    dup = tmp_path / "dup.tum"
    dup.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n1 2 0 0 0 0 0 1\n2 3 0 0 0 0 0 1\n")
    kept = read_tum(dup, duplicates="drop")
    assert kept.timestamps.tolist() == [0.0, 1.0, 2.0]
    assert kept.positions[:, 0].tolist() == [0.0, 1.0, 3.0]  # the first of the equal stamps is kept
    every = read_trajectory(dup, duplicates="keep")  # evo's way: all of them, in file order
    assert every.timestamps.tolist() == [0.0, 1.0, 1.0, 2.0] and every.positions[:, 0].tolist() == [0, 1, 2, 3]
    assert every.repeated_stamps and not kept.repeated_stamps
    (tmp_path / "back.tum").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n0.5 2 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryError, match=r"back.tum:3: timestamp 0.5 is out of order"):
        read_trajectory(tmp_path / "back.tum", duplicates="keep")  # keep admits equal stamps, never disorder


# -- cut-off and corrupt files: unit quaternions, orthonormal rotations, a last line that ends -------------


def _last_line_cut(text: str, keep: int) -> str:
    """``text`` cut ``keep`` characters into its last line's last (space-separated) field, no line end after it."""
    body, last = text.rstrip("\n").rsplit("\n", 1)
    return body + "\n" + last[: last.rfind(" ") + 1 + keep]


def test_evo_s_example_files_pass_the_quaternion_and_rotation_checks(shared_data: Path):
    from sgf_pipeline.trajectory import QUATERNION_TOLERANCE, ROTATION_TOLERANCE

    evo = shared_data / "evo"
    counts = {
        "freiburg1_xyz-groundtruth.txt": 3000,
        "freiburg1_xyz-rgbdslam.txt": 788,
        "fr2_desk_groundtruth.txt": 20957,
        "fr2_desk_ORB.txt": 2893,
        "V102.txt": 807,
    }
    for name, count in counts.items():
        assert len(read_tum(evo / name, duplicates="keep")) == count, name
    assert len(read_euroc_csv(evo / "V102_groundtruth.csv", duplicates="keep")) == 16702
    for name in ("KITTI_00_gt.txt", "KITTI_00_ORB.txt"):
        assert len(read_kitti(evo / name)) == 4541
    # the tolerances leave a margin over the real files' worst values (EuRoC's 6-decimal quaternions)
    worst = max(
        float(np.abs(np.linalg.norm(np.loadtxt(evo / n, usecols=(4, 5, 6, 7)), axis=1) - 1).max()) for n in counts
    )
    csv = np.loadtxt(evo / "V102_groundtruth.csv", delimiter=",", usecols=(4, 5, 6, 7))
    worst = max(worst, float(np.abs(np.linalg.norm(csv, axis=1) - 1).max()))
    assert worst < QUATERNION_TOLERANCE / 5
    kitti = np.loadtxt(evo / "KITTI_00_ORB.txt").reshape(-1, 3, 4)[:, :, :3]
    assert np.abs(kitti @ kitti.transpose(0, 2, 1) - np.eye(3)).max() < ROTATION_TOLERANCE / 100


def test_a_tum_file_whose_last_quaternion_was_cut_is_refused(shared_data: Path, tmp_path: Path):
    text = (shared_data / "evo" / "freiburg1_xyz-groundtruth.txt").read_text()
    lines = text.split("\n")
    last = len(lines) - 1  # the file ends with a line end: the last line's number
    # cut mid-number: '-0.2336' became '-0.2', and the line end is gone
    cut = tmp_path / "cut.txt"
    cut.write_text(_last_line_cut(text, 4))
    assert cut.read_text().endswith(" -0.2")
    with pytest.raises(
        TrajectoryError, match=rf"cut.txt:{last}: the last line has no line end, so the file may be cut"
    ):
        read_trajectory(cut)
    # a qw mangled into another number, the line end kept ('-0.2336' read as '2.71'): length from the values
    mangled = tmp_path / "mangled.txt"
    mangled.write_text(text.rsplit(" ", 1)[0] + " 2.71\n")
    q = np.array([0.6649, 0.6517, -0.2803, 2.71])
    with pytest.raises(TrajectoryError) as error:
        read_trajectory(mangled)
    message = str(error.value)
    assert message.startswith(f"{mangled}:{last}: the quaternion (qx qy qz qw) = (0.6649 0.6517 -0.2803 2.71)")
    assert f"has length {np.linalg.norm(q):.6g}, off 1 by more than 0.001" in message


def test_a_kitti_file_whose_last_value_was_cut_is_refused(shared_data: Path, tmp_path: Path):
    text = (shared_data / "evo" / "KITTI_00_gt.txt").read_text()
    cut = tmp_path / "cut.txt"
    cut.write_text(_last_line_cut(text, 3))  # tz '9.696153e+01' cut to '9.6': a plausible number, no line end
    assert cut.read_text().endswith(" 9.6")
    with pytest.raises(TrajectoryError, match=r"cut.txt:4541: the last line has no line end"):
        read_kitti(cut)
    # r33 cut from '9.988336e-01' to '9.9' with the line end kept: R is no rotation any more
    fields = text.rstrip("\n").rsplit("\n", 1)[1].split()
    fields[10] = "9.9"
    R = np.array([float(v) for v in fields]).reshape(3, 4)[:, :3]
    mangled = tmp_path / "mangled.txt"
    mangled.write_text(text.rstrip("\n").rsplit("\n", 1)[0] + "\n" + " ".join(fields) + "\n")
    deviation = np.abs(R @ R.T - np.eye(3)).max()
    with pytest.raises(
        TrajectoryError,
        match=rf"mangled.txt:4541: the pose's 3x3 block is not a rotation \(\|R R\^T - I\| = {deviation:.3g}, more than "
        r"0.001",
    ):
        read_kitti(mangled)


def test_an_euroc_csv_whose_last_quaternion_was_cut_is_refused(shared_data: Path, tmp_path: Path):
    text = (shared_data / "evo" / "V102_groundtruth.csv").read_text()
    body, last = text.rstrip("\n").rsplit("\n", 1)
    fields = last.split(",")
    fields[4] = "0.15"  # qw '0.159222' cut to '0.15' inside the line (the other columns follow)
    mangled = tmp_path / "mangled.csv"
    mangled.write_text(body + "\n" + ",".join(fields) + "\n")
    number = text.count("\n")
    q = np.array([float(v) for v in fields[4:8]])
    with pytest.raises(TrajectoryError, match=rf"mangled.csv:{number}: the quaternion \(qw qx qy qz\)") as error:
        read_euroc_csv(mangled, duplicates="keep")
    assert f"has length {np.linalg.norm(q):.6g}" in str(error.value)
    cut = tmp_path / "cut.csv"
    cut.write_text(body + "\n" + last[:40])
    with pytest.raises(TrajectoryError, match=rf"cut.csv:{number}: the last line has no line end"):
        read_euroc_csv(cut, duplicates="keep")


def test_the_quaternion_tolerance_admits_three_decimals(tmp_path: Path):
    from sgf_pipeline.trajectory import QUATERNION_TOLERANCE

    rng = np.random.default_rng(3)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rows = [f"{i} 0 0 0 {a:.3f} {b:.3f} {c:.3f} {d:.3f}" for i, (a, b, c, d) in enumerate(q)]
    (tmp_path / "three.tum").write_text("\n".join(rows) + "\n")
    assert len(read_tum(tmp_path / "three.tum")) == 500  # rounding moves a length by at most sqrt(4) * 0.0005
    for qw, refused in ((1 + 0.9 * QUATERNION_TOLERANCE, False), (1 + 1.1 * QUATERNION_TOLERANCE, True)):
        path = tmp_path / f"{qw}.tum"
        path.write_text(f"0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 {qw!r}\n")
        if refused:
            with pytest.raises(TrajectoryError, match=rf"{qw}.tum:2: the quaternion"):
                read_tum(path)
        else:
            np.testing.assert_allclose(read_tum(path).poses[1], np.eye(4), atol=1e-15)


def test_the_folder_reader_skips_a_pose_whose_quaternion_is_off_unit_length(tmp_path: Path):
    from sgf_pipeline.trajectory import parse_tum

    path = tmp_path / "odometry.tum"
    path.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 2.71\n2 2 0 0 0 0 0 1")  # a recording's file, cut or not
    ts, poses, lines = parse_tum(path)
    assert ts.tolist() == [0.0, 1.0, 2.0] and lines == [1, 2, 3]
    assert np.isnan(poses[1, :3, :3]).all() and np.isfinite(poses[[0, 2]]).all()
