"""ATE and RPE reproduce evo on evo's own test trajectories; trajectory files round-trip through evo."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sgf_pipeline.errors import DataError
from sgf_pipeline.evaluation import ate, ate_rmse, rpe
from sgf_pipeline.trajectory import Trajectory, read_trajectory

# evo 1.38.1's evo_ape results on these files (shared/data/README.md)
EVO_APE = [
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "none", 7.790289),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "se3", 1.303450),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "sim3", 0.937709),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "se3", 0.013470),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", "sim3", 0.006123),
]


def _read(path: Path) -> Trajectory:
    return read_trajectory(path, duplicates="drop")  # fr2_desk's ground truth repeats one timestamp


@pytest.mark.parametrize(("ref", "est", "align", "expected"), EVO_APE)
def test_ate_reproduces_evo_ape(shared_data: Path, ref: str, est: str, align: str, expected: float):
    evo = shared_data / "evo"
    result = ate(_read(evo / ref), _read(evo / est), align)  # type: ignore[arg-type]
    assert result.rmse == pytest.approx(expected, abs=1e-6)
    assert ate_rmse(_read(evo / ref), _read(evo / est), align) == result.rmse  # type: ignore[arg-type]
    assert result.min <= result.median <= result.max and result.rmse >= result.mean


def test_kitti_with_times_file_gives_the_same_ate(shared_data: Path):
    evo = shared_data / "evo"
    times = evo / "KITTI_00_gt_times.txt"
    gt = read_trajectory(evo / "KITTI_00_gt.txt", "kitti", times)
    orb = read_trajectory(evo / "KITTI_00_ORB.txt", "kitti", times)
    assert gt.timestamps[1] == pytest.approx(0.1037359)
    result = ate(gt, orb, "se3")
    assert result.rmse == pytest.approx(1.303450, abs=1e-6)
    assert result.pairs == 4541


def _evo_files(evo_dir: Path, ref: str, est: str):  # type: ignore[no-untyped-def]
    """Both files read by evo's own file_interface (an independent path to the same data)."""
    from evo.core import sync
    from evo.tools import file_interface

    if ref.startswith("KITTI"):
        return file_interface.read_kitti_poses_file(evo_dir / ref), file_interface.read_kitti_poses_file(evo_dir / est)
    r = file_interface.read_tum_trajectory_file(evo_dir / ref)
    e = file_interface.read_tum_trajectory_file(evo_dir / est)
    return sync.associate_trajectories(r, e, max_diff=0.01)


RPE_CASES = [
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", 1, "frames", "translation", "none"),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", 100, "meters", "rotation", "sim3"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", 1, "frames", "rotation", "se3"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", 0.1, "meters", "translation", "sim3"),
]


@pytest.mark.parametrize(("ref", "est", "delta", "unit", "relation", "align"), RPE_CASES)
def test_rpe_matches_evo_library(shared_data: Path, ref, est, delta, unit, relation, align):  # type: ignore[no-untyped-def]
    import copy

    from evo.core import metrics
    from evo.core.units import Unit
    from evo.main_rpe import rpe as evo_rpe

    evo = shared_data / "evo"
    ours = rpe(_read(evo / ref), _read(evo / est), delta, unit, relation, align)
    traj_ref, traj_est = _evo_files(evo, ref, est)
    theirs = evo_rpe(
        copy.deepcopy(traj_ref),
        copy.deepcopy(traj_est),
        metrics.PoseRelation.translation_part if relation == "translation" else metrics.PoseRelation.rotation_angle_deg,
        delta=delta,
        delta_unit={"frames": Unit.frames, "meters": Unit.meters}[unit],
        align=align != "none",
        correct_scale=align == "sim3",
    )
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert getattr(ours, key) == pytest.approx(theirs.stats[key], rel=1e-9, abs=1e-12), key
    assert ours.pairs == len(theirs.np_arrays["error_array"]) > 10


def test_rpe_and_ate_refuse_what_cannot_be_computed():
    ts = np.arange(5, dtype=float)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = ts
    a = Trajectory(ts, poses)
    far = Trajectory(ts + 100.0, poses)
    with pytest.raises(DataError, match=r"no poses of the two trajectories are within 0\.01 s"):
        ate(a, far)
    with pytest.raises(DataError, match="unknown alignment 'affine'"):
        ate(a, a, "affine")  # type: ignore[arg-type]
    with pytest.raises(DataError, match="delta unit 'seconds'"):
        rpe(a, a, 1.0, "seconds")  # type: ignore[arg-type]
    with pytest.raises(DataError, match="empty index list"):
        rpe(a, a, 50.0, "meters")
    assert ate(a, a, "none").rmse == 0.0
    two = Trajectory(ts[:2], poses[:2])
    with pytest.raises(DataError, match="at least 3 associated poses"):
        ate(two, two, "se3")


def test_sgf_eval_cli_writes_json(shared_data: Path, tmp_path: Path):
    evo = shared_data / "evo"
    out = tmp_path / "eval"
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "sgf-eval"),
            f"reference={evo / 'KITTI_00_gt.txt'}",
            f"estimate={evo / 'KITTI_00_ORB.txt'}",
            "align=sim3",
            "rpe.delta=10",
            f"hydra.run.dir={out}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "ATE (m)" in proc.stdout and "0.937709" in proc.stdout
    report = json.loads((out / "eval.json").read_text())
    assert report["ate"]["rmse"] == pytest.approx(0.937709, abs=1e-6)
    assert report["ate"]["pairs"] == 4541
    expected = rpe(_read(evo / "KITTI_00_gt.txt"), _read(evo / "KITTI_00_ORB.txt"), 10, "frames", "rotation", "sim3")
    assert report["rpe_rotation"]["rmse"] == pytest.approx(expected.rmse, rel=1e-12)
    assert report["units"] == {"ate": "m", "rpe_translation": "m", "rpe_rotation": "deg"}
    assert not any(p.name.startswith(".") and p.suffix == ".part" for p in out.iterdir())


def test_sgf_eval_cli_names_a_bad_file(tmp_path: Path):
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n1 0 0 nan 0 0 0 1\n")
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "sgf-eval"),
            f"reference={bad}",
            f"estimate={bad}",
            f"hydra.run.dir={tmp_path / 'out'}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert (
        "reference:" in proc.stderr
        and "bad.tum:2: non-finite pose (NaN or inf) or zero-length quaternion on line(s) [2]" in proc.stderr
    )


# -- like evo: repeated stamps kept, truncated estimates, trajectories in bags ---------------------------------


def _evo_v102(evo_dir: Path) -> tuple[float, int]:
    """evo's own reading, association and APE (``evo_ape euroc V102_groundtruth.csv V102.txt -a``)."""
    from evo.core import metrics, sync
    from evo.main_ape import ape
    from evo.tools import file_interface

    ref = file_interface.read_euroc_csv_trajectory(evo_dir / "V102_groundtruth.csv")
    est = file_interface.read_tum_trajectory_file(evo_dir / "V102.txt")
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    result = ape(ref, est, metrics.PoseRelation.translation_part, align=True)
    return float(result.stats["rmse"]), ref.num_poses


def test_duplicates_keep_reproduces_evo_ape_on_v102(shared_data: Path):
    """V1_02's estimate repeats 4 stamps; evo keeps those poses: so does duplicates=keep, to the last digit."""
    evo = shared_data / "evo"
    reference = read_trajectory(evo / "V102_groundtruth.csv", duplicates="keep")
    estimate = read_trajectory(evo / "V102.txt", duplicates="keep")
    assert len(estimate) == 807 and int(np.sum(np.diff(estimate.timestamps) == 0)) == 4
    expected, pairs = _evo_v102(evo)
    result = ate(reference, estimate, "se3")
    assert result.pairs == pairs == 798
    assert result.rmse == pytest.approx(expected, abs=1e-9)
    assert result.rmse == pytest.approx(0.091727, abs=1e-6)  # evo_ape's printed figure (shared/data/README.md)
    dropped = ate(reference, read_trajectory(evo / "V102.txt", duplicates="drop"), "se3")
    assert dropped.pairs == 794 and abs(dropped.rmse - expected) > 1e-5  # the default is not evo's figure


def _eval_cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(Path(sys.executable).parent / "sgf-eval"), *args, f"hydra.run.dir={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_sgf_eval_prints_the_pairs_and_warns_of_a_truncated_estimate(shared_data: Path, tmp_path: Path):
    evo = shared_data / "evo"
    whole = _eval_cli(
        tmp_path / "a", f"reference={evo / 'V102_groundtruth.csv'}", f"estimate={evo / 'V102.txt'}", "duplicates=keep"
    )
    assert whole.returncode == 0, whole.stderr
    assert "0.091727" in whole.stdout
    assert "798 pose pairs matched within 0.01 s (estimate 807 poses, reference 16702" in whole.stdout
    assert "of the reference's time span" not in whole.stdout + whole.stderr
    report = json.loads((tmp_path / "a" / "out" / "eval.json").read_text())
    assert report["matched_pairs"] == 798 and report["duplicates"] == "keep"
    # the first third of the estimate: scored on what it has, with a warning
    lines = (evo / "V102.txt").read_text().splitlines()
    (tmp_path / "short.txt").write_text("\n".join(lines[:270]) + "\n")
    short = _eval_cli(tmp_path / "b", f"reference={evo / 'V102_groundtruth.csv'}", f"estimate={tmp_path / 'short.txt'}")
    assert short.returncode == 0, short.stderr
    report = json.loads((tmp_path / "b" / "out" / "eval.json").read_text())
    reference = read_trajectory(evo / "V102_groundtruth.csv")
    span = reference.timestamps[-1] - reference.timestamps[0]
    start = max(reference.timestamps[0], float(lines[0].split()[0]))  # the estimate starts 4.6 s later
    expected = (float(lines[269].split()[0]) - start) / span
    assert report["coverage"] == pytest.approx(expected, rel=1e-9) and report["coverage"] < 0.4
    assert f"the estimate covers {100 * expected:.0f} % of the reference's time span" in short.stdout + short.stderr


def _v102_bag(evo: Path, path: Path, version: str = "ros2_sqlite3") -> Path:
    """V1_02 as a bag: the ground truth as PoseStamped, as tf (odom -> body under a static map -> odom), the
    estimate as Odometry."""
    from sgf_pipeline.geometry import pose_from_xyz_rpy
    from sgf_pipeline.trajectory.euroc import _ns_from_seconds

    from .recordings import odometry_message, pose_stamped, tf_message, transform_stamped, typestore, write_messages

    types = typestore(version).types
    ros1 = version == "ros1"
    gt = read_trajectory(evo / "V102_groundtruth.csv")
    est = read_trajectory(evo / "V102.txt", duplicates="keep")
    map_to_odom = pose_from_xyz_rpy(3.0, -2.0, 0.5, 0.0, 0.0, 1.1)
    msgs: list[tuple[str, str, int, object]] = []
    first = _ns_from_seconds(float(gt.timestamps[0]))
    static = transform_stamped(types, first, "map", "odom", map_to_odom, ros1)
    msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", first, tf_message(types, [static])))
    for t, pose in zip(gt.timestamps, gt.poses, strict=True):
        ns = _ns_from_seconds(float(t))
        msgs.append(("/vicon/pose", "geometry_msgs/msg/PoseStamped", ns, pose_stamped(types, ns, "odom", pose, ros1)))
        link = transform_stamped(types, ns, "odom", "body", pose, ros1)
        msgs.append(("/tf", "tf2_msgs/msg/TFMessage", ns, tf_message(types, [link])))
    for t, pose in zip(est.timestamps, est.poses, strict=True):
        ns = _ns_from_seconds(float(t))
        msgs.append(("/vio/odom", "nav_msgs/msg/Odometry", ns, odometry_message(types, ns, "odom", "body", pose, ros1)))
    return write_messages(path, msgs, version)


def test_trajectories_from_a_bag_give_evo_s_figure(shared_data: Path, tmp_path: Path):
    """PoseStamped, Odometry and tf topics of a bag are trajectories; read as evo reads them."""
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    from sgf_pipeline.bags import read_bag_trajectory, split_bag_source

    evo = shared_data / "evo"
    bag = _v102_bag(evo, tmp_path / "v102")
    assert split_bag_source(f"{bag}:/vicon/pose") == (bag, "/vicon/pose")
    assert split_bag_source(str(evo / "V102.txt")) is None
    gt = read_bag_trajectory(bag, "/vicon/pose")
    est = read_bag_trajectory(bag, "/vio/odom", duplicates="keep")
    with Reader(bag) as reader:  # evo's bag reader: the same stamps and poses
        for ours, topic in ((gt, "/vicon/pose"), (est, "/vio/odom")):
            theirs = file_interface.read_bag_trajectory(reader, topic)
            np.testing.assert_allclose(ours.timestamps, theirs.timestamps, rtol=0, atol=1e-6)
            np.testing.assert_allclose(ours.poses, np.asarray(theirs.poses_se3), rtol=0, atol=1e-12)
    result = ate(gt, est, "se3")
    assert result.pairs == 798 and result.rmse == pytest.approx(0.091727, abs=1e-6)
    # tf: body in map through the static map -> odom; se3 alignment takes the fixed offset off exactly
    chained = read_bag_trajectory(bag, "/tf:map.body")
    assert len(chained) == len(gt) and read_bag_trajectory(bag, "/tf").poses.shape == gt.poses.shape
    assert ate(chained, est, "se3").rmse == pytest.approx(result.rmse, abs=1e-9)
    assert float(np.linalg.norm(chained.positions[0] - gt.positions[0])) > 1.0  # really moved by map -> odom
    # the console script takes the same topics
    proc = _eval_cli(tmp_path, f"reference={bag}:/tf:map.body", f"estimate={bag}:/vio/odom", "duplicates=keep")
    assert proc.returncode == 0, proc.stderr
    assert "0.091727" in proc.stdout and "798 pose pairs matched" in proc.stdout
    for spec, message in (
        (f"{bag}:/nothing", r"no topic /nothing; topics with poses .*/tf, /tf_static, /vicon/pose, /vio/odom"),
        (f"{bag}:/tf:map", r"name the frames as <parent>\.<child>, e.g\. /tf:map\.base_link"),
        (f"{bag}:/tf:map.camera", r"does not join map and camera; the frames it has: body, map, odom"),
        (f"{bag}:/vicon/pose:map.body", r"frames are named only for a tf topic"),
    ):
        proc = _eval_cli(tmp_path / "bad", f"reference={spec}", f"estimate={evo / 'V102.txt'}")
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert re.search(message, proc.stderr), proc.stderr


def test_a_transform_stamped_topic_is_a_trajectory(tmp_path: Path):
    """A ground truth published as TransformStamped (a motion-capture bridge) reads as the poses it carries."""
    from sgf_pipeline.bags import read_bag_trajectory

    from .recordings import calibration, make_frames, write_bag

    frames = make_frames(6, seed=4)
    bag = write_bag(tmp_path / "drive.bag", frames, calibration(), "ros1", gt_kind="transform")
    truth = read_bag_trajectory(bag, "/ground_truth")
    np.testing.assert_allclose(truth.poses, [f.ground_truth for f in frames], atol=1e-12)
    np.testing.assert_allclose(truth.timestamps, [f.t for f in frames], atol=1e-6)


def test_bag_topics_are_found_with_or_without_the_leading_slash(shared_data: Path, tmp_path: Path):
    """A ROS 1 bag naming its topics without a slash, as evo's ROS_example.bag does: both spellings work."""
    from sgf_pipeline.bags import find_topic, read_bag_trajectory, split_bag_source
    from sgf_pipeline.trajectory.euroc import _ns_from_seconds

    from .recordings import pose_stamped, typestore, write_messages

    evo = shared_data / "evo"
    types = typestore("ros1").types
    msgs: list[tuple[str, str, int, object]] = []
    for topic, trajectory in (
        ("groundtruth", read_trajectory(evo / "V102_groundtruth.csv")),
        ("S-PTAM", read_trajectory(evo / "V102.txt", duplicates="keep")),
    ):
        for t, pose in zip(trajectory.timestamps, trajectory.poses, strict=True):
            ns = _ns_from_seconds(float(t))
            msgs.append((topic, "geometry_msgs/msg/PoseStamped", ns, pose_stamped(types, ns, "world", pose, True)))
    bag = write_messages(tmp_path / "example.bag", msgs, "ros1")
    assert split_bag_source(f"{bag}:groundtruth") == (bag, "groundtruth")
    assert split_bag_source(f"{bag}:/groundtruth") == (bag, "/groundtruth")
    assert split_bag_source(f"{tmp_path}:v2.tum") is None  # a folder that is no bag: a file name with a colon
    slash, bare = read_bag_trajectory(bag, "/groundtruth"), read_bag_trajectory(bag, "groundtruth")
    assert len(slash) == len(bare) == 16702  # V1_02's ground truth
    np.testing.assert_array_equal(slash.poses, bare.poses)
    # the console script, paths given positionally: evo's figure for V1_02 (798 pairs, repeated stamps kept)
    proc = _eval_cli(tmp_path, f"{bag}:/groundtruth", f"{bag}:S-PTAM", "duplicates=keep")
    assert proc.returncode == 0, proc.stderr
    assert "0.091727" in proc.stdout and "798 pose pairs matched" in proc.stdout
    report = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert report["reference"] == f"{bag.resolve()}:/groundtruth" and report["ate"]["pairs"] == 798
    # a name two topics answer to, and one no topic answers to
    assert find_topic(["groundtruth", "/groundtruth"], "/groundtruth", bag) == "/groundtruth"  # spelled exactly
    with pytest.raises(DataError, match=r"example.bag: //groundtruth is ambiguous: the bag has /groundtruth and "):
        find_topic(["groundtruth", "/groundtruth"], "//groundtruth", bag)
    assert find_topic(["/odom"], "odom", bag) == "/odom" and find_topic(["/odom"], "odometry", bag) is None
    with pytest.raises(DataError, match=r"no topic /nothing; topics with poses .*: S-PTAM, groundtruth"):
        read_bag_trajectory(bag, "/nothing")
