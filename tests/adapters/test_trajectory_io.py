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
