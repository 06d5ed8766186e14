"""The kornia path of IPM: batched, differentiable warps that run on a GPU when there is one.

torch and kornia are imported inside the functions, so that the cv2 path never loads them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from sgf_pipeline.calibration import Calibration
from sgf_pipeline.types import BevGrid
from sgf_plugins.shared.bev_homography import MIN_DEPTH, RollAxis

if TYPE_CHECKING:
    import torch


def resolve_device(device: str) -> str:
    """``auto`` becomes ``cuda`` when a GPU is usable, else ``cpu``; other names pass through."""
    if device != "auto":
        return device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _rotations(axis: str, angles: torch.Tensor) -> torch.Tensor:
    import torch

    c, s = torch.cos(angles), torch.sin(angles)
    one, zero = torch.ones_like(angles), torch.zeros_like(angles)
    if axis == "x":
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "y":
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def bev_to_image_homographies(
    calibration: Calibration,
    grid: BevGrid,
    psi: torch.Tensor,
    theta: torch.Tensor,
    roll_axis: RollAxis = "optical",
) -> torch.Tensor:
    """(B, 3, 3) homographies from BEV index coordinates to image pixels, differentiable in ``psi``, ``theta``.

    The batched torch form of :func:`sgf_plugins.shared.bev_homography.bev_to_image_homography` (eq. 1-4).
    """
    import torch

    dtype, device = psi.dtype, psi.device
    as_tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
    pose = calibration.camera_to_base_matrix
    r_cb = as_tensor(pose[:3, :3])
    if roll_axis == "optical":
        rotation = _rotations("y", theta) @ r_cb @ _rotations("z", -psi)
    else:
        rotation = _rotations("y", theta) @ _rotations("x", -psi) @ r_cb
    world_to_camera = rotation.transpose(-1, -2)
    position = as_tensor(pose[:3, 3])
    plane = torch.stack([world_to_camera[..., 0], world_to_camera[..., 1], -world_to_camera @ position], dim=-1)
    pixel_to_ground = as_tensor(np.linalg.inv(grid.ground_to_pixel_matrix))
    return as_tensor(calibration.intrinsics.matrix) @ plane @ pixel_to_ground


def warp_to_bev(
    images: torch.Tensor,
    homographies: torch.Tensor,
    grid: BevGrid,
    mode: str = "bilinear",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp (B, C, H, W) float images into the BEV with (B, 3, 3) BEV -> image homographies.

    Returns the BEVs (B, C, h, w), zero where the ground is not visible, and the visibility masks
    (B, h, w): the pixel centre maps in front of the camera and inside ``[0, W-1] x [0, H-1]``, the
    same rule as :func:`sgf_plugins.shared.bev_homography.visible_mask`.
    """
    import torch
    from kornia.geometry.transform import warp_perspective

    height, width = images.shape[-2:]
    homographies = homographies.to(images.dtype)
    # kornia takes the source -> destination transform (align_corners: pixel centres on integers).
    bev = warp_perspective(
        images, torch.linalg.inv(homographies), (grid.height, grid.width), mode=mode, align_corners=True
    )
    v, u = torch.meshgrid(
        torch.arange(grid.height, dtype=images.dtype, device=images.device),
        torch.arange(grid.width, dtype=images.dtype, device=images.device),
        indexing="ij",
    )
    points = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(-1, 3)
    mapped = points @ homographies.transpose(-1, -2)
    depth = mapped[..., 2]
    x = mapped[..., 0] / depth.clamp_min(MIN_DEPTH)
    y = mapped[..., 1] / depth.clamp_min(MIN_DEPTH)
    valid = (depth > MIN_DEPTH) & (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    valid = valid.reshape(-1, grid.height, grid.width)
    return bev * valid[:, None].to(bev.dtype), valid


def warp_image(
    pixels: np.ndarray, homography: np.ndarray, grid: BevGrid, interpolation: str, device: str
) -> tuple[np.ndarray, np.ndarray]:
    """One uint8 image through :func:`warp_to_bev`, back to a uint8 BEV and a bool mask."""
    import torch

    tensor: Any = torch.from_numpy(np.ascontiguousarray(pixels))
    tensor = tensor.to(device=device, dtype=torch.float32)
    tensor = tensor[None, None] if tensor.ndim == 2 else tensor.permute(2, 0, 1)[None]
    h = torch.as_tensor(homography, dtype=torch.float64, device=device)[None]
    mode = "nearest" if interpolation == "nearest" else "bilinear"
    with torch.no_grad():
        bev, valid = warp_to_bev(tensor, h.to(torch.float32), grid, mode=mode)
    out = bev[0].round().clamp(0, 255).to(torch.uint8).cpu().numpy()
    out = out[0] if pixels.ndim == 2 else np.ascontiguousarray(out.transpose(1, 2, 0))
    return out, valid[0].cpu().numpy()
