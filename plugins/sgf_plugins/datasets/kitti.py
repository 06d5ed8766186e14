"""``dataset=kitti``: a KITTI odometry sequence (``image_0/``, ``calib.txt``, ``times.txt``, ``poses/NN.txt``).

KITTI's poses are those of the left camera (``cam0``, optical frame: z forward, y down) in the
frame of ``cam0`` at the first image. The pipeline wants poses of the robot's base (x forward,
y left, z up, origin on the ground under the camera), so each camera pose ``T_i`` becomes
``B_i = C T_i C^-1`` with ``C`` = camera_to_base: the base of the first frame is the world
origin. ``C`` is the KITTI mounting: the camera 1.65 m above the road, looking level
(``camera_height``, ``camera_pitch``). Ground truth is the poses file; the odometry is the same
poses (a perfect odometry) unless ``odometry`` names a file of estimated camera poses (KITTI
format), e.g. a visual odometry's output, converted the same way.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import numpy as np
from pydantic import Field

from sgf_pipeline import DataError, RunContext, StageParams, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration, Intrinsics, camera_to_base_from_mounting
from sgf_pipeline.calibration_io import image_size, intrinsics_from_projection, kitti_projection, read_kitti_calib
from sgf_pipeline.geometry import invert
from sgf_pipeline.trajectory import TrajectoryError, read_kitti, read_times
from sgf_pipeline.types import Frame
from sgf_plugins.datasets._common import RecordedDataset, RecordedParams, describe_dir, read_image_file

#: KITTI's camera height above the road (m), from the KITTI sensor setup.
KITTI_CAMERA_HEIGHT = 1.65


class KittiIntrinsics(StageParams):
    """Pinhole intrinsics given in the config instead of ``calib.txt`` (all four required)."""

    fx: float = Field(gt=0.0, description="focal length x (px)")
    fy: float = Field(gt=0.0, description="focal length y (px)")
    cx: float = Field(description="principal point x (px)")
    cy: float = Field(description="principal point y (px)")


class KittiParams(RecordedParams):
    """Options of the KITTI odometry reader (empty paths take KITTI's own layout under ``path``)."""

    camera: str = Field("image_0", description="image folder: image_0/image_1 (grey), image_2/image_3 (colour)")
    calib: str = Field("", description="calib.txt (default: <path>/calib.txt)")
    times: str = Field("", description="times.txt (default: <path>/times.txt)")
    poses: str = Field(
        "", description="ground-truth poses (default: <path>/poses.txt or <path>/../../poses/<sequence>.txt)"
    )
    odometry: str = Field("", description="estimated camera poses (KITTI format) used as odometry; default: poses")
    intrinsics: KittiIntrinsics | None = Field(None, description="fx, fy, cx, cy; overrides calib.txt")
    camera_height: float = Field(KITTI_CAMERA_HEIGHT, gt=0.0, description="camera centre above the road (m)")
    camera_pitch: float = Field(
        0.0, ge=-math.pi / 2, le=math.pi / 2, description="optical axis below the horizon (rad, positive down)"
    )
    sequence: str = Field("", description="sequence name in reports (default: the folder's name)")


class KittiDataset(RecordedDataset):
    """A KITTI odometry sequence, poses converted from the camera to the base convention."""

    name = "kitti"
    Params = KittiParams
    params: KittiParams

    def __init__(self, params: KittiParams) -> None:
        super().__init__(params)
        root = self.recording_dir("sequence folder (.../sequences/00)")
        self.root = root
        image_dir = root / params.camera
        self.images = sorted(p for p in image_dir.glob("*.png")) if image_dir.is_dir() else []
        if not self.images:
            raise DataError(f"no PNG images in {image_dir} (dataset.camera={params.camera}); {describe_dir(root)}")
        n = len(self.images)
        self.camera_to_base = camera_to_base_from_mounting(params.camera_height, params.camera_pitch)
        self.calibration = self.prepare_calibration(
            Calibration(intrinsics=self._intrinsics(), camera_to_base=self.camera_to_base)
        )
        self.timestamps = self._times(n)
        self.ground_truth = self._poses(self._poses_path(), n, "poses")
        odometry = self._poses(Path(params.odometry).expanduser(), n, "odometry") if params.odometry else None
        if odometry is None:
            odometry = self.ground_truth
        if odometry is None:
            raise DataError(
                f"KITTI sequence {root} has no poses file (sequences 11-21 have none): give dataset.poses=<file> "
                "or an estimated trajectory with dataset.odometry=<file in KITTI format>"
            )
        self.odometry: np.ndarray = odometry

    def _intrinsics(self) -> Intrinsics:
        width, height = image_size(self.images[0])
        if self.params.intrinsics is not None:
            k = self.params.intrinsics
            return Intrinsics(fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, width=width, height=height)
        calib = Path(self.params.calib).expanduser() if self.params.calib else self.root / "calib.txt"
        if not calib.is_file():
            raise DataError(
                f"KITTI calibration {calib} not found ({describe_dir(calib.parent)}). Give dataset.calib=<calib.txt> "
                "or the intrinsics: dataset.intrinsics='{fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157}'"
            )
        digits = "".join(ch for ch in self.params.camera if ch.isdigit())
        camera = int(digits) if digits else 0
        return intrinsics_from_projection(kitti_projection(read_kitti_calib(calib), camera, str(calib)), width, height)

    def _times(self, n: int) -> np.ndarray:
        path = Path(self.params.times).expanduser() if self.params.times else self.root / "times.txt"
        if not path.is_file():
            raise DataError(
                f"KITTI times file {path} not found; {describe_dir(path.parent)}. Give dataset.times=<file>"
            )
        try:
            ts = read_times(path)
        except TrajectoryError as exc:
            raise DataError(str(exc)) from None
        if ts.size != n:
            raise DataError(
                f"{path} has {ts.size} timestamps but {self.root / self.params.camera} holds {n} images; "
                "they must match one to one"
            )
        return ts

    def _poses_path(self) -> Path | None:
        if self.params.poses:
            path = Path(self.params.poses).expanduser()
            if not path.is_file():
                raise DataError(f"dataset.poses: {path} not found; {describe_dir(path.parent)}")
            return path
        for candidate in (self.root / "poses.txt", self.root.parent.parent / "poses" / f"{self.root.name}.txt"):
            if candidate.is_file():
                return candidate
        return None

    def _poses(self, path: Path | None, n: int, what: str) -> np.ndarray | None:
        if path is None:
            return None
        if not path.is_file():
            raise DataError(f"dataset.{what}: {path} not found; {describe_dir(path.parent)}")
        try:
            camera_poses = read_kitti(path).poses
        except TrajectoryError as exc:
            raise DataError(str(exc)) from None
        if len(camera_poses) != n:
            raise DataError(
                f"{path} has {len(camera_poses)} poses but {self.root / self.params.camera} holds {n} images; "
                "they must match one to one"
            )
        c = self.camera_to_base
        return np.einsum("ij,njk,kl->nil", c, camera_poses, invert(c))

    def __len__(self) -> int:
        """Number of images."""
        return len(self.images)

    def begin(self, context: RunContext) -> None:
        """Calibration, rate and name into the run context."""
        context.calibration = self.calibration
        context.sequence = self.params.sequence or self.root.name
        if len(self.timestamps) > 1:
            context.rate_hz = float(1.0 / np.median(np.diff(self.timestamps)))

    def frames(self) -> Iterator[Frame]:
        """The sequence's frames in order, images decoded lazily."""
        self.yielded = 0
        for i, path in enumerate(self.images):
            image = self.image_source(partial(read_image_file, path), f"frame {i} ({path})")
            if image is None:
                continue
            self.yielded += 1
            yield Frame(
                index=i,
                timestamp=float(self.timestamps[i]),
                image=image,
                odometry=self.odometry[i].copy(),
                calibration=self.calibration,
                ground_truth=None if self.ground_truth is None else self.ground_truth[i].copy(),
            )


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the KITTI dataset."""
    registry.add(KittiDataset)
