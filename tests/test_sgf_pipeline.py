"""The SGF stages in the runner: registration, wiring, a synthetic campus loop, metrics.json, and the configs."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from sgf_plugins.sgf.association.stage import OnlineGroupsParams
from sgf_plugins.sgf.descriptor import PolarContextParams
from sgf_plugins.sgf.detector import HuWindowParams
from sgf_synthetic import (
    Annulus,
    ConvexPart,
    GroundShape,
    SaliencyStream,
    arrow_shape,
    ell_shape,
    rectangle,
    tee_shape,
)
from sgf_testing import conf_node

from sgf_pipeline import Dataset, Pipeline, RunContext, Stage, hookimpl, load_plugins
from sgf_pipeline.geometry import pose_from_xy_yaw
from sgf_pipeline.truth import SequenceTruth
from sgf_pipeline.types import Bev, Frame, SaliencyMap

ROOT = Path(__file__).resolve().parents[1]


class Recorded:
    """A synthetic stream rendered once: frames, BEVs, saliency maps and the truth of its passes."""

    frames: ClassVar[list[Frame]] = []
    bevs: ClassVar[dict[int, Bev]] = {}
    saliency: ClassVar[dict[int, SaliencyMap]] = {}
    truth: ClassVar[SequenceTruth | None] = None


class StreamDataset(Dataset):
    """Test dataset: the recorded stream's frames, with its ground truth."""

    name = "sgf_test_stream"

    def frames(self) -> Iterator[Frame]:
        yield from Recorded.frames

    def __len__(self) -> int:
        return len(Recorded.frames)

    def begin(self, context: RunContext) -> None:
        context.truth = Recorded.truth


class RecordedBev(Stage):
    """Test IPM: the recorded BEV of the frame."""

    kind = "ipm"
    name = "sgf_test_bev"
    output = "bev"

    def process(self, frame: Frame) -> Bev:
        return Recorded.bevs[frame.index]


class RecordedSaliency(Stage):
    """Test saliency: the recorded saliency map of the BEV."""

    kind = "saliency"
    name = "sgf_test_saliency"
    output = "saliency"

    def process(self, bev: Bev) -> SaliencyMap:
        return Recorded.saliency[bev.frame_index]


class TestPlugin:
    """Registers the recorded-stream stages."""

    @hookimpl
    def sgf_register_stages(self, registry) -> None:
        registry.add(StreamDataset)
        registry.add(RecordedBev)
        registry.add(RecordedSaliency)


def campus_loop() -> tuple[list[GroundShape], list[np.ndarray], list[np.ndarray]]:
    """Out along a street past seven markings (two identical arrows 13.5 m apart), a U-turn, and back.

    The odometry drifts (1 % scale, 0.02 deg of heading per step) so the way back is seen about
    half a metre off: the spatial gate must allow for it and still keep the two arrows apart.
    """
    diamond = (ConvexPart(np.array([[-0.8, 0.0], [0.0, -0.4], [0.8, 0.0], [0.0, 0.4]])),)
    shapes = [
        GroundShape(arrow_shape(), (5.03, 0.21, 0.05), 1),
        GroundShape((Annulus(0.3),), (9.52, -0.38, 0.0), 2),
        GroundShape(ell_shape(), (14.01, 0.27, 1.0), 3),
        GroundShape(arrow_shape(), (18.53, 0.21, 0.05), 4),  # the same design as instance 1
        GroundShape((rectangle(1.5, 0.3),), (22.94, 0.02, 1.2), 5),
        GroundShape(diamond, (27.47, 0.13, -0.5), 6),
        GroundShape(tee_shape(), (31.05, -0.12, 2.5), 7),
    ]
    step, turn = 0.3, 38.0
    poses = [pose_from_xy_yaw(i * step, 0.0, 0.0) for i in range(int(turn / step))]
    for i in range(1, 12):  # the U-turn: a half circle of radius 0.35 m
        angle = math.pi * i / 12
        poses.append(pose_from_xy_yaw(turn + 0.35 * math.sin(angle), 0.35 - 0.35 * math.cos(angle), angle))
    poses += [pose_from_xy_yaw(turn - i * step, 0.7, math.pi) for i in range(int(turn / step))]
    odometry = [poses[0]]
    for a, b in itertools.pairwise(poses):
        d = np.linalg.inv(a) @ b
        noisy = pose_from_xy_yaw(1.01 * d[0, 3], d[1, 3], math.atan2(d[1, 0], d[0, 0]) + math.radians(0.02))
        odometry.append(odometry[-1] @ noisy)
    return shapes, poses, odometry


@pytest.fixture(scope="module")
def recorded():
    shapes, poses, odometry = campus_loop()
    stream = SaliencyStream(shapes, poses, odometry=odometry, supersample=2)
    Recorded.frames, Recorded.bevs, Recorded.saliency = [], {}, {}
    for frame, bev, saliency in stream:
        Recorded.frames.append(frame)
        Recorded.bevs[frame.index] = bev
        Recorded.saliency[frame.index] = saliency
    Recorded.truth = stream.truth()
    return Recorded


def config(run_dir_plots: bool = False) -> dict:
    return {
        "pipeline": ["dataset", "ipm", "saliency", "detector", "descriptor", "association"],
        "dataset": {"name": "sgf_test_stream"},
        "ipm": {"name": "sgf_test_bev"},
        "saliency": {"name": "sgf_test_saliency"},
        "detector": conf_node("detector/hu_window.yaml"),
        "descriptor": conf_node("descriptor/polar_context.yaml"),
        "association": conf_node("association/online_groups.yaml"),
        "run": {"progress": False, "plots": run_dir_plots},
    }


def test_configs_hold_the_paper_defaults():
    assert HuWindowParams().hu_threshold == 0.005
    p = PolarContextParams()
    assert (p.max_radius, p.num_sectors, p.num_rings) == (2.0, 90, 10)
    assert OnlineGroupsParams().match.new_group_distance == 0.7


def test_stages_are_registered_through_entry_points():
    registry = load_plugins().registry
    assert registry.get("detector", "hu_window").signature.output_types[0].__name__ == "SgfDetections"
    assert registry.get("descriptor", "polar_context").cls.output == "descriptors"
    inputs = {i.parameter: i for i in registry.get("association", "online_groups").signature.inputs}
    assert inputs["estimate"].previous and inputs["estimate"].optional
    assert [i.parameter for i in registry.get("detector", "hu_window").signature.inputs] == ["frame", "bev", "saliency"]


def test_a_synthetic_loop_through_the_runner(recorded, tmp_path):
    plugins = load_plugins(extra=[("sgf_test_stream", TestPlugin())])
    pipeline = Pipeline.from_config(config(), run_dir=tmp_path / "run", plugins=plugins)
    groups_by_frame = {}
    for frame in pipeline.frames():
        step = pipeline.process(frame)
        for a in step.outputs["assignments"].items:
            groups_by_frame[a.descriptor.sgf.frame_index] = a
    metrics = pipeline.finish()
    written = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert written["sgf"] == metrics["sgf"]
    truth = recorded.truth
    assert len(truth.on_path) == 7 and len(truth.revisits) == 7
    assert metrics["sgf"]["detected"] == 7 and metrics["sgf"]["total"] == 7
    assert metrics["sgf"]["selected"] == 14  # one per marking per pass
    assert metrics["sgf"]["purity"] == 1.0 and metrics["sgf"]["groups"] == 7
    assert metrics["sgf"]["symmetric_groups"] == 1  # the round manhole
    loops = metrics["loops"]
    assert (loops["pairs_found"], loops["pairs_total"]) == (7, 7)
    assert (loops["pairs_found_reverse"], loops["pairs_total_reverse"]) == (7, 7)
    # Every revisit is matched to its first pass with a yaw of about 180 degrees (a reverse loop).
    for a in groups_by_frame.values():
        if not a.new_group:
            assert a.matched is not None and a.matched.sgf.instance_id == a.descriptor.sgf.instance_id
            if not a.symmetric:
                assert abs(math.degrees(a.yaw)) > 170.0
    groups = pipeline.context.artifacts["sgf_groups"]
    assert sorted(len(g.members) for g in groups) == [2] * 7


def test_without_the_spatial_gate_identical_arrows_merge(recorded):
    """Perceptual aliasing: the two arrows share one design; only the gate keeps their groups apart."""
    cfg = config()
    cfg["association"]["gate"]["enabled"] = False
    plugins = load_plugins(extra=[("sgf_test_stream", TestPlugin())])
    metrics = Pipeline.from_config(cfg, plugins=plugins).run()
    assert metrics["sgf"]["detected"] == 7
    assert metrics["sgf"]["mixed_groups"] >= 1 and metrics["sgf"]["purity"] < 1.0


def test_the_learning_free_detector_drives_the_same_loop(recorded, tmp_path):
    """``saliency=classical`` (top-hat and threshold on the recorded BEVs) drives the same loop."""
    plugins = load_plugins(extra=[("sgf_test_stream", TestPlugin())])
    cfg = config()
    cfg["saliency"] = conf_node("saliency/classical.yaml")
    pipeline = Pipeline.from_config(cfg, run_dir=tmp_path / "run", plugins=plugins)
    for frame in pipeline.frames():
        pipeline.process(frame)
    metrics = pipeline.finish()
    sgf, loops = metrics["sgf"], metrics["loops"]
    # The recorded BEVs are grey (a mono camera): the detector takes them as they are.
    assert (sgf["detected"], sgf["total"], sgf["selected"], sgf["false_selected"]) == (7, 7, 14, 0)
    assert sgf["purity"] == 1.0 and sgf["groups"] == 7 and sgf["symmetric_groups"] == 1
    assert (loops["pairs_found"], loops["pairs_found_reverse"], loops["pairs_total"]) == (7, 7, 7)
