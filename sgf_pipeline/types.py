"""Values that flow along the pipeline's edges, one class per kind of value.

Poses are 4x4 homogeneous matrices (float64). The robot's base frame has x forward, y left and
z up, with its origin on the ground under the robot; the camera frame is the optical frame
(x right, y down, z forward). Images are ``uint8``: ``(H, W, 3)`` RGB or ``(H, W)`` grey.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from sgf_pipeline.calibration import Calibration


class Frame:
    """One camera frame with the robot's odometry, IMU attitude and, when known, ground truth.

    The image may be given as a callable that loads it on first access, so that frames skipped
    by keyframe selection are never decoded or rendered.
    """

    __slots__ = (
        "_image",
        "calibration",
        "ground_truth",
        "imu_roll_pitch",
        "index",
        "instance_ids",
        "odometry",
        "path_ahead",
        "timestamp",
    )

    def __init__(
        self,
        index: int,
        timestamp: float,
        image: np.ndarray | Callable[[], np.ndarray],
        odometry: np.ndarray,
        calibration: Calibration,
        imu_roll_pitch: tuple[float, float] | None = None,
        ground_truth: np.ndarray | None = None,
        instance_ids: np.ndarray | Callable[[], np.ndarray | None] | None = None,
    ) -> None:
        self.index = index
        self.timestamp = timestamp
        self._image = image
        self.odometry = odometry
        self.calibration = calibration
        self.imu_roll_pitch = imu_roll_pitch
        self.ground_truth = ground_truth
        self.instance_ids = instance_ids
        #: The odometry and IMU of the frames after this one, when the runner read ahead for a stage
        #: that asked (:attr:`sgf_pipeline.stage.Stage.read_ahead`); ``None`` otherwise.
        self.path_ahead: PathAhead | None = None

    @property
    def image(self) -> np.ndarray:
        """The camera image (loaded on first access)."""
        if callable(self._image):
            self._image = self._image()
        return self._image

    @property
    def image_loaded(self) -> bool:
        """Whether the image has been loaded already."""
        return not callable(self._image)

    def truth_ids(self) -> np.ndarray | None:
        """Ground-truth marking instance per pixel (0 = no marking), or ``None`` when unknown."""
        if callable(self.instance_ids):
            self.instance_ids = self.instance_ids()
        return self.instance_ids

    def __repr__(self) -> str:
        return f"Frame(index={self.index}, timestamp={self.timestamp:.3f})"


@dataclass(frozen=True)
class PathAhead:
    """What the robot measured on the path it drove after a frame: the runner's read-ahead.

    ``odometry`` (M, 4, 4) and ``imu_roll_pitch`` (M, 2, rad; NaN where a frame had none) of the
    M frames that followed, in time order, every frame (keyframes or not) until the odometry had
    moved ``distance`` metres; ``complete`` is False when the sequence ended before that.
    """

    odometry: np.ndarray
    imu_roll_pitch: np.ndarray
    distance: float
    complete: bool

    def __post_init__(self) -> None:
        if self.odometry.ndim != 3 or self.odometry.shape[1:] != (4, 4):
            raise ValueError(f"PathAhead.odometry must be (M, 4, 4) poses, got shape {self.odometry.shape}")
        if self.imu_roll_pitch.shape != (len(self.odometry), 2):
            raise ValueError(
                f"PathAhead.imu_roll_pitch must be ({len(self.odometry)}, 2), got {self.imu_roll_pitch.shape}"
            )

    def __len__(self) -> int:
        return len(self.odometry)


@dataclass(frozen=True)
class CameraImage:
    """The camera image after enhancement, ready for IPM."""

    pixels: np.ndarray
    frame_index: int


@dataclass(frozen=True)
class BevGrid:
    """The metric grid of a bird's-eye view (the virtual camera of eq. 3-4).

    Row 0 is the far edge (``x_max``), column 0 the left edge (``y_max``); a pixel's centre is at
    ``(u + 0.5, v + 0.5)``. Ground coordinates are in the robot's base frame.
    """

    resolution: float
    x_min: float
    x_max: float
    y_min: float
    y_max: float

    @property
    def width(self) -> int:
        """Number of columns."""
        return round((self.y_max - self.y_min) / self.resolution)

    @property
    def height(self) -> int:
        """Number of rows."""
        return round((self.x_max - self.x_min) / self.resolution)

    @property
    def ground_to_pixel_matrix(self) -> np.ndarray:
        """3x3 affine map from ground ``(x, y, 1)`` to pixel ``(u, v, 1)`` (eq. 3-4)."""
        r = self.resolution
        return np.array([[0.0, -1.0 / r, self.y_max / r - 0.5], [-1.0 / r, 0.0, self.x_max / r - 0.5], [0.0, 0.0, 1.0]])

    def pixel_to_ground(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Metric ground coordinates ``(x, y)`` of pixel coordinates (eq. 9)."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        return self.x_max - (v + 0.5) * self.resolution, self.y_max - (u + 0.5) * self.resolution

    def ground_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates ``(u, v)`` of metric ground coordinates."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        return (self.y_max - y) / self.resolution - 0.5, (self.x_max - x) / self.resolution - 0.5


@dataclass(frozen=True)
class Bev:
    """A metric bird's-eye view of the ground in front of the robot."""

    image: np.ndarray
    valid: np.ndarray
    grid: BevGrid
    frame_index: int
    timestamp: float
    instance_ids: np.ndarray | None = None
    roll: float = 0.0
    pitch: float = 0.0
    homography: np.ndarray | None = None  # 3x3: BEV index (u, v, 1) -> the image pixel it was resampled from


@dataclass(frozen=True)
class SaliencyMap:
    """Per-pixel saliency in [0, 1] of a BEV."""

    probability: np.ndarray
    bev: Bev


@dataclass(frozen=True)
class SalientGroundFeature:
    """A selected SGF: the most salient view of one physical ground feature in one pass."""

    track_id: int
    frame_index: int
    timestamp: float
    odometry: np.ndarray
    pixels: np.ndarray
    grid: BevGrid
    saliency: float
    hu: np.ndarray
    views: int
    instance_id: int | None = None
    homography: np.ndarray | None = None  # the view's BEV -> image homography (``Bev.homography``)

    def without_pixels(self) -> SalientGroundFeature:
        """A copy without the BEV pixels: what a long-lived record keeps (a descriptor's points hold the shape)."""
        if np.asarray(self.pixels).size == 0 and self.homography is None:
            return self
        return replace(self, pixels=np.zeros((0, 2), dtype=np.int32), homography=None)


@dataclass(frozen=True)
class SgfDetections:
    """The SGFs selected on one frame (often none)."""

    items: tuple[SalientGroundFeature, ...] = ()


@dataclass(frozen=True)
class SgfDescriptor:
    """The polar descriptor of an SGF's metric ground points (eq. 9-10)."""

    sgf: SalientGroundFeature
    points: np.ndarray
    centroid: np.ndarray
    matrix: np.ndarray
    ring_key: np.ndarray

    def without_pixels(self) -> SgfDescriptor:
        """A copy whose SGF has no BEV pixels (an SGF group keeps its members so)."""
        sgf = self.sgf.without_pixels()
        return self if sgf is self.sgf else replace(self, sgf=sgf)


@dataclass(frozen=True)
class SgfDescriptors:
    """The descriptors made on one frame."""

    items: tuple[SgfDescriptor, ...] = ()


@dataclass(frozen=True)
class GroupAssignment:
    """An SGF descriptor assigned to an SGF group (eq. 10).

    ``symmetric`` groups (a round manhole) give no loop factors. ``ambiguous`` marks a match eq. 10
    cannot vouch for: an ``aliased`` group (a repeated pattern such as the triangles of a give-way
    row), or look-alike groups inside the spatial gate that tie with the chosen one; then
    ``alternatives`` holds the closest member of each tied group, for a loop stage that can tell
    them apart by other evidence (their neighbouring SGFs).
    """

    descriptor: SgfDescriptor
    group_id: int
    new_group: bool
    distance: float
    shift: int
    yaw: float
    matched: SgfDescriptor | None
    symmetric: bool
    ambiguous: bool = False
    aliased: bool = False
    alternatives: tuple[LookAlike, ...] = ()


@dataclass(frozen=True)
class LookAlike:
    """A group tied with the chosen one by eq. 10: its closest member and that member's relative yaw."""

    group_id: int
    matched: SgfDescriptor
    shift: int
    yaw: float


@dataclass(frozen=True)
class GroupAssignments:
    """The group assignments made on one frame."""

    items: tuple[GroupAssignment, ...] = ()


@dataclass(frozen=True)
class LoopConstraint:
    """A relative-pose constraint between two robot poses from an SGF match (eq. 11).

    ``relative`` is the 4x4 pose of ``frame_to``'s base in ``frame_from``'s base; ``covariance``
    is 3x3 over the planar part ``(x, y, yaw)`` of that relative pose, in its local (right)
    tangent space (GTSAM's ``Pose2`` convention). With ``from_map``, ``frame_from`` is a frame
    of the prior SGF map (:mod:`sgf_pipeline.sgf_map`), not of this run: an inter-session factor.
    With ``marking`` (a round marking, whose heading cannot be read: a position-only loop), the
    constraint fixes where that marking, at ``marking`` (x, y) in ``frame_to``'s base, lies from
    both poses, not the turn between them: ``relative``'s turn about the marking is the estimate's,
    and ``covariance`` leaves it almost free.
    """

    frame_from: int
    frame_to: int
    relative: np.ndarray
    covariance: np.ndarray
    group_id: int
    reverse: bool
    fitness: float
    inlier_ratio: float
    instance_ids: tuple[int | None, int | None] = (None, None)
    from_map: bool = False
    marking: tuple[float, float] | None = None

    @property
    def position_only(self) -> bool:
        """Whether the constraint fixes only where its marking lies (see ``marking``)."""
        return self.marking is not None


@dataclass(frozen=True)
class LoopConstraints:
    """The loop constraints found on one frame."""

    items: tuple[LoopConstraint, ...] = ()


@dataclass(frozen=True)
class OdometryScale:
    """A factor on the odometry's distances (true distance = factor x odometry distance), as estimated so far.

    ``sigma`` is the factor's standard deviation (inf while too few measurements); ``pairs`` the
    measurements behind it. The back-end multiplies each new odometry step's translation by ``factor``.
    ``yaw_bias`` (rad/m) is the odometry's heading bias (it turns that much more to the left per metre
    than the ground does) and ``yaw_bias_sigma`` its standard deviation (inf while unmeasured).
    ``sigma_xy`` (m/sqrt(m)) and ``sigma_yaw`` (rad/sqrt(m)) are the odometry's distance and heading
    random walks as measured, upper bounds with their uncertainty (inf while unmeasured).
    """

    factor: float
    sigma: float
    pairs: int
    yaw_bias: float = 0.0
    yaw_bias_sigma: float = math.inf
    sigma_xy: float = math.inf
    sigma_yaw: float = math.inf


@dataclass(frozen=True)
class OdometryDrift:
    """The odometry's errors left in the back-end's estimate, as measured so far (None: not measured).

    ``scale_error`` (a fraction of the distance) is the uncertainty of the scale factor the back-end
    applies; ``sigma_xy`` (m/sqrt(m)) and ``sigma_yaw`` (rad/sqrt(m)) are the random walks of the
    odometry's distance and heading. The gates size their drift by them, by their priors where None.
    """

    scale_error: float | None = None
    sigma_xy: float | None = None
    sigma_yaw: float | None = None


@dataclass(frozen=True)
class YawBiasCorrection:
    """The back-end's model of the odometry's heading bias per metre, which the gates size their drift by.

    The bias is taken off the odometry steps after frame ``since`` (None: off none of them);
    ``sigma`` (rad/m) is the uncertainty of the bias left in those steps, ``uncorrected`` (rad/m)
    the root mean square of the bias in the steps no correction covers, as the back-end knows it now.
    """

    since: int | None
    sigma: float
    uncorrected: float


@dataclass(frozen=True)
class PoseEstimate:
    """The back-end's current estimate of every processed frame's pose (map frame).

    A snapshot: a back-end publishes a new one whenever a pose changes and never alters one it has
    published, so stages may cache what they derive from it by its identity.
    """

    frame_index: int
    poses: Mapping[int, np.ndarray]
    #: the back-end's correction of the odometry's heading bias, None while it makes none
    yaw_bias: YawBiasCorrection | None = None
    #: the odometry's scale error and random walks as measured, None while nothing is
    drift: OdometryDrift | None = None

    @property
    def latest(self) -> np.ndarray:
        """The estimated pose of the newest frame."""
        return self.poses[self.frame_index]

    def stack(self, frames: Sequence[int] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The poses of ``frames`` as (K, 4, 4), NaN where the estimate has none, and the (K,) mask of found ones.

        Uses the mapping's own ``take(frames)`` (same result) when it has one, so that a back-end's
        table answers thousands of frames without a Python lookup each.
        """
        take = getattr(self.poses, "take", None)
        if take is not None:
            poses, found = take(frames)
            return np.asarray(poses, dtype=np.float64), np.asarray(found, dtype=bool)
        out = np.full((len(frames), 4, 4), np.nan)
        found = np.zeros(len(frames), dtype=bool)
        for k, f in enumerate(frames):
            pose = self.poses.get(int(f))
            if pose is not None:
                out[k], found[k] = pose, True
        return out, found
