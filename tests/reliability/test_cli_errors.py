"""Console scripts given bad arguments: exit status 2 and one paragraph on stderr, never a traceback."""

from __future__ import annotations

import json
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from adapters.recordings import (
    KITTI_K,
    T0_NS,
    calibration,
    make_frames,
    tf_message,
    transform_stamped,
    typestore,
    write_bag,
    write_folder,
)
from adapters.test_euroc_dataset import make_euroc
from sgf_testing import run_cli

from sgf_pipeline.calibration import Calibration, Intrinsics
from sgf_pipeline.geometry import pose_from_xyz_rpy


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("cli")
    folder = write_folder(base / "seq", make_frames(2, seed=1), calibration())
    broken = write_folder(base / "broken", make_frames(2, seed=1), calibration())
    (broken / "calibration.yaml").write_text("intrinsics: {fx: 100, fy: [\n")
    binary = base / "junk.tum"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe")
    still = base / "still.tum"
    still.write_text("".join(f"{i}.0 1 2 0 0 0 0 1\n" for i in range(6)))
    fine = base / "fine.tum"
    fine.write_text("".join(f"{i}.0 {i} {i % 2} 0 0 0 0 1\n" for i in range(6)))
    cut = base / "cut.tum"
    cut.write_text(fine.read_text()[:-3])
    bag = base / "garbage.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 4)
    empty = base / "empty"
    empty.mkdir()
    types = typestore().types
    tf = tf_message(types, [transform_stamped(types, T0_NS, "map", "base_link", pose_from_xyz_rpy(1, 2, 0, 0, 0, 0))])
    tf_bag = write_bag(
        base / "tf_bag",
        make_frames(3, seed=2),
        calibration(),
        extra=[("/tf_static", "tf2_msgs/msg/TFMessage", T0_NS, tf)],
    )
    fx, fy, cx, cy = KITTI_K
    car = Calibration.from_mounting(Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=1241, height=376), 1.65, 0.0)
    frames = make_frames(2, seed=1)
    for f in frames:
        f.image = np.zeros((376, 1241, 3), np.uint8)
    level = write_folder(base / "level", frames, car)
    euroc = make_euroc(base / "euroc", frames=4)
    corrupt_run = base / "runs_corrupt" / "r1"
    corrupt_run.mkdir(parents=True)
    (corrupt_run / "metrics.json").write_text('{"status": "finished", "ate_rmse_m": {')
    tagged_run = base / "runs_tagged" / "r1"
    tagged_run.mkdir(parents=True)
    (tagged_run / "metrics.json").write_text(json.dumps({"status": "finished", "sequence": "s"}))
    (tagged_run / "config.yaml").write_text("!!python/object/apply:os.system ['touch pwned']\n")
    return {
        "folder": folder,
        "broken": broken,
        "binary": binary,
        "still": still,
        "fine": fine,
        "cut": cut,
        "bag": bag,
        "empty": empty,
        "corrupt_runs": corrupt_run.parent,
        "tagged_runs": tagged_run.parent,
        "tf_bag": tf_bag,
        "level": level,
        "euroc": euroc,
        "base": base,
    }


RUN = ["dataset=folder", "pipeline=[dataset]", "run.progress=false"]

CASES: list[tuple[str, str, list[str], str]] = [
    ("unknown key", "sgf-run", [*RUN, "foo=1"], r"^error: foo: no such key \(top-level keys: dataset, .*, run, "),
    (
        "a misspelt key",
        "sgf-run",
        ["dataset=rosbag", "dataset.image_topc=/cam"],
        r"^error: dataset.image_topc: no such key; did you mean dataset.image_topic or dataset.imu_topic\? \(keys of "
        r"dataset: name, path, .*image_topic, ",
    ),
    ("unknown variant", "sgf-run", [*RUN, "ipm=nope"], r"Could not find 'ipm/nope'\n  Available options in 'ipm':"),
    ("bad override syntax", "sgf-run", [*RUN, "enhance.clip_limit=["], r"no viable alternative at input '\['"),
    ("missing dataset path", "sgf-run", RUN, r"dataset=folder cannot start: dataset=folder needs the sequence folder"),
    (
        "unset environment variable",
        "sgf-run",
        [*RUN, "dataset.path=${oc.env:SGF_SURELY_UNSET_456}"],
        r"dataset.path: the value cannot be resolved: .*Environment variable 'SGF_SURELY_UNSET_456' not found",
    ),
    ("a _target_", "sgf-run", [*RUN, "+enhance._target_=os.system"], r"enhance._target_: `_target_` is refused"),
    ("a pickle rerun", "sgf-run", ["--experimental-rerun=config.pickle"], r"--experimental-rerun is not supported: "),
    ("broken calibration", "sgf-run", [*RUN, "dataset.path={broken}"], r"calibration.yaml:\d+: not valid YAML"),
    (
        "no trajectories",
        "sgf-eval",
        [],
        r"give the reference trajectory: sgf-eval REFERENCE ESTIMATE \[key=value ...\] \(or reference=<file> estimate=",
    ),
    (
        "three paths",
        "sgf-eval",
        ["{fine}", "{fine}", "{still}", "align=none"],
        r"too many paths \('.*still.tum' left over\): sgf-eval REFERENCE ESTIMATE \[key=value ...\]; other options",
    ),
    ("a path given twice", "sgf-eval", ["{fine}", "reference={fine}"], r"reference is given twice, as the path '"),
    ("a cut trajectory", "sgf-eval", ["{cut}", "{fine}"], r"reference: .*cut.tum:6: the last line has no line end"),
    (
        "binary trajectory",
        "sgf-eval",
        ["reference={binary}", "estimate={binary}"],
        r"reference: .*junk.tum.*not a text",
    ),
    (
        "a robot that never moved",
        "sgf-eval",
        ["reference={still}", "estimate={still}"],
        r"se3 alignment is not possible .*one point or one line .*use align=none",
    ),
    ("unknown alignment", "sgf-eval", ["reference={fine}", "estimate={fine}", "align=affine"], r"sgf-eval.align: "),
    ("garbage bag", "sgf-bag-info", ["{bag}"], r"cannot open bag .*garbage.bag: .*truncated or corrupt"),
    ("a folder that is no bag", "sgf-bag-info", ["path={empty}"], r"empty is a folder without metadata.yaml"),
    ("no run directory", "sgf-report", [], r"which runs\? pass a run or multirun directory"),
    (
        "corrupt metrics",
        "sgf-report",
        ["{corrupt_runs}"],
        r"r1/metrics.json is not valid JSON .*was the run interrupted\?",
    ),
    (
        "python tag in a config",
        "sgf-report",
        ["{tagged_runs}"],
        r"r1/config.yaml:1: not valid YAML: could not determine",
    ),
    ("unknown kind", "sgf-plugins", ["kind=teleport"], r"kind=teleport: no plugin registers stages of that kind"),
    (
        "a tf tree that does not place the camera",
        "sgf-run",
        [
            "dataset=rosbag",
            "dataset.path={tf_bag}",
            "dataset.image_topic=/camera/image_raw",
            "dataset.camera_info_topic=/camera/camera_info",
            "dataset.odometry_topic=/odom",
            "pipeline=[dataset]",
            "run.progress=false",
        ],
        r"the tf tree \(/tf_static\) does not join base_link and camera; the frames it has: base_link, map",
    ),
    (
        "a region the camera does not see",
        "sgf-run",
        [
            "dataset=folder",
            "dataset.path={level}",
            "pipeline=[dataset,enhance,ipm]",
            "ipm.region=fixed",
            "run.progress=false",
        ],
        r"no pixel of the ipm region x in \[0.5, 5.62\] m.* is visible from the camera \(1.65 m high.*ipm.region=auto",
    ),
    (
        "a ground truth that is not there",
        "sgf-run",
        ["dataset=euroc", "dataset.path={euroc}", "dataset.groundtruth=leica0", "dataset.camera_height=0.5"],
        r"dataset.groundtruth=leica0: no such folder under .*mav0",
    ),
    (
        "a bag topic with no pose",
        "sgf-eval",
        ["reference={tf_bag}:/camera/image_raw", "estimate={fine}"],
        r"reference: .*tf_bag:/camera/image_raw carries sensor_msgs/msg/Image, which holds no pose",
    ),
]


def test_bad_arguments_exit_2_with_one_paragraph(files: dict[str, Path]):
    def launch(case: tuple[str, str, list[str], str]):
        _, script, args, _ = case
        for key, value in files.items():
            args = [a.replace("{" + key + "}", str(value)) for a in args]
        if script == "sgf-run" or script == "sgf-eval":
            args.append(f"hydra.run.dir={files['base'] / 'out' / case[0].replace(' ', '_')}")
        return run_cli(script, *args, cwd=files["base"], timeout=120)

    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(launch, CASES))
    failures = []
    for (label, script, _, pattern), result in zip(CASES, results, strict=True):
        stderr = result.stderr.rstrip("\n")
        problems = []
        if result.returncode != 2:
            problems.append(f"exit status {result.returncode}")
        if not stderr.startswith("error: "):
            problems.append("stderr does not start with 'error: '")
        if "Traceback" in stderr + result.stdout or "HYDRA_FULL_ERROR" in stderr:
            problems.append("a traceback or Hydra's traceback hint")
        if "\n\n" in stderr:
            problems.append("more than one paragraph")
        if not re.search(pattern, stderr, re.DOTALL):
            problems.append(f"no match for {pattern!r}")
        if problems:
            failures.append(f"{script} ({label}): {'; '.join(problems)}\n{stderr[:600]}")
    assert not failures, "\n\n".join(failures)
    assert not (files["base"] / "pwned").exists()


def test_a_traceback_on_request(files: dict[str, Path]):
    result = run_cli(
        "sgf-eval", f"reference={files['binary']}", f"estimate={files['binary']}", env={"SGF_PIPELINE_TRACEBACK": "1"}
    )
    assert result.returncode == 1
    assert "Traceback (most recent call last)" in result.stderr and "DataError: reference: " in result.stderr


@pytest.mark.parametrize(
    ("metrics", "message"),
    [
        ({"ate_rmse_m": {"sgf": "1.2 m"}}, r"ate_rmse_m.sgf must be a number or null, got '1.2 m'"),
        ({"loops": {"closed": True}}, r"loops.closed must be a number or null, got True"),
        ({"timing": [1, 2]}, r"timing must be a mapping, got \[1, 2\]"),
        ({"timing": {"stages": {"ipm": {"mean_ms": "fast"}}}}, r"timing.stages must map stage kinds to"),
        ({"sequence": ["a"]}, r"sequence must be a name, got \['a'\]"),
    ],
)
def test_sgf_report_refuses_metrics_of_another_shape(tmp_path: Path, metrics: dict, message: str):
    from sgf_experiments.runs import find_runs

    from sgf_pipeline.errors import DataError

    run = tmp_path / "r1"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"status": "finished", **metrics}))
    with pytest.raises(DataError, match=rf"r1/metrics.json: {message}"):
        find_runs(tmp_path)


def test_positional_paths_become_overrides():
    from sgf_pipeline.cli.common import positional_overrides
    from sgf_pipeline.errors import ConfigError

    keys, usage = ("reference", "estimate"), "sgf-eval REFERENCE ESTIMATE"
    assert positional_overrides(["a.txt", "b c.txt", "align=sim3"], keys, usage) == [
        "reference=a.txt",
        "estimate='b c.txt'",
        "align=sim3",
    ]
    assert positional_overrides(["d.bag:/gt", "1.5", "-m"], keys, usage) == [
        "reference=d.bag:/gt",
        "estimate='1.5'",
        "-m",
    ]
    assert positional_overrides(["-m", "a.txt"], keys, usage) == ["-m", "a.txt"]  # only leading paths
    assert positional_overrides(["reference=a", "estimate=b"], keys, usage) == ["reference=a", "estimate=b"]
    with pytest.raises(
        ConfigError, match=r"^estimate is given twice, as the path 'b' and as estimate=...; give it once"
    ):
        positional_overrides(["a", "b", "estimate=c"], keys, usage)


@pytest.mark.parametrize(
    ("script", "forms"),
    [
        (
            "sgf-eval",
            [
                "sgf-eval REFERENCE ESTIMATE [key=value ...]",
                "sgf-eval reference=REFERENCE estimate=ESTIMATE [key=value ...]",
            ],
        ),
        ("sgf-bag-info", ["sgf-bag-info BAG [key=value ...]", "sgf-bag-info path=BAG [key=value ...]"]),
        ("sgf-report", ["sgf-report DIR [out=OTHER_DIR]", "sgf-report dir=DIR [out=OTHER_DIR]"]),
    ],
)
def test_help_shows_both_forms(script: str, forms: list[str]):
    result = run_cli(script, "--help")
    assert result.returncode == 0 and result.stderr == ""
    usage = result.stdout.split("Usage:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert [line.strip() for line in usage] == forms


def test_a_closed_stdout_ends_quietly(files: dict[str, Path]):
    """`sgf-bag-info BAG | head -1` with head gone before the first line: no traceback, status 0."""
    import os
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)  # the reader is gone: every write to the pipe fails (EPIPE)
    try:
        proc = subprocess.run(
            [str(Path(sys.executable).parent / "sgf-bag-info"), str(files["tf_bag"])],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
        )
    finally:
        os.close(write)
    assert proc.returncode == 0 and proc.stderr == ""
