"""Buildings in the camera view: walls with plaster, windows and a plinth, warped onto their quads."""

from __future__ import annotations

import math
from collections import OrderedDict

import cv2
import numpy as np

from sgf_plugins.world.drawing import CameraView, Item, Lighting, ToCamera, blend_into, clip_near
from sgf_plugins.world.layout import Building, CampusLayout
from sgf_plugins.world.noise import lattice_noise, rng_for

_STYLES = [
    ((196, 184, 164), (70, 84, 96), 3.4, 2.6),
    ((168, 82, 62), (58, 70, 82), 3.6, 3.0),
    ((210, 206, 198), (52, 74, 98), 3.3, 2.2),
    ((128, 132, 138), (40, 58, 76), 3.5, 3.4),
    ((182, 160, 120), (66, 80, 88), 3.2, 2.8),
    ((150, 120, 100), (48, 60, 70), 3.8, 2.4),
]


class Buildings:
    """The walls of the campus buildings: their quads, textures (cached per level of detail) and drawing."""

    def __init__(self, layout: CampusLayout, seed: int, building_z: list[float]) -> None:
        self.layout = layout
        self.seed = seed
        self.building_z = building_z
        self._facades: OrderedDict[tuple[int, int, bool, int], np.ndarray] = OrderedDict()
        quads, owners = [], []
        for i, b in enumerate(layout.buildings):
            z0 = self.building_z[i]
            for side in range(4):
                a, c = b.corners[side], b.corners[(side + 1) % 4]
                quads.append(
                    [
                        [a[0], a[1], z0 + b.height],
                        [c[0], c[1], z0 + b.height],
                        [c[0], c[1], z0 - 1.0],
                        [a[0], a[1], z0 - 1.0],
                    ]
                )
                owners.append((i, side))
        self._facade_quads = np.asarray(quads, np.float64).reshape(-1, 4, 3)
        self._facade_owner = owners
        self._cam_rot = np.eye(3)
        self._cam_trans = np.zeros(3)

    def set_camera(self, rot: np.ndarray, trans: np.ndarray) -> None:
        """The world-to-camera rotation and translation of the frame about to be drawn."""
        self._cam_rot = rot
        self._cam_trans = trans

    def facade_texture(self, building: int, side: int, width: float, night: bool, lod: int = 0) -> np.ndarray:
        """RGB texture of one wall (0.1 m per pixel, halved ``lod`` times): plaster, windows, a plinth."""
        key = (building, side, night, lod)
        found = self._facades.get(key)
        if found is not None:
            self._facades.move_to_end(key)
            return found
        if lod > 0:
            finer = self.facade_texture(building, side, width, night, lod - 1)
            half = cv2.resize(
                finer, (max(1, finer.shape[1] // 2), max(1, finer.shape[0] // 2)), interpolation=cv2.INTER_AREA
            )
            self._facades[key] = half
            return half
        key = (building, side, night, 0)
        found = self._facades.get(key)
        if found is not None:
            self._facades.move_to_end(key)
            return found
        b = self.layout.buildings[building]
        wall, glass, storey, bay = _STYLES[b.style]
        res = 0.1
        w_px, h_px = max(2, round(width / res)), max(2, round(b.height / res))
        rng = rng_for(self.seed, 301, building, side)
        noise = lattice_noise(self.seed + 301 + building, 0.0, h_px * res, w_px, h_px, res, 1.6)
        tex = np.empty((h_px, w_px, 4), np.float32)
        tex[..., :3] = np.asarray(wall, np.float32) * (1.0 + 0.06 * noise)[..., None]
        tex[..., 3] = 255.0
        floors = int(b.height // storey)
        bays = max(1, int(width // bay))
        margin = (width - bays * bay) / 2
        lit = rng.random((floors, bays)) < 0.25
        for f in range(floors):
            z0 = f * storey + 0.9
            z1 = z0 + storey * 0.5
            r0, r1 = h_px - round(z1 / res), h_px - round(z0 / res)
            for k in range(bays):
                x0 = margin + k * bay + bay * 0.18
                x1 = x0 + bay * 0.64
                c0, c1 = round(x0 / res), round(x1 / res)
                if night:
                    colour = [88, 74, 50] if lit[f, k] else [9, 10, 13]
                else:
                    colour = [int(v * rng.uniform(0.85, 1.15)) for v in glass]
                cv2.rectangle(tex, (c0, r0), (c1, r1), (*colour, 255.0), -1)
                cv2.rectangle(tex, (c0, r0), (c1, r1), (*[v * 0.6 for v in wall], 255.0), 1)
        tex[h_px - round(0.6 / res) :, :, :3] *= 0.7
        if night:
            window = (tex[..., 0] > 80) & (tex[..., 2] > 50) & (tex[..., 0] < 110)
            tex[..., :3] = np.where(window[..., None], tex[..., :3], tex[..., :3] * 0.05)
        out = np.clip(tex[..., :3], 0, 255).astype(np.uint8)
        self._facades[key] = out
        while len(self._facades) > 96:
            self._facades.popitem(last=False)
        return out

    def queue(self, items: list[Item], view: CameraView) -> None:
        """Queue the walls that face the camera and can show in the image."""
        centre, rot, trans, image = view.centre, view.rot, view.trans, view.image
        depth, K, light, to_cam = view.depth, view.K, view.light, view.to_cam
        h, w = image.shape[:2]
        layout = self.layout
        quads = self._facade_quads
        if len(quads):
            mid = quads.mean(axis=1)
            d2 = (mid[:, 0] - centre[0]) ** 2 + (mid[:, 1] - centre[1]) ** 2
            edge = quads[:, 1, :2] - quads[:, 0, :2]
            normal = np.column_stack([edge[:, 1], -edge[:, 0]])
            facing = ((centre[:2] - mid[:, :2]) * normal).sum(axis=1) > 0
            cand = np.flatnonzero((d2 < 140.0**2) & facing)
            if cand.size:
                pc = quads[cand].reshape(-1, 3) @ rot.T + trans
                pc = pc.reshape(-1, 4, 3)
                z = np.maximum(pc[..., 2], 1e-6)
                u = K[0, 0] * pc[..., 0] / z + K[0, 2]
                v = K[1, 1] * pc[..., 1] / z + K[1, 2]
                front = pc[..., 2] > 0.05
                any_front = front.any(axis=1)
                all_front = front.all(axis=1)
                off = (
                    (u < 0).all(axis=1) | (u > w).all(axis=1) | (v < 0).all(axis=1) | (v > h).all(axis=1)
                ) & all_front
                for j in cand[any_front & ~off]:
                    bi, side = self._facade_owner[j]
                    b = layout.buildings[bi]
                    queued = self._facade_item(bi, side, b, quads[j], centre, to_cam, image, depth, K, light)
                    if queued is not None:
                        items.append(queued)

    def _facade_item(
        self,
        index: int,
        side: int,
        b: Building,
        quad: np.ndarray,
        centre: np.ndarray,
        to_cam: ToCamera,
        image: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> Item | None:
        base_z = self.building_z[index]
        a, c = quad[0, :2], quad[1, :2]
        edge = c - a
        length = float(np.linalg.norm(edge))
        normal = np.array([edge[1], -edge[0], 0.0]) / max(length, 1e-9)
        pc = to_cam(quad)
        dist = float(np.linalg.norm(0.5 * (a + c) - centre[:2]))

        def draw() -> None:
            self._draw_facade(index, side, b, a, c, length, normal, base_z, pc, image, depth, K, light)

        return dist, draw

    def _draw_facade(
        self,
        index: int,
        side: int,
        b: Building,
        a: np.ndarray,
        c: np.ndarray,
        length: float,
        normal: np.ndarray,
        base_z: float,
        pc: np.ndarray,
        image: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> None:
        h, w = image.shape[:2]
        clipped = clip_near(pc)
        if len(clipped) < 3:
            return
        uv = np.stack(
            [K[0, 0] * clipped[:, 0] / clipped[:, 2] + K[0, 2], K[1, 1] * clipped[:, 1] / clipped[:, 2] + K[1, 2]], 1
        )
        c0, c1 = max(0, math.floor(uv[:, 0].min())), min(w, math.ceil(uv[:, 0].max()) + 1)
        r0, r1 = max(0, math.floor(uv[:, 1].min())), min(h, math.ceil(uv[:, 1].max()) + 1)
        if c1 <= c0 or r1 <= r0:
            return
        level = 0.9 * light.gain if light.night else light.at(np.array([*((a + c) / 2), base_z + 2.0]), normal)
        if r1 - r0 < 10:
            # a far wall a few pixels high: its mean colour (the windows are below a pixel)
            colour = self.facade_texture(index, side, length, light.night).reshape(-1, 3).mean(axis=0) * level
            self._fill(image, depth, uv, colour.astype(np.float32), max(float(pc[:, 2].min()), 0.5))
            return
        # the texture level whose texels are about a pixel at the wall's nearest point
        px_per_m = K[0, 0] / max(float(pc[:, 2].min()), 0.5)
        lod = min(4, max(0, math.floor(math.log2(max(1e-6, 10.0 / px_per_m)))))
        tex = self.facade_texture(index, side, length, light.night, lod)
        texel = length / tex.shape[1], b.height / tex.shape[0]
        # texture pixel (x, y) -> world: a + x*texel*e_u + (height - y*texel)*e_z
        e_u = np.array([(c - a)[0], (c - a)[1], 0.0]) / max(length, 1e-9)
        m = np.column_stack(
            [texel[0] * e_u, np.array([0.0, 0.0, -texel[1]]), np.array([a[0], a[1], base_z + b.height])]
        )
        # camera = R m (x, y, 1) (homogeneous world, last coordinate 1 -> translation)
        cam_from_tex = self._cam_rot @ m
        cam_from_tex[:, 2] += self._cam_trans
        hom = K @ cam_from_tex
        shift = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
        warped = cv2.warpPerspective(
            tex, shift @ hom, (c1 - c0, r1 - r0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        alpha = np.zeros((r1 - r0, c1 - c0), np.float32)
        cv2.fillPoly(alpha, [np.round((uv - [c0, r0]) * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
        nearest = float(pc[:, 2].min())
        alpha *= depth[r0:r1, c0:c1] > max(nearest, 0.5)  # a rise of the ground can hide a wall's foot
        # night walls are stored dark with their lit windows: they glow on their own
        roi = image[r0:r1, c0:c1]
        blend_into(roi, warped, alpha, level)

    def _fill(self, image: np.ndarray, depth: np.ndarray, uv: np.ndarray, colour: np.ndarray, z: float) -> None:
        h, w = image.shape[:2]
        c0, c1 = max(0, math.floor(uv[:, 0].min())), min(w, math.ceil(uv[:, 0].max()) + 1)
        r0, r1 = max(0, math.floor(uv[:, 1].min())), min(h, math.ceil(uv[:, 1].max()) + 1)
        if c1 <= c0 or r1 <= r0:
            return
        mask = np.zeros((r1 - r0, c1 - c0), np.float32)
        cv2.fillPoly(mask, [np.round((uv - [c0, r0]) * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
        mask *= depth[r0:r1, c0:c1] > z
        roi = image[r0:r1, c0:c1]
        blend_into(roi, colour, mask)
