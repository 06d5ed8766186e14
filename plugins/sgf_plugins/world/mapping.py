"""Pictures of a campus world: the top-down map with the route, markings and revisits, and sample frames."""

from __future__ import annotations

import io
import math
import os
from pathlib import Path

import cv2
import numpy as np

from sgf_pipeline.io import atomic_write_bytes
from sgf_pipeline.truth import MarkingPass
from sgf_plugins.world.world import CampusWorld

MAP_TILE = 64.0


def ground_map(world: CampusWorld, bounds: tuple[float, float, float, float], res: float) -> np.ndarray:
    """Top-down RGB image (north up) of the ground within ``bounds = (x0, y0, x1, y1)`` at ``res`` m/px."""
    x0, y0, x1, y1 = bounds
    x0, y0 = math.floor(x0 / MAP_TILE) * MAP_TILE, math.floor(y0 / MAP_TILE) * MAP_TILE
    x1, y1 = math.ceil(x1 / MAP_TILE) * MAP_TILE, math.ceil(y1 / MAP_TILE) * MAP_TILE
    n = round(MAP_TILE / res)
    cols, rows = round((x1 - x0) / MAP_TILE), round((y1 - y0) / MAP_TILE)
    out = np.zeros((rows * n, cols * n, 3), np.uint8)
    gen = world.renderer.generator
    for j in range(rows):
        for i in range(cols):
            rgba, _ = gen.region(x0 + i * MAP_TILE, y1 - j * MAP_TILE, n, n, res, geometry_step=2)
            lit = rgba[..., :3].astype(np.float32) * (0.55 + 0.45 * rgba[..., 3:] / 255.0) * 1.15
            out[j * n : (j + 1) * n, i * n : (i + 1) * n] = np.clip(lit, 0, 255).astype(np.uint8)
    _draw_buildings_and_trees(world, out, x0, y1, res)
    return out


def _draw_buildings_and_trees(world: CampusWorld, img: np.ndarray, x0: float, y_top: float, res: float) -> None:
    def px(p: np.ndarray) -> np.ndarray:
        return np.round(np.stack([(p[:, 0] - x0) / res, (y_top - p[:, 1]) / res], axis=1) * 16).astype(np.int32)

    for t in world.layout.trees:
        c = px(t.position[None])[0]
        cv2.circle(img, (int(c[0]), int(c[1])), round(t.canopy_radius / res * 16), (58, 96, 44), -1, cv2.LINE_AA, 4)
        cv2.circle(img, (int(c[0]), int(c[1])), round(t.canopy_radius / res * 16), (40, 70, 34), 1, cv2.LINE_AA, 4)
    for b in world.layout.buildings:
        shade = 150 + 4 * b.style
        cv2.fillPoly(img, [px(b.corners)], (shade, shade - 6, shade - 14), cv2.LINE_AA, 4)
        cv2.polylines(img, [px(b.corners)], True, (80, 78, 74), 2, cv2.LINE_AA, 4)


def save_map(world: CampusWorld, path: str | os.PathLike[str], res: float | None = None) -> Path:
    """Write the map PNG: ground, buildings, the route by time, markings on it and the revisit points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    drive = world.drive
    truth = world.truth
    xy = drive.xy
    margin = 30.0
    bounds = (xy[:, 0].min() - margin, xy[:, 1].min() - margin, xy[:, 0].max() + margin, xy[:, 1].max() + margin)
    span = max(bounds[2] - bounds[0], bounds[3] - bounds[1])
    res = res or max(0.1, span / 1600.0)
    image = ground_map(world, bounds, res)
    gx0 = math.floor(bounds[0] / MAP_TILE) * MAP_TILE
    gy1 = math.ceil(bounds[3] / MAP_TILE) * MAP_TILE
    extent = (gx0, gx0 + image.shape[1] * res, gy1 - image.shape[0] * res, gy1)
    aspect = (bounds[3] - bounds[1]) / (bounds[2] - bounds[0])
    fig, ax = plt.subplots(figsize=(12, 12 * aspect + 0.8), dpi=150)
    ax.imshow(image, extent=extent, interpolation="antialiased")
    points = ax.scatter(xy[:, 0], xy[:, 1], c=drive.timestamps, cmap="plasma", s=1.2, linewidths=0, zorder=3)
    step = max(1, len(xy) // 40)
    for k in range(step, len(xy) - 1, step):
        a, b = xy[k], xy[min(k + 5, len(xy) - 1)]
        if np.linalg.norm(b - a) > 0.2:
            ax.annotate("", xy=b, xytext=a, arrowprops={"arrowstyle": "-|>", "color": "white", "lw": 0.8}, zorder=4)
    on_path = truth.on_path
    for m in world.layout.markings:
        colour = "#ffffff" if m.design.category == "standard" else "#ff9f1c"
        if m.instance_id in on_path:
            ax.plot(m.x, m.y, "o", ms=5, mfc=colour, mec="black", mew=0.6, zorder=5)
        else:
            ax.plot(m.x, m.y, ".", ms=3, color=colour, alpha=0.6, zorder=2)
    for r in truth.revisits:
        pose = truth.markings[r.instance_id].pose
        style = ("^", "#e63946") if r.reverse else ("s", "#2a9d8f")
        ax.plot(pose[0], pose[1], style[0], ms=9, mfc="none", mec=style[1], mew=1.6, zorder=6)
    ax.plot(*xy[0], "*", ms=14, color="#00e676", mec="black", zorder=7)
    ax.plot(*xy[-1], "X", ms=11, color="#ff1744", mec="black", zorder=7)
    rev = sum(r.reverse for r in truth.revisits)
    ax.set_title(
        f"{world.name} (seed {world.seed}, scale {world.params.scale:g}): {drive.length:.0f} m, {len(drive)} frames, "
        f"{len(on_path)} markings on the path, {len(truth.revisits)} revisit pairs ({rev} reverse)",
        fontsize=10,
    )
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_xlim(bounds[0], bounds[2])
    ax.set_ylim(bounds[1], bounds[3])
    handles = [
        Line2D([], [], marker="o", ls="", mfc="#ffffff", mec="black", label="standard marking on the path"),
        Line2D([], [], marker="o", ls="", mfc="#ff9f1c", mec="black", label="custom marking on the path"),
        Line2D([], [], marker="s", ls="", mfc="none", mec="#2a9d8f", mew=1.6, label="forward revisit"),
        Line2D([], [], marker="^", ls="", mfc="none", mec="#e63946", mew=1.6, label="reverse revisit"),
        Line2D([], [], marker="*", ls="", color="#00e676", mec="black", ms=12, label="start"),
        Line2D([], [], marker="X", ls="", color="#ff1744", mec="black", ms=10, label="end"),
    ]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.07), ncol=6, fontsize=8, frameon=False)
    fig.colorbar(points, ax=ax, fraction=0.03, pad=0.01, label="time (s)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def overlay_ids(image: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The image with each marking instance tinted in its own colour (for looking at ids)."""
    out = image.astype(np.float32)
    for ident in np.unique(ids[ids > 0]):
        hue = (int(ident) * 47) % 180
        colour = cv2.cvtColor(np.array([[[hue, 220, 255]]], np.uint8), cv2.COLOR_HSV2RGB)[0, 0].astype(np.float32)
        sel = ids == ident
        out[sel] = 0.45 * out[sel] + 0.55 * colour
    return np.clip(out, 0, 255).astype(np.uint8)


def sample_frames(world: CampusWorld) -> dict[str, int]:
    """Frames worth looking at: a marking in full view by day, the same place at night, a speed bump."""
    truth = world.truth
    drive = world.drive

    def area(p: MarkingPass) -> float:
        size = truth.markings[p.instance_id].size
        return size[0] * size[1]

    # the largest custom marking seen for a while (a logo or painted text rather than a drain)
    long_enough = [p for p in truth.passes if p.end_frame - p.start_frame >= 8] or list(truth.passes)
    custom = sorted((p for p in long_enough if truth.markings[p.instance_id].category == "custom"), key=area)[::-1]
    chosen = custom or sorted(long_enough, key=area)[::-1]
    day = (chosen[0].start_frame + chosen[0].end_frame) // 2 if chosen else len(drive) // 2
    pitch = np.array([math.asin(max(-1.0, min(1.0, -float(p[2, 0])))) for p in drive.poses])
    bump = int(np.argmax(np.abs(pitch)))
    ahead = int(np.clip(bump - round(2.2 * world.params.rate_hz / max(drive.speed[bump], 0.5)), 0, len(drive) - 1))
    return {"day": day, "night": day, "speed_bump": bump, "speed_bump_ahead": ahead}


def save_samples(world: CampusWorld, folder: str | os.PathLike[str]) -> dict[str, Path]:
    """Write the sample frames (and their id overlays) as PNGs into ``folder``."""
    folder = Path(folder)
    written: dict[str, Path] = {}
    for name, k in sample_frames(world).items():
        cond = world.frame_conditions(k)
        if name == "night":
            cond = world.conditions(night=True, time=cond.time, noise_seed=k)
        image, ids = world.render(world.drive.poses[k], cond)
        for suffix, picture in (("", image), ("_ids", overlay_ids(image, ids))):
            ok, data = cv2.imencode(".png", cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
            if not ok:
                raise RuntimeError(f"could not encode the sample {name}")
            path = folder / f"{name}{suffix}.png"
            atomic_write_bytes(path, data.tobytes())
            written[name + suffix] = path
    return written
