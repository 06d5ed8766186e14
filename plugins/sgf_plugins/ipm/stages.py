"""The IPM stages (paper Sec. III-A): one resampling into the BEV, a compensation strategy per variant.

:class:`InversePerspectiveMapping` warps the image into the metric BEV; its compensation strategy
(:mod:`sgf_plugins.ipm.compensation`, :mod:`sgf_plugins.ipm.ahead`) decides the ``(psi, theta)``
of eq. 1-2 each frame is warped with. The registered variants pick their strategy:

- ``ipm=plain``: :class:`InversePerspectiveMapping`, :class:`~sgf_plugins.ipm.compensation.NoCompensation`;
- ``ipm=mc``: :class:`MotionCompensatedIPM`, :class:`~sgf_plugins.ipm.compensation.ReferenceCompensation`
  (``ipm=mc_ahead``: the same with the parameters of :data:`AHEAD_MC`);
- ``ipm=mc_plane``: :class:`PlaneMotionCompensatedIPM`, :class:`~sgf_plugins.ipm.ahead.GroundPlaneCompensation`;
- ``ipm=mc_hindsight``: :class:`HindsightMotionCompensatedIPM`, :class:`~sgf_plugins.ipm.ahead.HindsightCompensation`.
"""

from __future__ import annotations

import cv2
import numpy as np

from sgf_pipeline import DataError, RunContext, Stage
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.types import Bev, CameraImage, Frame
from sgf_plugins.ipm.ahead import GroundPlaneCompensation, HindsightCompensation
from sgf_plugins.ipm.compensation import (
    Compensation,
    MotionCompensation,
    NoCompensation,
    PoseQueueReference,
    ReferenceCompensation,
)
from sgf_plugins.ipm.hindsight import GroundAhead
from sgf_plugins.ipm.params import (
    AHEAD_MC,
    HindsightMotionCompensatedIpmParams,
    IpmParams,
    MotionCompensatedIpmParams,
    PlaneMotionCompensatedIpmParams,
)
from sgf_plugins.ipm.reference import PoseQueue, ReferenceAttitude
from sgf_plugins.shared.bev_homography import bev_to_image_homography, visible_mask
from sgf_plugins.shared.bev_region import choose_region

__all__ = [
    "AHEAD_MC",
    "HindsightMotionCompensatedIPM",
    "HindsightMotionCompensatedIpmParams",
    "InversePerspectiveMapping",
    "IpmParams",
    "MotionCompensatedIPM",
    "MotionCompensatedIpmParams",
    "PlaneMotionCompensatedIPM",
    "PlaneMotionCompensatedIpmParams",
]

_INTERPOLATION = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}


class InversePerspectiveMapping(Stage):
    """Plain IPM: the calibrated camera's view of a flat ground, resampled onto a metric BEV grid.

    The BEV's pixel <-> ground mapping is exactly its ``BevGrid`` (eq. 3-4 and eq. 9): ground
    coordinates in the robot's base frame on the ground plane. ``Bev.instance_ids`` is the frame's
    ground-truth instance mask warped with the same homography (nearest neighbour), so BEV masks
    align pixel for pixel. One ``cv2.warpPerspective`` per frame, or kornia with ``backend=kornia``.
    ``compensation``: the strategy giving each frame its ``(psi, theta)``; none for plain IPM.
    """

    kind = "ipm"
    name = "plain"
    output = "bev"
    Params = IpmParams

    def __init__(self, params: IpmParams, compensation: Compensation | None = None) -> None:
        super().__init__(params)
        self.params: IpmParams = params
        self.grid = params.grid
        self.compensator: Compensation = NoCompensation() if compensation is None else compensation
        self._checked: Calibration | None = None
        self._device: str | None = None

    @property
    def read_ahead(self) -> float:
        """The metres of path the runner reads ahead of each frame for this stage's strategy."""
        return self.compensator.read_ahead

    def begin(self, context: RunContext) -> None:
        """Forget the calibration checked, the region chosen and the strategy's state of the previous sequence."""
        self._checked = None
        self.grid = self.params.grid
        self.compensator.reset()

    def finalize(self, context: RunContext) -> None:
        """The region resampled (``ipm.region``) when it is not the configured one, then the strategy's counts."""
        if self.grid != self.params.grid:
            g = self.grid
            context.metrics.setdefault("ipm", {})["region"] = {
                "x_min": g.x_min,
                "x_max": g.x_max,
                "y_min": g.y_min,
                "y_max": g.y_max,
                "configured": [self.params.x_min, self.params.x_max, self.params.y_min, self.params.y_max],
            }
        entry = self.compensator.metrics()
        if entry:
            context.metrics.setdefault("ipm", {}).update(entry)

    def compensation(self, frame: Frame, image: np.ndarray | None = None) -> tuple[float, float]:
        """``(psi, theta)`` of eq. 1-2 for this frame from the strategy (``image``: the pixels the IPM warps)."""
        return self.compensator.compensate(frame, image, self.grid)

    def homography(self, calibration: Calibration, psi: float = 0.0, theta: float = 0.0) -> np.ndarray:
        """BEV index coordinates -> image pixels for this stage's grid, compensated by psi and theta (eq. 1-4)."""
        return bev_to_image_homography(calibration, self.grid, psi, theta, self.compensator.roll_axis)

    def process(self, frame: Frame, image: CameraImage) -> Bev:
        """The metric BEV of the frame's (enhanced) image."""
        pixels = image.pixels
        calibration = frame.calibration
        self._check(calibration, pixels)
        psi, theta = self.compensation(frame, pixels)
        h = self.homography(calibration, psi, theta)
        bev, valid = self.warp(pixels, h)
        ids = frame.truth_ids()
        instance_ids = None if ids is None else self.warp_ids(ids, h, valid, pixels.shape[:2])
        return Bev(
            bev, valid, self.grid, frame.index, frame.timestamp, instance_ids, roll=-psi, pitch=theta, homography=h
        )

    def warp(self, pixels: np.ndarray, homography: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Resample an image into the BEV; pixels outside the visible ground are zero."""
        if self.params.backend == "kornia":
            from sgf_plugins.ipm.kornia_backend import resolve_device, warp_image

            if self._device is None:
                self._device = resolve_device(self.params.device)
            return warp_image(pixels, homography, self.grid, self.params.interpolation, self._device)
        height, width = pixels.shape[:2]
        valid = visible_mask(homography, self.grid, width, height)
        bev = cv2.warpPerspective(
            pixels,
            homography,
            (self.grid.width, self.grid.height),
            flags=_INTERPOLATION[self.params.interpolation] | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return cv2.bitwise_and(bev, bev, mask=valid.view(np.uint8)), valid  # zero outside the view

    def warp_ids(
        self, ids: np.ndarray, homography: np.ndarray, valid: np.ndarray, image_shape: tuple[int, ...]
    ) -> np.ndarray:
        """Warp per-pixel instance ids with the same mapping, nearest neighbour (0 outside the view)."""
        if ids.shape[:2] != tuple(image_shape[:2]):
            raise DataError(f"instance id mask {ids.shape[:2]} does not match the image {tuple(image_shape[:2])}")
        source = ids.astype(np.int32) if ids.dtype not in (np.uint16, np.int32) else ids
        out = cv2.warpPerspective(
            source,
            homography,
            (self.grid.width, self.grid.height),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return cv2.bitwise_and(out, out, mask=valid.view(np.uint8))

    def _check(self, calibration: Calibration, pixels: np.ndarray) -> None:
        intr = calibration.intrinsics
        if pixels.ndim not in (2, 3) or pixels.shape[:2] != (intr.height, intr.width):
            raise DataError(
                f"image of shape {pixels.shape} does not match the calibration's {intr.width}x{intr.height} "
                "(the intrinsics must belong to the image the IPM receives)"
            )
        if calibration is self._checked:
            return
        if calibration.height <= 0.0:
            raise DataError(f"the camera is {calibration.height:.3f} m above the ground; IPM needs it above (> 0)")
        self.grid = choose_region(calibration, self.params.grid, self.params.region, "ipm")
        self._checked = calibration


class MotionCompensatedIPM(InversePerspectiveMapping):
    """MC-IPM: IPM compensated by the roll and pitch of the robot relative to a reference attitude (eq. 1-4).

    The strategy is :class:`~sgf_plugins.ipm.compensation.ReferenceCompensation`: the attitude
    against the pose queue's reference (:class:`~sgf_plugins.ipm.compensation.PoseQueueReference`).
    ``Bev.roll`` and ``Bev.pitch`` carry the compensated relative roll and pitch; the BEV shows the
    ground plane under the robot as seen at the reference attitude, so ground points lifted from
    it (eq. 9) belong with the planar part (x, y, yaw) of the robot's pose. ``finalize`` writes the
    reference's frame counts and ``max_abs_pitch_compensation`` to metrics.json under ``ipm``.

    Extensions, off by default and on in ``ipm=mc_ahead`` (:data:`AHEAD_MC`): ``reference_fit=line``
    with ``lookahead`` (the reference follows a hill's grade and the BEV's plane takes the grade
    ahead, :class:`~sgf_plugins.ipm.reference.PoseQueue`), and ``attitude_noise`` (the IMU's noise
    shrunk out of psi and theta). ``compensation``: a strategy of a variant built on MC-IPM.
    """

    name = "mc"
    Params = MotionCompensatedIpmParams
    compensator: MotionCompensation

    def __init__(self, params: MotionCompensatedIpmParams, compensation: MotionCompensation | None = None) -> None:
        super().__init__(params, ReferenceCompensation(params) if compensation is None else compensation)
        self.params: MotionCompensatedIpmParams = params

    @property
    def reference(self) -> PoseQueueReference:
        """The pose queue reference (for ``mc_plane`` and ``mc_hindsight``: mc_ahead's, which they build on)."""
        return self.compensator.reference

    @property
    def queue(self) -> PoseQueue:
        """The pose queue."""
        return self.reference.queue

    @property
    def last_reference(self) -> ReferenceAttitude | None:
        """The reference attitude of the last frame queued."""
        return self.reference.last_reference

    @property
    def counts(self) -> dict[str, int]:
        """The reference's frame counts."""
        return self.reference.counts

    def attitude(self, frame: Frame) -> tuple[float, float]:
        """The frame's ``(roll, pitch)`` in rad from the configured source."""
        return self.reference.attitude(frame)


class PlaneMotionCompensatedIPM(MotionCompensatedIPM):
    """MC-IPM whose BEV plane is the ground ahead as the camera sees it (extension of Sec. III-A).

    The strategy is :class:`~sgf_plugins.ipm.ahead.GroundPlaneCompensation`: the robot's own roll
    and pitch against its ground (a bump) come from the IMU as in ``ipm=mc_ahead``; the ground
    ahead's attitude, which no past pose knows at the foot or crest of a hill, is fitted to the
    current view and one about ``plane_baseline`` metres back. Until the first fit, and without an
    image, it is ``ipm=mc_ahead``. ``finalize`` adds ``plane_fits``, ``plane_skipped_bumps`` and
    ``plane_no_fit`` to metrics.json under ``ipm``.
    """

    name = "mc_plane"
    Params = PlaneMotionCompensatedIpmParams
    compensator: GroundPlaneCompensation

    def __init__(self, params: PlaneMotionCompensatedIpmParams) -> None:
        super().__init__(params, GroundPlaneCompensation(params))
        self.params: PlaneMotionCompensatedIpmParams = params

    @property
    def plane_counts(self) -> dict[str, int]:
        """How many frames had a plane fit, were skipped in a bump, or had none."""
        return self.compensator.counts


class HindsightMotionCompensatedIPM(MotionCompensatedIPM):
    """MC-IPM whose BEV plane is the ground ahead as the robot later drove over it (extension of Sec. III-A).

    The strategy is :class:`~sgf_plugins.ipm.ahead.HindsightCompensation`: the pipeline reads
    ``hindsight`` metres of path ahead of each frame (``Frame.path_ahead``, :attr:`read_ahead`),
    the plane of the ground within the BEV's reach is fitted to it, and the robot's attitude is
    compensated against that plane. Without a path (a robot feeding frames live, or one that turns
    out of the BEV or stops at the sequence's end) it is ``ipm=mc_ahead``. ``finalize`` adds
    ``hindsight_planes`` and ``hindsight_fallbacks`` to metrics.json under ``ipm``.
    """

    name = "mc_hindsight"
    Params = HindsightMotionCompensatedIpmParams
    compensator: HindsightCompensation

    def __init__(self, params: HindsightMotionCompensatedIpmParams) -> None:
        super().__init__(params, HindsightCompensation(params))
        self.params: HindsightMotionCompensatedIpmParams = params

    @property
    def hindsight_counts(self) -> dict[str, int]:
        """How many frames had a plane from the path ahead or fell back to mc_ahead."""
        return self.compensator.counts

    @property
    def last_ground(self) -> GroundAhead | None:
        """The plane of the last frame's path ahead (None: it fell back to mc_ahead)."""
        return self.compensator.last_ground
