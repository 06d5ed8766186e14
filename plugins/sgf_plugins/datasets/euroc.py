"""``dataset=euroc``: a recording in the EuRoC/ASL layout (``mav0/cam0``, ``imu0``, ``state_groundtruth_estimate0``).

Frames (the ASL layout's "body" frame ``B`` is the one ``sensor.yaml``'s ``T_BS`` refers to):

* camera_to_base comes from the config: ``camera_to_base``, or ``camera_height`` + ``camera_tilt``,
  or ``body_to_base`` (then camera_to_base = body_to_base ``T_BS``). The body's pose on the base
  follows from it: body_to_base = camera_to_base ``T_BS^-1``.
* Ground truth (``state_groundtruth_estimate0/data.csv``, or another folder's ``data.csv``, or a
  TUM or EuRoC CSV file: body poses in a z-up world ``R``) becomes base poses
  ``T_RS body_to_base^-1``, interpolated at the image times. A ground-truth folder without a
  ``data.csv`` is named in a warning and the run goes on without ground truth.
* Odometry: the file named by ``odometry`` (TUM, KITTI or EuRoC CSV; body or base poses per
  ``odometry_frame``), or else the ground truth itself (a perfect odometry; the ASL layout has no
  wheel odometry).
* Roll and pitch: ``imu0`` holds raw gyro and accelerometer samples; a complementary filter
  (:func:`sgf_pipeline.imu.roll_pitch_from_inertial`) turns them into the base's attitude.

Images are undistorted with ``sensor.yaml``'s model (radial-tangential or equidistant); the
``sensor.yaml`` files may carry OpenCV's ``%YAML:1.0`` first line, as the published sequences do.
Camera frames before the first or after the last odometry sample are left out (EuRoC's camera
starts before its ground truth); they are counted as ``trimmed`` in metrics.json.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from sgf_pipeline import DataError, RunContext, StageRegistry, hookimpl
from sgf_pipeline.calibration import Calibration
from sgf_pipeline.calibration_io import euroc_matrix, read_euroc_sensor_yaml
from sgf_pipeline.geometry import invert
from sgf_pipeline.imu import roll_pitch_from_inertial
from sgf_pipeline.io import read_text, read_yaml
from sgf_pipeline.timesync import PoseSeries, ValueSeries
from sgf_pipeline.trajectory import TrajectoryError, read_trajectory, seconds_from_ns
from sgf_pipeline.types import Frame
from sgf_plugins.datasets._common import (
    MountingParams,
    RecordedDataset,
    describe_dir,
    mounting_matrix,
    read_image_file,
)

log = logging.getLogger("sgf_pipeline.datasets")
#: The ground-truth folder of the published sequences.
GROUND_TRUTH_FOLDER = "state_groundtruth_estimate0"


class EurocParams(MountingParams):
    """Options of the EuRoC/ASL reader."""

    camera: str = Field("cam0", description="camera folder under mav0")
    imu: str = Field("imu0", description="IMU folder under mav0 (empty: no roll/pitch)")
    groundtruth: str = Field(
        GROUND_TRUTH_FOLDER,
        description="ground truth: a folder under mav0 holding data.csv, or a TUM or EuRoC CSV file (empty: none)",
    )
    body_to_base: list[list[float]] | None = Field(
        None, description="4x4 pose of the body frame (T_BS's reference) in the base frame"
    )
    odometry: str = Field("", description="odometry file (TUM, KITTI or EuRoC CSV); default: the ground truth")
    odometry_frame: Literal["body", "base"] = Field("body", description="whose poses the odometry file holds")
    max_time_diff: float = Field(0.02, gt=0.0, description="s; furthest odometry/IMU/ground-truth sample from an image")
    interpolate: bool = Field(True, description="interpolate poses between samples (else take the nearest)")
    imu_gain: float = Field(1.0, ge=0.0, description="complementary filter gain (1/s) pulling roll/pitch to gravity")
    sequence: str = Field("", description="sequence name in reports (default: the folder's name)")


def _read_csv_ns(path: Path, min_columns: int, what: str) -> tuple[np.ndarray, list[list[str]], list[int]]:
    """Integer ns timestamps, the other fields and line numbers of an ASL CSV."""
    stamps: list[int] = []
    rows: list[list[str]] = []
    lines: list[int] = []
    for number, line in enumerate(read_text(path).split("\n"), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) < min_columns:
            raise DataError(f"{path}:{number}: a {what} line has at least {min_columns} fields, got {len(fields)}")
        try:
            stamp = int(fields[0])
        except ValueError:
            raise DataError(f"{path}:{number}: timestamp {fields[0]!r:.40} is not an integer of nanoseconds") from None
        if not -(2**63) <= stamp < 2**63:
            raise DataError(f"{path}:{number}: timestamp {fields[0]!r:.40} ns is out of range (64-bit ns)")
        stamps.append(stamp)
        rows.append(fields[1:])
        lines.append(number)
    return np.asarray(stamps, dtype=np.int64), rows, lines


class EurocDataset(RecordedDataset):
    """A recording in the EuRoC/ASL folder layout."""

    name = "euroc"
    Params = EurocParams
    params: EurocParams

    def __init__(self, params: EurocParams) -> None:
        super().__init__(params)
        root = self.recording_dir("recording folder (the one holding mav0/)")
        self.mav = root / "mav0" if (root / "mav0").is_dir() else root
        self.root = root
        cam_dir = self.mav / params.camera
        for needed in (cam_dir / "data.csv", cam_dir / "sensor.yaml"):
            if not needed.is_file():
                raise DataError(f"EuRoC camera file {needed} not found; {describe_dir(needed.parent)}")
        camera = read_euroc_sensor_yaml(cam_dir / "sensor.yaml")
        self.rate_hz = camera.rate_hz
        camera_to_base = self._camera_to_base(camera.camera_to_body)
        self.body_to_base = camera_to_base @ invert(camera.camera_to_body)
        self.calibration = self.prepare_calibration(
            Calibration(intrinsics=camera.intrinsics, distortion=camera.distortion, camera_to_base=camera_to_base)
        )
        self.frame_ns, self.image_paths = self._camera_rows(cam_dir)
        self.timestamps = seconds_from_ns(self.frame_ns)
        self.ground_truth = self._ground_truth()
        self.odometry = self._odometry()
        self.attitude = self._attitude()
        self.trimmed = 0

    def _camera_to_base(self, camera_to_body: np.ndarray) -> np.ndarray:
        matrix = mounting_matrix(self.params, self.name)
        if matrix is not None:
            return matrix
        if self.params.body_to_base is not None:
            body_to_base = np.asarray(self.params.body_to_base, dtype=np.float64)
            if body_to_base.shape != (4, 4):
                raise DataError(f"dataset.body_to_base must be 4x4, got shape {body_to_base.shape}")
            return body_to_base @ camera_to_body
        raise DataError(
            "dataset=euroc: the camera's mounting on the robot is unknown. Give dataset.camera_height=<m above the "
            "ground> (and dataset.camera_tilt=<rad down>), dataset.camera_to_base=<4x4>, or "
            "dataset.body_to_base=<4x4 pose of the body frame in the base frame>"
        )

    def _camera_rows(self, cam_dir: Path) -> tuple[np.ndarray, list[Path]]:
        ns, rows, lines = _read_csv_ns(cam_dir / "data.csv", 2, "camera (timestamp, filename)")
        if ns.size == 0:
            raise DataError(f"{cam_dir / 'data.csv'} lists no images")
        keep: list[int] = []
        last = None
        for i, t in enumerate(ns):
            if last is not None and t <= last:
                kind = "duplicated timestamp" if t == last else "timestamp out of order"
                self.skips.problem(
                    kind, f"{cam_dir / 'data.csv'}:{lines[i]}: image timestamp {int(t)} ns is not after {int(last)} ns"
                )
                continue
            keep.append(i)
            last = t
        for i in keep:
            name = Path(rows[i][0])
            if not rows[i][0] or name.is_absolute() or ".." in name.parts:
                raise DataError(
                    f"{cam_dir / 'data.csv'}:{lines[i]}: image name {rows[i][0]!r:.60} must be a file name inside "
                    f"{cam_dir / 'data'} (no absolute path, no '..')"
                )
        paths = [cam_dir / "data" / rows[i][0] for i in keep]
        return ns[keep], paths

    def _ground_truth(self) -> PoseSeries | None:
        path = self._ground_truth_file()
        if path is None:
            return None
        try:
            trajectory = read_trajectory(path, duplicates="drop")
        except TrajectoryError as exc:
            raise DataError(str(exc)) from None
        base_to_body = invert(self.body_to_base)
        return PoseSeries(trajectory.timestamps, trajectory.poses @ base_to_body, "ground truth")

    def _ground_truth_file(self) -> Path | None:
        """The ground-truth file ``groundtruth`` names: a folder's ``data.csv`` or a trajectory file."""
        name = self.params.groundtruth
        if not name:
            return None
        given = Path(name).expanduser()
        candidates = [given] if given.is_absolute() else [self.mav / given, self.root / given, given]
        for candidate in candidates:
            if candidate.is_file():
                return candidate
            if candidate.is_dir():
                if (candidate / "data.csv").is_file():
                    return candidate / "data.csv"
                log.warning(
                    "dataset=euroc: the ground-truth folder %s has no data.csv, so the run has no ground truth "
                    "(%s); name a TUM or CSV file with dataset.groundtruth=<file>",
                    candidate,
                    describe_dir(candidate),
                )
                return None
        if name != GROUND_TRUTH_FOLDER:
            raise DataError(
                f"dataset.groundtruth={name}: no such folder under {self.mav} and no such file; give a folder under "
                f"mav0 holding data.csv, or a TUM or EuRoC CSV file ({describe_dir(self.mav)})"
            )
        log.info("dataset=euroc: %s has no %s; the run has no ground truth", self.mav, GROUND_TRUTH_FOLDER)
        return None

    def _odometry(self) -> PoseSeries:
        if self.params.odometry:
            path = Path(self.params.odometry).expanduser()
            if not path.is_file():
                raise DataError(f"dataset.odometry: {path} not found; {describe_dir(path.parent)}")
            try:
                trajectory = read_trajectory(path)
            except TrajectoryError as exc:
                raise DataError(str(exc)) from None
            poses = trajectory.poses
            if self.params.odometry_frame == "body":
                poses = poses @ invert(self.body_to_base)
            return PoseSeries(trajectory.timestamps, poses, "odometry")
        if self.ground_truth is None:
            raise DataError(
                f"{self.mav} has no ground truth ({self.params.groundtruth or 'dataset.groundtruth is empty'}) to use "
                f"as odometry; give an odometry file with dataset.odometry=<file>; {describe_dir(self.mav)}"
            )
        return self.ground_truth

    def _attitude(self) -> ValueSeries | None:
        if not self.params.imu:
            return None
        imu_dir = self.mav / self.params.imu
        path = imu_dir / "data.csv"
        if not path.is_file():
            raise DataError(
                f"IMU file {path} not found (set dataset.imu='' to run without IMU); {describe_dir(imu_dir)}"
            )
        ns, rows, lines = _read_csv_ns(path, 7, "IMU (timestamp, w_x, w_y, w_z, a_x, a_y, a_z)")
        try:
            data = np.asarray([[float(v) for v in r[:6]] for r in rows], dtype=np.float64).reshape(-1, 6)
        except ValueError:
            raise DataError(f"{path}: non-numeric gyro or accelerometer value") from None
        good = np.asarray(np.isfinite(data).all(axis=1), dtype=bool)
        for i in np.flatnonzero(~good):
            self.skips.problem("bad imu", f"{path}:{lines[int(i)]}: non-finite IMU sample")
        last: int | None = None
        for i in np.flatnonzero(good):  # each kept sample after the last kept one (a running maximum)
            if last is not None and ns[i] <= last:
                self.skips.problem(
                    "imu timestamp", f"{path}:{lines[int(i)]}: IMU timestamp {int(ns[i])} ns is not after {last} ns"
                )
                good[i] = False
            else:
                last = int(ns[i])
        ns, data = ns[good], data[good]
        if ns.size == 0:
            raise DataError(f"{path} has no usable IMU samples")
        imu_to_body = np.eye(4)
        if (imu_dir / "sensor.yaml").is_file():
            meta = read_yaml(imu_dir / "sensor.yaml", "IMU sensor file") or {}
            node = meta.get("T_BS") if isinstance(meta, dict) else None
            if node is not None:
                imu_to_body = euroc_matrix(node, "T_BS", imu_dir / "sensor.yaml")
        imu_to_base = self.body_to_base @ imu_to_body
        ts = seconds_from_ns(ns)
        roll_pitch = roll_pitch_from_inertial(ts, data[:, 0:3], data[:, 3:6], self.params.imu_gain, imu_to_base)
        return ValueSeries(ts, roll_pitch, "imu roll/pitch")

    def __len__(self) -> int:
        """Number of camera images listed."""
        return len(self.image_paths)

    def begin(self, context: RunContext) -> None:
        """Calibration, rate and name into the run context."""
        context.calibration = self.calibration
        context.sequence = self.params.sequence or self.root.name
        if self.rate_hz:
            context.rate_hz = self.rate_hz
        elif len(self.timestamps) > 1:
            context.rate_hz = float(1.0 / np.median(np.diff(self.timestamps)))

    def frames(self) -> Iterator[Frame]:
        """Camera frames within the odometry's time span, with interpolated poses and roll/pitch."""
        p = self.params
        span = self.odometry.span()
        assert span is not None
        self.yielded = self.trimmed = 0
        for i, (t, path) in enumerate(zip(self.timestamps, self.image_paths, strict=True)):
            t = float(t)
            if t < span[0] - p.max_time_diff or t > span[1] + p.max_time_diff:
                self.trimmed += 1
                continue
            odometry = self.odometry.at(t, p.max_time_diff, p.interpolate)
            if odometry is None:
                self.skips.problem(
                    "no odometry", f"no odometry pose within {p.max_time_diff} s of image {i} (t={t:.6f} s)"
                )
                continue
            if not path.is_file():
                self.skips.problem("missing image", f"image {i}: {path} not found; {describe_dir(path.parent, 5)}")
                continue
            image = self.image_source(partial(read_image_file, path), f"frame {i} ({path.name})")
            if image is None:
                continue
            yield self.make_frame(i, t, image, odometry)

    def finalize(self, context: RunContext) -> None:
        """Skips and frames outside the odometry's span into metrics.json."""
        super().finalize(context)
        context.metrics["dataset"]["trimmed"] = self.trimmed


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the EuRoC/ASL dataset."""
    registry.add(EurocDataset)
