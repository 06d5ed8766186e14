"""The BEV's metric error on the synthetic world, by kind of ground: plain IPM, the paper's MC-IPM and its extensions."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from sgf_experiments.ipm_accuracy import (
    AHEAD_MC,
    BevSamples,
    IpmAccuracy,
    bev_position_error,
    default_variants,
    evaluate,
    ground_kind,
    main,
)
from sgf_plugins.ipm import InversePerspectiveMapping, IpmParams
from sgf_plugins.ipm.stages import PlaneMotionCompensatedIPM, PlaneMotionCompensatedIpmParams
from sgf_plugins.world import CampusWorld, build_world

# campus_reverse_slope at 30 %, seed 0: flat ground and a speed bump (frames 146-154), then flat
# ground into a hill (transition from frame 486, a steady slope from 570); MC-IPM's queue fills on
# the flat frames before each.
FRAMES = [*range(0, 170), *range(420, 600)]
#: metres between the joints of the world's small concrete slabs
SLAB_PERIOD = 1.0


@pytest.fixture(scope="module")
def flat_world() -> CampusWorld:
    return build_world("campus_delivery", seed=3, flat_ground=True, occluders=False, sensor_noise=False)


@pytest.fixture(scope="module")
def hilly() -> IpmAccuracy:
    world = build_world("campus_reverse_slope", seed=0, scale=0.3, occluders=False, sensor_noise=False)
    return evaluate(world, default_variants(), FRAMES)


def test_plain_ipm_is_exact_on_a_flat_world(flat_world) -> None:
    plain = InversePerspectiveMapping(IpmParams())
    samples = BevSamples(plain.grid, step=8)
    h = plain.homography(flat_world.calibration)
    for k in (0, 40, 80):
        pose = flat_world.drive.poses[k]
        layers = flat_world.render_layers(pose, flat_world.frame_conditions(k))
        error = bev_position_error(layers.ground_xy(), pose, h, samples)
        assert error < 0.002, k  # the texel maps' interpolation, nothing else
        assert ground_kind(flat_world, pose) == "flat"
        # a BEV shifted by 10 cm is measured as 10 cm off
        shifted = h @ np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -0.1 / plain.grid.resolution], [0.0, 0.0, 1.0]])
        assert bev_position_error(layers.ground_xy(), pose, shifted, samples) == pytest.approx(0.1, abs=0.003)


def test_the_kinds_of_ground_along_the_window(hilly: IpmAccuracy) -> None:
    kinds = dict(zip(hilly.frames, hilly.kinds, strict=True))
    assert kinds[20] == "flat" and kinds[148] == "bump" and kinds[520] == "transition" and kinds[590] == "slope"


def test_mc_ipm_against_plain_ipm_by_kind_of_ground(hilly: IpmAccuracy) -> None:
    table = {kind: {v: hilly.mean(v, kind) for v in hilly.errors} for kind in ("flat", "bump", "transition")}
    print("\n" + hilly.table())
    flat, bump, transition = table["flat"], table["bump"], table["transition"]
    # over the speed bump: both MC-IPMs undo the robot's pitch, plain IPM cannot
    assert bump["mc_ahead"] * 3.0 <= bump["plain"] and bump["mc"] * 3.0 <= bump["plain"]
    # onto the hill: the paper's reference lags half a queue behind the grade; mc_ahead's line fit
    # follows it and looks 2 m ahead, below plain IPM, which takes the ground for the robot's plane
    assert transition["mc_ahead"] < transition["plain"] < transition["mc"]
    assert transition["mc_ahead"] * 2.0 <= transition["mc"]
    # on flat ground: the IMU's noise is compensated as motion by the paper's MC-IPM; mc_ahead
    # shrinks it out and agrees with plain IPM to a few centimetres
    assert abs(flat["mc_ahead"] - flat["plain"]) < 0.04 and flat["mc_ahead"] < flat["mc"]
    # ipm=mc_plane: the ground ahead fitted from two views; on the steady slope it is the best
    # (plain IPM takes the slope's plane from the robot, the line fits of mc_ahead extrapolate a
    # change that has stopped), over the bump it keeps the IMU's compensation, on flat ground it
    # agrees with plain IPM to a few centimetres; onto the hill it is the best too (measured on this
    # window, slope / bump / flat / transition: 5.7 / 14.9 / 6.6 / 5.8 cm against plain IPM's
    # 13.3 / 357 / 5.6 / 17.8 cm; 8.6 cm at transitions with the 1 m baseline and looser priors before)
    slope = {v: hilly.mean(v, "slope") for v in hilly.errors}
    assert slope["mc_plane"] * 1.5 <= slope["plain"] and slope["mc_plane"] < slope["mc_ahead"]
    assert bump["mc_plane"] * 3.0 <= bump["plain"]
    assert transition["mc_plane"] * 2.5 <= transition["plain"] and transition["mc_plane"] < transition["mc_ahead"]
    assert abs(flat["mc_plane"] - flat["plain"]) < 0.03
    # ipm=mc_hindsight: the plane of the path the robot drove next (the BEV made 6.5 m later); on this
    # window, flat / slope / transition / bump: 3.7 / 7.1 / 5.0 / 16.0 cm (the target: 3x at transitions
    # and over bumps, and agreement on flat ground)
    assert transition["mc_hindsight"] * 3.0 <= transition["plain"] and bump["mc_hindsight"] * 3.0 <= bump["plain"]
    assert slope["mc_hindsight"] * 1.5 <= slope["plain"] and abs(flat["mc_hindsight"] - flat["plain"]) < 0.03


def test_the_command_writes_table_csv_and_plot(tmp_path: Path) -> None:
    out = tmp_path / "acc"
    assert main(["--preset", "campus_delivery", "--scale", "0.3", "--frames", "4", "--out", str(out)]) == 0
    table = (out / "ipm_accuracy.md").read_text()
    assert "| all | 4 |" in table and "mc_ahead (cm)" in table
    rows = (out / "ipm_accuracy.csv").read_text().splitlines()
    assert rows[0] == "frame,ground,plain,mc,mc_ahead,mc_plane,mc_hindsight" and len(rows) == 5
    assert all(math.isfinite(float(x)) for x in rows[1].split(",")[2:])
    assert (out / "ipm_accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["--preset", "campus_nowhere", "--out", str(tmp_path / "x")]) == 1
    # a choice of variants
    two = tmp_path / "two"
    args = ["--preset", "campus_delivery", "--scale", "0.3", "--frames", "2", "--out", str(two)]
    assert main([*args, "--variants", "plain, mc_hindsight"]) == 0
    assert (two / "ipm_accuracy.csv").read_text().splitlines()[0] == "frame,ground,plain,mc_hindsight"
    bad = ["--preset", "campus_delivery", "--frames", "2", "--out", str(tmp_path / "bad"), "--variants", "plain,mc_x"]
    assert main(bad) == 1 and not (tmp_path / "bad").exists()  # refused before any work
    # world parameters
    rough = tmp_path / "rough"
    rough_args = ["--preset", "campus_delivery", "--scale", "0.3", "--frames", "2", "--out", str(rough)]
    assert main([*rough_args, "--variants", "plain", "--world", "rough_paving_per_km=50"]) == 0
    assert "rough_paving_per_km=50" in (rough / "ipm_accuracy.md").read_text().splitlines()[0]
    assert main([*bad[:6], "--world", "rough_paving_per_km"]) == 1
    assert main([*bad[:6], "--world", "roughness=3"]) == 1  # not a world parameter
    assert not (tmp_path / "bad").exists()


def _longest_lock(errors: list[float]) -> int:
    """The most consecutive frames whose BEV is more than half a slab off: nearer the wrong joint than the right one."""
    longest = run = 0
    for error in errors:
        run = run + 1 if error > SLAB_PERIOD / 2.0 else 0
        longest = max(longest, run)
    return longest


def test_mc_plane_does_not_lock_onto_the_joints_of_a_slab_paving() -> None:
    """Seed 1 climbs over concrete slabs (frames 560-640) whose joints repeat every metre: seen from views a
    metre apart, the joints also line up under a wrong plane. A fit locked onto the wrong joint puts the BEV
    more than half a slab off for as long as the lock holds. With a 1 m baseline the fit locks; with the
    default 0.6 m baseline it does not (no five frames in a row that far off, as with plain IPM), and its
    mean error stays below plain IPM's. When and for how long the lock holds depends on the fits' rounding
    (12 to 23 frames under three settings of the numerical libraries' code paths); that it happens does not."""
    world = build_world("campus_reverse_slope", seed=1, scale=0.3, occluders=False, sensor_noise=False)
    variants = {
        "plain": InversePerspectiveMapping(IpmParams()),
        "metre": PlaneMotionCompensatedIPM(
            PlaneMotionCompensatedIpmParams(**AHEAD_MC, plane_baseline=1.0, plane_min_baseline=0.5)
        ),
        "default": PlaneMotionCompensatedIPM(PlaneMotionCompensatedIpmParams(**AHEAD_MC)),
    }
    result = evaluate(world, variants, range(560, 640))
    assert _longest_lock(result.errors["metre"]) >= 5, result.errors["metre"]
    assert _longest_lock(result.errors["default"]) < 5 and _longest_lock(result.errors["plain"]) == 0
    assert result.mean("default") < result.mean("plain") < 0.25
