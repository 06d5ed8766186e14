"""The SGF descriptor (Sec. III-C, eq. 9): metric ground points of a selected SGF and their polar context."""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from pydantic import Field

from sgf_pipeline import RunContext, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.geometry import invert, rotation_rpy, rpy_from_rotation
from sgf_pipeline.imu import steadied_roll_pitch
from sgf_pipeline.types import Frame, SalientGroundFeature, SgfDescriptor, SgfDescriptors, SgfDetections
from sgf_plugins.sgf.terrain import driven_ground, intersect_ground, march_ground, pixel_rays, wheel_ground
from sgf_plugins.shared.frame_log import FrameLog
from sgf_plugins.shared.polar import polar_context, ring_key, voxel_downsample

#: Frames of odometry the driven-ground lift remembers (a feature's valid range is far shorter).
TERRAIN_FRAMES = 2_000
#: IMU roll or pitch (rad) beyond which level odometry is taken for planar odometry that left the attitude out.
PLANAR_ATTITUDE = 0.01
log = logging.getLogger("sgf_pipeline.sgf")


class PolarContextParams(StageParams):
    """Downsampling and the polar grid of the descriptor (paper: L_max = 2 m, N_s = 90, N_r = 10)."""

    max_radius: float = Field(2.0, gt=0.0, description="L_max: radius (m) of the descriptor around the centroid")
    num_sectors: int = Field(90, ge=4, description="N_s: azimuth sectors (2 pi / N_s each)")
    num_rings: int = Field(10, ge=1, description="N_r: rings (L_max / N_r each)")
    voxel_size: float = Field(0.02, ge=0.0, description="voxel grid (m) for downsampling the SGF points; 0 = none")
    bin_value: Literal["count", "density", "occupancy"] = Field(
        "count", description="bin value: ground points in the bin, points per square metre, or 0/1 occupancy"
    )
    min_points: int = Field(3, ge=1, description="SGFs with fewer ground points after downsampling are dropped")
    ground: Literal["plane", "driven"] = Field(
        "driven",
        description="where eq. 9 puts the SGF pixels: on the BEV's plane (the paper), or where their camera rays meet "
        "the ground the robot drove over since the view (3-D odometry: heights and the IMU's attitude)",
    )
    ground_ahead: float = Field(
        3.0, ge=0.0, description="driven: metres the newest pose's tangent plane is extended ahead (the far paint)"
    )
    ground_radius: float = Field(
        3.0, gt=0.0, description="driven: an SGF with a pixel farther (m) from every ground sample stays on the plane"
    )
    ground_model: Literal["base", "wheels"] = Field(
        "base",
        description="driven: the ground is the base poses' tangent planes, each ray meeting its nearest one (base), "
        "or the wheels' contact tracks, each ray marched to its first crossing, the SGF lifted once the robot has "
        "driven past its paint (wheels: paint on a speed bump lands on the bump)",
    )
    ground_contacts: tuple[float, ...] = Field(
        (0.25, -0.25),
        min_length=1,
        description="wheels: where the wheels touch the ground (m ahead of the base origin; the world's robot: "
        "wheelbase 0.5 m, centred)",
    )
    attitude_window: float = Field(
        0.0,
        ge=0.0,
        description="driven: metres of driving on either side of the view whose median odometry (IMU) roll and pitch "
        "is the camera's, the view's own deviation from it counted through attitude_noise (0.6 steadies the "
        "lift: the IMU's noise tilts the whole driven ground under the camera, 0.25 degrees stretch paint 4.4 m "
        "ahead by 6 %); 0 = the view's own attitude (the default: not better on Tables 2 and 3, docs/method.md)",
    )
    attitude_noise: float = Field(
        0.005,
        ge=0.0,
        description="driven: sigma (rad, about twice the IMU's roll/pitch noise); the view's deviation d from the "
        "median counts d^3 / (d^2 + sigma^2): noise mostly dropped, a bump's pitch kept",
    )
    ground_past: float | None = Field(
        0.5,
        ge=0.0,
        description="wheels: an SGF waits until the robot has driven this far (m) past its farthest pixel, so the "
        "ground under the marking is measured before the lift; null = lift at selection",
    )


def lift(sgf: SalientGroundFeature) -> np.ndarray:
    """Eq. 9: the SGF's pixels as metric ground points (M, 2) in its frame's base frame, on the BEV's plane."""
    pixels = np.asarray(sgf.pixels).reshape(-1, 2)
    x, y = sgf.grid.pixel_to_ground(pixels[:, 0], pixels[:, 1])
    return np.stack([x, y], axis=1)


def lift_driven(
    sgf: SalientGroundFeature,
    calibration: Calibration,
    driven: np.ndarray,
    ahead: float,
    radius: float,
    contacts: tuple[float, ...] | None = None,
    view_roll_pitch: tuple[float, float] | None = None,
) -> np.ndarray | None:
    """The SGF's pixels where their camera rays meet the driven ground (M, 2), or None where it does not cover them.

    ``driven``: odometry poses (N, 4, 4) from the SGF's frame on (the first is its frame's).
    ``contacts``: None for the base poses' tangent planes (``ground_model=base``), else the wheels'
    positions ahead of the base origin (``ground_model=wheels``); then pixels whose rays skimmed a
    crest before meeting the ground are left out (fewer rows than pixels). ``view_roll_pitch``: the
    camera's roll and pitch (rad) when known better than from the view's own odometry pose.
    """
    if sgf.homography is None or len(driven) == 0:
        return None
    view = np.asarray(driven[0], dtype=np.float64)
    if view_roll_pitch is not None:
        view = view.copy()
        view[:3, :3] = rotation_rpy(*view_roll_pitch, rpy_from_rotation(view[:3, :3])[2])
    local = invert(view) @ np.asarray(driven, dtype=np.float64)  # poses in the view's base frame
    origin, directions = pixel_rays(np.asarray(sgf.pixels), sgf.homography, calibration)
    if contacts is None:
        points, normals = driven_ground(local, ahead, step=0.25)
        hit, covered = intersect_ground(origin, directions, points, normals, radius)
    else:
        points, normals = wheel_ground(local, ahead, step=0.25, contacts=contacts)
        hit, covered = march_ground(origin, directions, points, normals, radius)
    if not covered.all():
        return None
    return hit[np.isfinite(hit[:, 0]), :2]


def describe(
    sgf: SalientGroundFeature,
    params: PolarContextParams,
    ground: np.ndarray | None = None,
) -> SgfDescriptor | None:
    """The descriptor of one SGF, or None when fewer than ``min_points`` ground points lie within L_max.

    ``ground``: the SGF pixels' metric points (M, 2) when lifted otherwise than by eq. 9 on the BEV's plane.
    """
    points = voxel_downsample(lift(sgf) if ground is None else ground, params.voxel_size)
    if len(points) < params.min_points:
        return None
    centroid = points.mean(axis=0)
    if np.count_nonzero(np.hypot(*(points - centroid).T) < params.max_radius) < params.min_points:
        return None  # a ring wider than L_max: an empty descriptor, which eq. 10 can never match
    matrix = polar_context(points, centroid, params.num_rings, params.num_sectors, params.max_radius, params.bin_value)
    return SgfDescriptor(sgf=sgf, points=points, centroid=centroid, matrix=matrix, ring_key=ring_key(matrix))


class PolarContext(Stage):
    """Lift each selected SGF to metric ground points (eq. 9), downsample, and describe it around its centroid.

    Points are in the robot's base frame of the SGF's own frame; sectors count counter-clockwise
    from its heading. The bin value is an ambiguity of the paper: Scan Context stores the largest
    height in a bin, but every SGF point lies on the ground (z ~ 0). Here the default is the
    ``count`` of ground points in the bin, which after voxel downsampling is the marking's area in
    the bin (a density per bin). Eq. 10 normalises every column, so the options differ only in how
    they weight rings: ``density`` (per square metre) lifts the few points of the inner rings,
    ``occupancy`` drops the radial extent. Over 12 rendered markings seen from 5 headings with
    noisy masks (bench/bench_sgf.py), ``count`` separates the same marking (eq. 10 p95 0.043)
    from different ones (p5 0.131) best, against 0.062/0.085 for ``density``, and gives the
    smallest yaw error (p95 3.2 degrees). The default voxel (2 cm) is the BEV's pixel: at 4 cm
    the 4-degree sectors of the inner rings empty out and the same-marking median rises five-fold
    (0.021 to 0.104), overlapping different markings.

    ``ground=driven`` lifts the pixels along their camera rays onto the ground the robot drove
    over between the view and the SGF's selection (``sgf_plugins.sgf.terrain``), instead of onto
    the BEV's plane: where the grade changes under a marking the plane misplaces it by about
    d^2 / h times the change (docs/method.md, "SGF points on the ground driven over").
    """

    kind = "descriptor"
    name = "polar_context"
    output = "descriptors"
    Params = PolarContextParams

    def __init__(self, params: PolarContextParams) -> None:
        super().__init__(params)
        self.params: PolarContextParams = params
        self._dropped = 0
        self._frames = FrameLog(keep=TERRAIN_FRAMES)
        self._ground: dict[str, int] = {}
        self._warned = False
        self._waiting: list[tuple[float, SalientGroundFeature]] = []

    def begin(self, context: RunContext) -> None:
        """Reset the counts and the odometry; announce the descriptor's shape (N_r, N_s) to later stages."""
        self._dropped = 0
        self._frames = FrameLog(keep=TERRAIN_FRAMES)
        self._ground = {"driven": 0, "plane": 0}
        self._warned = False
        self._waiting = []
        context.artifacts["descriptor_shape"] = (self.params.num_rings, self.params.num_sectors)

    def process(self, frame: Frame, sgfs: SgfDetections) -> SgfDescriptors:
        """The descriptors of this frame's selected SGFs."""
        p = self.params
        items: list[SalientGroundFeature] = list(sgfs.items)
        if p.ground == "driven":
            self._frames.append(frame)
            self._check_attitude(frame)
            if p.ground_model == "wheels" and p.ground_past is not None:
                items = self._ready(items, p.ground_past)
        out = []
        for sgf in items:
            ground = None
            if p.ground == "driven":
                if sgf.frame_index in self._frames:  # the view's odometry, and all since, are remembered
                    driven = self._frames.odometry_since(sgf.frame_index)
                    contacts = p.ground_contacts if p.ground_model == "wheels" else None
                    attitude = self._view_attitude(sgf.frame_index)
                    ground = lift_driven(
                        sgf, frame.calibration, driven, p.ground_ahead, p.ground_radius, contacts, attitude
                    )
                self._ground["plane" if ground is None else "driven"] += 1
            descriptor = describe(sgf, p, ground)
            if descriptor is None:
                self._dropped += 1
            else:
                out.append(descriptor)
        return SgfDescriptors(tuple(out))

    def _view_attitude(self, frame_index: int) -> tuple[float, float] | None:
        """The view's roll and pitch steadied over ``attitude_window`` (None: the view's own)."""
        if self.params.attitude_window <= 0.0:
            return None
        poses, k = self._frames.around(frame_index, self.params.attitude_window)
        roll_pitch = np.array([rpy_from_rotation(pose[:3, :3])[:2] for pose in poses])
        return steadied_roll_pitch(roll_pitch, k, self.params.attitude_noise)

    def _ready(self, new: list[SalientGroundFeature], past: float) -> list[SalientGroundFeature]:
        """The SGFs whose ground has been driven: ``past`` metres beyond their farthest pixel since their view."""
        travelled = self._frames.travelled
        for sgf in new:
            since = self._frames.get_distance(sgf.frame_index)
            if since is None:
                self._waiting.append((-np.inf, sgf))  # its view is forgotten: lifted on the plane at once
            else:
                self._waiting.append((since + float(lift(sgf)[:, 0].max()) + past, sgf))
        ready = [sgf for due, sgf in self._waiting if due <= travelled]
        self._waiting = [(due, sgf) for due, sgf in self._waiting if due > travelled]
        return ready

    def _check_attitude(self, frame: Frame) -> None:
        """Warn once when the odometry is level while the IMU is not: planar odometry gives the lift no attitude."""
        if self._warned or frame.imu_roll_pitch is None:
            return
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        level = abs(odometry[2, 0]) < 1e-9 and abs(odometry[2, 1]) < 1e-9
        if level and max(abs(a) for a in frame.imu_roll_pitch) > PLANAR_ATTITUDE:
            self._warned = True
            roll, pitch = frame.imu_roll_pitch
            log.warning(
                "descriptor.ground=driven: frame %d's odometry is level but the IMU reads roll %.3f, pitch %.3f rad; "
                "with planar odometry the SGF points are lifted without the robot's attitude (as plain IPM would); "
                "set descriptor.ground=plane to keep the IPM's compensation",
                frame.index,
                roll,
                pitch,
            )

    def finalize(self, context: RunContext) -> None:
        """Report how many SGFs had too few points to describe."""
        sgf = context.metrics.setdefault("sgf", {})
        sgf["too_few_points"] = self._dropped
        if self._waiting:
            sgf["waiting_for_ground_at_end"] = len(self._waiting)
        if self.params.ground == "driven":
            sgf["lifted_on_driven_ground"] = self._ground["driven"]
            sgf["lifted_on_plane"] = self._ground["plane"]


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the polar context descriptor."""
    registry.add(PolarContext)
