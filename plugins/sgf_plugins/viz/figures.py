"""Figures of the selected SGFs and their groups (paper Fig. 4 and 5), drawn by a lifecycle-hook observer.

The observer keeps the last BEVs in a bounded buffer, records each group assignment with a crop
of the BEV it was selected from, and at the end of the run writes ``sgf_frames.png`` (selected
SGFs outlined in their group's colour) and ``sgf_groups.png`` (the members of the largest groups
side by side: the same marking seen from other poses, reverse passes included).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgf_pipeline import hookimpl
from sgf_pipeline.io import atomic_path
from sgf_pipeline.run_info import RunInfo, StageNode
from sgf_pipeline.types import Bev, Frame, GroupAssignments

BUFFER_FRAMES = 150
MAX_RECORDS = 400


@dataclass
class SelectedView:
    """One selected SGF with the BEV it was selected from (cropped around it)."""

    frame_index: int
    group_id: int
    new_group: bool
    symmetric: bool
    instance_id: int | None
    crop: np.ndarray
    outline: np.ndarray


def group_colour(group_id: int) -> tuple[int, int, int]:
    """A saturated colour per SGF group (RGB), the same in every figure."""
    hue = (group_id * 47) % 180
    hsv = np.array([[[hue, 220, 255]]], dtype=np.uint8)
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(r), int(g), int(b)


class SgfFigureObserver:
    """Records BEVs and group assignments during a run and draws them at its end."""

    def __init__(self) -> None:
        self._bevs: dict[int, OrderedDict[int, Bev]] = {}
        self._views: dict[int, list[SelectedView]] = {}

    @hookimpl
    def sgf_run_start(self, run: RunInfo) -> None:
        """Start with empty buffers."""
        self._bevs[id(run)] = OrderedDict()
        self._views[id(run)] = []

    @hookimpl
    def sgf_after_stage(self, run: RunInfo, stage: StageNode, frame: Frame, output: Any, seconds: float) -> None:
        """Keep recent BEVs; record each assignment with the BEV its SGF came from."""
        if run.run_dir is None or not getattr(run.options, "plots", True):
            return
        bevs = self._bevs.setdefault(id(run), OrderedDict())
        if isinstance(output, Bev):
            bevs[output.frame_index] = output
            while len(bevs) > BUFFER_FRAMES:
                bevs.popitem(last=False)
        elif isinstance(output, GroupAssignments):
            views = self._views.setdefault(id(run), [])
            for item in output.items:
                if len(views) >= MAX_RECORDS:
                    break
                sgf = item.descriptor.sgf
                bev = bevs.get(sgf.frame_index)
                if bev is None or sgf.pixels.size == 0:
                    continue
                views.append(
                    self._record(
                        bev, sgf.pixels, item.group_id, item.new_group, item.symmetric, sgf.instance_id, sgf.frame_index
                    )
                )

    @staticmethod
    def _record(
        bev: Bev,
        pixels: np.ndarray,
        group_id: int,
        new_group: bool,
        symmetric: bool,
        instance_id: int | None,
        frame_index: int,
    ) -> SelectedView:
        h, w = bev.image.shape[:2]
        mask = np.zeros((h, w), np.uint8)
        mask[pixels[:, 1].clip(0, h - 1), pixels[:, 0].clip(0, w - 1)] = 1
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        outline = np.concatenate([c.reshape(-1, 2) for c in contours]) if contours else np.zeros((0, 2), int)
        image = bev.image.copy() if bev.image.ndim == 3 else cv2.cvtColor(bev.image, cv2.COLOR_GRAY2RGB)
        if image.dtype != np.uint8:
            image = np.clip(image * (255.0 if image.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
        image[~bev.valid] = (image[~bev.valid] * 0.35).astype(np.uint8)
        cv2.drawContours(image, contours, -1, group_colour(group_id), 2)
        return SelectedView(frame_index, group_id, new_group, symmetric, instance_id, image, outline)

    @hookimpl
    def sgf_run_end(self, run: RunInfo, metrics: dict[str, Any]) -> None:
        """Write sgf_frames.png and sgf_groups.png into the run directory."""
        views = self._views.pop(id(run), [])
        self._bevs.pop(id(run), None)
        if run.run_dir is None or not views or not getattr(run.options, "plots", True):
            return
        plot_selected(run.run_dir / "sgf_frames.png", views)
        plot_groups(run.run_dir / "sgf_groups.png", views)


def _save(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def plot_selected(path: Path, views: list[SelectedView], count: int = 24) -> None:
    """A grid of selected SGFs outlined in their group's colour (paper Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chosen = views[:: max(1, len(views) // count)][:count]
    cols = min(6, len(chosen))
    rows = (len(chosen) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(2.3 * cols, 2.5 * rows), dpi=100, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, view in zip(axes.ravel(), chosen, strict=False):
        ax.imshow(view.crop)
        tag = "new " if view.new_group else ""
        sym = " sym" if view.symmetric else ""
        ax.set_title(f"f{view.frame_index} {tag}g{view.group_id}{sym}", fontsize=8)
    fig.suptitle("Selected SGFs in their BEV (outline colour = SGF group)", fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def plot_groups(path: Path, views: list[SelectedView], groups: int = 6, members: int = 5) -> None:
    """Members of the largest SGF groups side by side (paper Fig. 5: one marking, several poses)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_group: dict[int, list[SelectedView]] = {}
    for view in views:
        by_group.setdefault(view.group_id, []).append(view)
    largest = sorted(by_group.values(), key=len, reverse=True)[:groups]
    largest = [g for g in largest if len(g) > 1] or largest[:1]
    cols = max(len(g[:members]) for g in largest)
    fig, axes = plt.subplots(len(largest), cols, figsize=(2.3 * cols, 2.4 * len(largest)), dpi=100, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for r, group in enumerate(largest):
        for c, view in enumerate(group[:members]):
            crop = view.crop
            if len(view.outline):
                ys, xs = view.outline[:, 1], view.outline[:, 0]
                pad = 20
                y0, y1 = max(0, ys.min() - pad), min(crop.shape[0], ys.max() + pad)
                x0, x1 = max(0, xs.min() - pad), min(crop.shape[1], xs.max() + pad)
                crop = crop[y0:y1, x0:x1]
            axes[r, c].imshow(crop)
            axes[r, c].set_title(f"group {view.group_id}: frame {view.frame_index}", fontsize=8)
    fig.suptitle("SGF groups: the same marking from several passes", fontsize=10)
    fig.tight_layout()
    _save(fig, path)


_OBSERVER = SgfFigureObserver()

# pluggy registers this module; the observer's hook implementations are its module-level names.
sgf_run_start = _OBSERVER.sgf_run_start
sgf_after_stage = _OBSERVER.sgf_after_stage
sgf_run_end = _OBSERVER.sgf_run_end
