"""``dataset=folder``: the project's own folder format (spec: :mod:`sgf_pipeline.folder_format`, docs/datasets.md)."""

from __future__ import annotations

from collections.abc import Iterator
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field

from sgf_pipeline import DataError, RunContext, StageRegistry, hookimpl
from sgf_pipeline.folder_format import FORMAT, VERSION, read_calibration_yaml, read_truth_json
from sgf_pipeline.io import read_text, read_yaml
from sgf_pipeline.timesync import PoseSeries
from sgf_pipeline.trajectory import TrajectoryError, parse_tum
from sgf_pipeline.truth import SequenceTruth
from sgf_pipeline.types import Frame
from sgf_plugins.datasets._common import (
    RecordedDataset,
    RecordedParams,
    describe_dir,
    finite_pose,
    read_image_file,
)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_SAME_TIME = 1e-6  # s: a row of odometry.tum belongs to the image with this timestamp (9 decimals written)


class FolderParams(RecordedParams):
    """Options of the folder reader."""

    masks: bool = Field(True, description="load masks/ (marking instance ids) when the folder has them")
    max_time_diff: float = Field(
        0.01, gt=0.0, description="s; ground truth not given per image is interpolated from samples this close"
    )


class FolderDataset(RecordedDataset):
    """A sequence in the project's folder format: images, timestamps, odometry, IMU, calibration, truth."""

    name = "folder"
    Params = FolderParams
    params: FolderParams

    def __init__(self, params: FolderParams) -> None:
        super().__init__(params)
        root = self.recording_dir("sequence folder")
        self.root = root
        self.meta = self._read_meta()
        self.calibration = self.prepare_calibration(self._need_calibration())
        self.images = sorted(p for p in (root / "images").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
        if not (root / "images").is_dir() or not self.images:
            raise DataError(f"{root}/images has no PNG or JPEG images; {describe_dir(root / 'images')}")
        n = len(self.images)
        if isinstance(self.meta.get("frames"), int) and self.meta["frames"] != n:
            raise DataError(
                f"{root}/sequence.yaml says frames: {self.meta['frames']} but images/ holds {n} images; "
                "the folder is incomplete (an interrupted copy?)"
            )
        self.timestamps = self._read_timestamps(n)
        self.odometry = self._read_odometry(n)
        self.imu = self._read_imu(n)
        self.ground_truth = self._read_ground_truth(n)
        self.keep = self._usable_rows(n)
        self.truth = self._read_truth()

    # -- reading the index files --------------------------------------------------------------

    def _need(self, name: str) -> Path:
        path = self.root / name
        if not path.is_file():
            raise DataError(f"{self.root} has no {name}, which the folder format requires; {describe_dir(self.root)}")
        return path

    def _read_meta(self) -> dict[str, object]:
        path = self.root / "sequence.yaml"
        if not path.is_file():
            return {"name": self.root.name}
        meta = read_yaml(path, "sequence file") or {}
        if not isinstance(meta, dict):
            raise DataError(f"{path}: expected a mapping (format, version, name, rate_hz, frames)")
        if meta.get("format", FORMAT) != FORMAT:
            raise DataError(
                f"{path}: format is {meta.get('format')!r}, not {FORMAT!r}; is this another dataset layout?"
            )
        version = meta.get("version", VERSION)
        if not isinstance(version, int) or version > VERSION:
            raise DataError(f"{path}: folder format version {version!r}; this sgf-pipeline reads up to {VERSION}")
        return meta

    def _need_calibration(self):  # type: ignore[no-untyped-def]
        return read_calibration_yaml(self._need("calibration.yaml"))

    def _read_timestamps(self, n: int) -> np.ndarray:
        path = self._need("timestamps.txt")
        values: list[float] = []
        for number, line in enumerate(read_text(path).split("\n"), start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                values.append(float(line.split()[0]))
            except ValueError:
                raise DataError(f"{path}:{number}: not a timestamp: {line[:60]!r}") from None
        ts = np.asarray(values, dtype=np.float64)
        if ts.size != n:
            raise DataError(f"{path} has {ts.size} timestamps but images/ holds {n} images; they must match one to one")
        if not np.all(np.isfinite(ts)):
            raise DataError(f"{path}: non-finite timestamp at image {int(np.flatnonzero(~np.isfinite(ts))[0])}")
        return ts

    def _read_odometry(self, n: int) -> np.ndarray:
        path = self._need("odometry.tum")
        try:
            ts, poses, _ = parse_tum(path)
        except TrajectoryError as exc:
            raise DataError(str(exc)) from None
        if ts.size != n:
            raise DataError(f"{path} has {ts.size} poses but images/ holds {n} images; give one pose per image")
        off = np.flatnonzero(np.abs(ts - self.timestamps) > _SAME_TIME)
        if off.size:
            i = int(off[0])
            raise DataError(
                f"{path}: pose {i} is at t={ts[i]!r} but image {i} at t={self.timestamps[i]!r}; "
                "odometry.tum must have one row per image at the image's timestamp"
            )
        return poses

    def _read_imu(self, n: int) -> np.ndarray | None:
        path = self.root / "imu.csv"
        if not path.is_file():
            return None
        lines = [(k, ln.strip()) for k, ln in enumerate(read_text(path).split("\n"), start=1) if ln.strip()]
        if not lines or [h.strip() for h in lines[0][1].split(",")] != ["timestamp", "roll", "pitch"]:
            raise DataError(f"{path}: the first line must be the header 'timestamp,roll,pitch'")
        rows = []
        for number, line in lines[1:]:
            try:
                rows.append([float(v) for v in line.split(",")])
            except ValueError:
                raise DataError(f"{path}:{number}: not numbers: {line[:60]!r}") from None
            if len(rows[-1]) != 3:
                raise DataError(f"{path}:{number}: expected 3 values (timestamp, roll, pitch), got {len(rows[-1])}")
        data = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
        if len(data) != n:
            raise DataError(f"{path} has {len(data)} rows but images/ holds {n} images; give one row per image")
        off = np.flatnonzero(np.abs(data[:, 0] - self.timestamps) > _SAME_TIME)
        if off.size:
            raise DataError(f"{path}: row {int(off[0])} is not at the timestamp of image {int(off[0])}")
        return data[:, 1:3]

    def _read_ground_truth(self, n: int) -> list[np.ndarray | None] | None:
        path = self.root / "groundtruth.tum"
        if not path.is_file():
            return None
        try:
            ts, poses, lines = parse_tum(path)
        except TrajectoryError as exc:
            raise DataError(str(exc)) from None
        if ts.size == n and np.all(np.abs(ts - self.timestamps) <= _SAME_TIME):
            return [p if finite_pose(p) else None for p in poses]
        # Ground truth at its own rate (motion capture, LiDAR SLAM): interpolate at the image times.
        good = np.array([finite_pose(p) for p in poses]) & np.isfinite(ts)
        ts, poses = ts[good], poses[good]
        if ts.size > 1 and np.any(np.diff(ts) <= 0):
            row = int(np.flatnonzero(np.diff(ts) <= 0)[0]) + 1
            raise DataError(f"{path}:{lines[row]}: timestamps must increase strictly")
        series = PoseSeries(ts, poses, "ground truth")
        return [series.at(float(t), self.params.max_time_diff) for t in self.timestamps]

    def _usable_rows(self, n: int) -> np.ndarray:
        """Rows with a finite odometry pose and a timestamp after the previous usable one."""
        keep = np.ones(n, dtype=bool)
        last = -np.inf
        for i in range(n):
            t = self.timestamps[i]
            if t <= last:
                kind = "duplicated timestamp" if t == last else "timestamp out of order"
                self.skips.problem(
                    kind,
                    f"{self.root}/timestamps.txt: image {i} ({self.images[i].name}) at t={t!r} is not after t={last!r}",
                )
                keep[i] = False
                continue
            if not finite_pose(self.odometry[i]):
                self.skips.problem(
                    "bad pose",
                    f"{self.root}/odometry.tum: pose {i} is not finite (NaN or inf) or not of a unit quaternion",
                )
                keep[i] = False
                continue
            if self.imu is not None and not np.all(np.isfinite(self.imu[i])):
                self.skips.problem("bad imu", f"{self.root}/imu.csv: roll/pitch of image {i} is not finite")
                keep[i] = False
                continue
            last = t
        return keep

    def _read_truth(self) -> SequenceTruth | None:
        path = self.root / "truth.json"
        if not path.is_file():
            return None
        return read_truth_json(path)

    # -- the Dataset contract -----------------------------------------------------------------

    def __len__(self) -> int:
        """Number of usable frames."""
        return int(self.keep.sum())

    def begin(self, context: RunContext) -> None:
        """Calibration, ground truth, rate and name into the run context."""
        context.calibration = self.calibration
        context.truth = self.truth
        context.sequence = str(self.meta.get("name") or self.root.name)
        rate = self.meta.get("rate_hz")
        if isinstance(rate, (int, float)) and rate > 0:
            context.rate_hz = float(rate)
        elif len(self.timestamps) > 1:
            context.rate_hz = float(1.0 / np.median(np.diff(self.timestamps)))

    def _mask_loader(self, index: int):  # type: ignore[no-untyped-def]
        path = self.root / "masks" / f"{self.images[index].stem}.png"
        if not self.params.masks or not path.is_file():
            return None

        def load() -> np.ndarray:
            mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if mask is None:
                raise DataError(f"mask {path} cannot be decoded (corrupt or truncated)")
            if mask.ndim != 2:
                raise DataError(f"mask {path} must be a one-channel uint16 PNG of instance ids, got shape {mask.shape}")
            return mask.astype(np.uint16, copy=False)

        return load

    def frames(self) -> Iterator[Frame]:
        """The usable frames in time order, images decoded lazily."""
        self.yielded = 0
        for i in np.flatnonzero(self.keep):
            i = int(i)
            path = self.images[i]
            image = self.image_source(partial(read_image_file, path), f"frame {i} ({path.name})")
            if image is None:
                continue
            self.yielded += 1
            yield Frame(
                index=i,
                timestamp=float(self.timestamps[i]),
                image=image,
                odometry=self.odometry[i].copy(),
                calibration=self.calibration,
                imu_roll_pitch=None if self.imu is None else (float(self.imu[i, 0]), float(self.imu[i, 1])),
                ground_truth=None if self.ground_truth is None else self.ground_truth[i],
                instance_ids=self._mask_loader(i),
            )


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the folder dataset."""
    registry.add(FolderDataset)
