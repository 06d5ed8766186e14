"""The paper's Fig. 10: one frame through plain IPM and MC-IPM, side by side.

``python -m sgf_plugins.ipm.figure SEQUENCE_DIR --frame N --out fig10.png`` reads a sequence in
the project's folder format (what ``sgf-world`` writes), runs both IPM variants over frames
``0..N`` (MC-IPM needs the pose queue) and writes camera | IPM | MC-IPM as one PNG.

In a run whose IPM compensates the robot's motion, an observer keeps the keyframe it compensated
most (the largest roll and pitch it applied) and writes that frame's figure as
``ipm_comparison.png`` in the run directory at the end, which ``sgf-report`` shows.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline import hookimpl
from sgf_pipeline.errors import DataError, SgfError
from sgf_pipeline.folder_format import read_calibration_yaml
from sgf_pipeline.io import atomic_write_bytes
from sgf_pipeline.run_info import RunInfo, StageNode
from sgf_pipeline.trajectory import TrajectoryError, read_tum
from sgf_pipeline.types import Bev, CameraImage, Frame
from sgf_plugins.ipm.stages import (
    InversePerspectiveMapping,
    IpmParams,
    MotionCompensatedIPM,
    MotionCompensatedIpmParams,
)

PANEL = 384  # pixels of each panel's height
RUN_FIGURE = "ipm_comparison.png"


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image


def _label(panel: np.ndarray, text: str) -> np.ndarray:
    out = panel.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 22), (0, 0, 0), thickness=-1)
    cv2.putText(out, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def bev_panel(bev: Bev, height: int = PANEL, metre_grid: bool = True) -> np.ndarray:
    """A BEV scaled to ``height`` rows, invisible ground dark blue, with 1 m grid lines."""
    image = _rgb(bev.image).copy()
    image[~bev.valid] = (20, 20, 60)
    scale = height / image.shape[0]
    out = cv2.resize(image, (round(image.shape[1] * scale), height), interpolation=cv2.INTER_NEAREST)
    if metre_grid:
        g = bev.grid
        xs = np.arange(np.ceil(g.x_min), g.x_max, 1.0)
        ys = np.arange(np.ceil(g.y_min), g.y_max, 1.0)
        for v in (g.ground_to_pixel(xs, np.zeros_like(xs))[1] + 0.5) * scale:
            cv2.line(out, (0, round(v)), (out.shape[1], round(v)), (255, 200, 0), 1)
        for u in (g.ground_to_pixel(np.zeros_like(ys), ys)[0] + 0.5) * scale:
            cv2.line(out, (round(u), 0), (round(u), out.shape[0]), (255, 200, 0), 1)
    return out


def comparison_figure(camera: np.ndarray, plain: Bev, mc: Bev) -> np.ndarray:
    """Camera image | plain IPM | MC-IPM (RGB uint8), like the paper's Fig. 10."""
    cam = _rgb(camera)
    scale = PANEL / cam.shape[0]
    cam = cv2.resize(cam, (round(cam.shape[1] * scale), PANEL), interpolation=cv2.INTER_AREA)
    gap = np.full((PANEL, 6, 3), 255, dtype=np.uint8)
    mc_text = f"MC-IPM  roll {np.degrees(mc.roll):+.1f} deg, pitch {np.degrees(mc.pitch):+.1f} deg"
    return np.hstack(
        [
            _label(cam, f"camera, frame {plain.frame_index}"),
            gap,
            _label(bev_panel(plain), "IPM"),
            gap,
            _label(bev_panel(mc), mc_text),
        ]
    )


def save_png(path: str | Path, image_rgb: np.ndarray) -> Path:
    """Write an RGB image as PNG atomically."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DataError(f"could not encode the figure for {path}")
    atomic_write_bytes(path, data.tobytes())
    return Path(path)


def read_sequence(root: str | Path) -> Iterator[Frame]:
    """Frames of a folder-format sequence (images, calibration, odometry, optional IMU), in order."""
    root = Path(root)
    images = sorted(p for p in (root / "images").glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not images:
        raise DataError(f"{root}: no images in {root / 'images'} (expected a sequence in the folder format)")
    calibration = read_calibration_yaml(root / "calibration.yaml")
    try:
        odometry = read_tum(root / "odometry.tum")
    except TrajectoryError as exc:
        raise DataError(f"{root}: {exc}") from None
    if len(odometry) != len(images):
        raise DataError(f"{root}: {len(images)} images but {len(odometry)} odometry poses")
    imu: np.ndarray | None = None
    if (root / "imu.csv").is_file():
        imu = np.loadtxt(root / "imu.csv", delimiter=",", skiprows=1, ndmin=2)
        if imu.shape != (len(images), 3):
            raise DataError(f"{root / 'imu.csv'}: expected {len(images)} rows of timestamp,roll,pitch")
    for i, path in enumerate(images):
        bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if bgr is None:
            raise DataError(f"cannot read image {path}")
        image = bgr if bgr.ndim == 2 else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        attitude = None if imu is None else (float(imu[i, 1]), float(imu[i, 2]))
        yield Frame(i, float(odometry.timestamps[i]), image, odometry.poses[i], calibration, attitude)


def plain_params(params: IpmParams) -> IpmParams:
    """The plain-IPM parameters of an IPM stage's (the same grid and resampling)."""
    return IpmParams(**{k: getattr(params, k) for k in IpmParams.model_fields})


def figure_from_frames(
    frames: Iterator[Frame], index: int, params: MotionCompensatedIpmParams | None = None
) -> np.ndarray:
    """Run MC-IPM over frames ``0..index`` and return the comparison figure of frame ``index``."""
    mc_params = params or MotionCompensatedIpmParams()
    plain, mc = InversePerspectiveMapping(plain_params(mc_params)), MotionCompensatedIPM(mc_params)
    for frame in frames:
        image = CameraImage(_rgb(frame.image), frame.index)
        if frame.index < index:
            mc.compensation(frame)  # the pose queue sees every earlier frame
            continue
        return comparison_figure(frame.image, plain.process(frame, image), mc.process(frame, image))
    raise DataError(f"the sequence ends before frame {index}")


@dataclass
class _Compensated:
    """The keyframe a run's MC-IPM compensated most so far, with what its figure needs."""

    size: float
    frame: Frame
    image: CameraImage
    bev: Bev
    params: IpmParams


class IpmFigureObserver:
    """Writes Fig. 10 of the keyframe a run's motion-compensated IPM compensated most."""

    def __init__(self) -> None:
        self._images: dict[int, CameraImage] = {}
        self._best: dict[int, _Compensated] = {}

    @hookimpl
    def sgf_run_start(self, run: RunInfo) -> None:
        """Start with nothing kept."""
        self._images.pop(id(run), None)
        self._best.pop(id(run), None)

    @hookimpl
    def sgf_after_stage(self, run: RunInfo, stage: StageNode, frame: Frame, output: Any, seconds: float) -> None:
        """Keep the image IPM warps, and the frame with the largest compensation."""
        if run.run_dir is None or not getattr(run.options, "plots", True):
            return
        if isinstance(output, CameraImage):
            self._images[id(run)] = output
            return
        ipm = stage.stage
        if not isinstance(output, Bev) or not isinstance(ipm, MotionCompensatedIPM):
            return
        image = self._images.get(id(run))  # what this IPM warped: the stage before it made it
        if image is None or image.frame_index != frame.index:
            return
        size = float(np.hypot(output.roll, output.pitch))
        best = self._best.get(id(run))
        if best is None or size > best.size:
            self._best[id(run)] = _Compensated(size, frame, image, output, ipm.params)

    @hookimpl
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        """Write ipm_comparison.png: camera | plain IPM | the run's MC-IPM of that keyframe."""
        best = self._best.pop(id(run), None)
        self._images.pop(id(run), None)
        if best is None or run.run_dir is None:
            return
        g = best.bev.grid  # the region the run's IPM resampled (moved where the camera sees the ground)
        region = {"x_min": g.x_min, "x_max": g.x_max, "y_min": g.y_min, "y_max": g.y_max, "region": "fixed"}
        params = plain_params(best.params).model_copy(update=region)
        plain = InversePerspectiveMapping(params).process(best.frame, best.image)
        save_png(run.run_dir / RUN_FIGURE, comparison_figure(best.frame.image, plain, best.bev))


_OBSERVER = IpmFigureObserver()

# pluggy registers this module (entry point ``ipm_figure``); its hook implementations are these names.
sgf_run_start = _OBSERVER.sgf_run_start
sgf_after_stage = _OBSERVER.sgf_after_stage
sgf_run_end = _OBSERVER.sgf_run_end


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: write the Fig. 10 comparison of one frame of a folder-format sequence."""
    parser = argparse.ArgumentParser(prog="python -m sgf_plugins.ipm.figure", description=__doc__.splitlines()[0])
    parser.add_argument("sequence", type=Path, help="sequence folder (folder format: images/, calibration.yaml, ...)")
    parser.add_argument("--frame", type=int, required=True, help="frame index to show")
    parser.add_argument("--out", type=Path, default=Path("fig10_ipm_vs_mc.png"), help="PNG to write")
    parser.add_argument("--queue-size", type=int, default=50, help="MC-IPM queue size N")
    parser.add_argument("--roll-axis", choices=("optical", "base"), default="optical", help="MC-IPM roll axis")
    args = parser.parse_args(argv)
    try:
        params = MotionCompensatedIpmParams(queue_size=args.queue_size, roll_axis=args.roll_axis)
        figure = figure_from_frames(read_sequence(args.sequence), args.frame, params)
        print(save_png(args.out, figure))
    except SgfError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
