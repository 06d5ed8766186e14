"""What stands above the ground in a camera view: sky, building walls, trees, lamps, people and vehicles.

Everything here draws into a float image with painter's order (far first) and a depth test
against the ground where it matters (walls and trees behind a rise). People and vehicles also
draw into an occlusion mask, so that the marking ids they hide become 0.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from sgf_plugins.world.layout import Agent, Building, CampusLayout, Lamp, Tree
from sgf_plugins.world.noise import lattice_noise, rng_for

Project = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

_STYLES = [
    ((196, 184, 164), (70, 84, 96), 3.4, 2.6),
    ((168, 82, 62), (58, 70, 82), 3.6, 3.0),
    ((210, 206, 198), (52, 74, 98), 3.3, 2.2),
    ((128, 132, 138), (40, 58, 76), 3.5, 3.4),
    ((182, 160, 120), (66, 80, 88), 3.2, 2.8),
    ((150, 120, 100), (48, 60, 70), 3.8, 2.4),
]


@dataclass
class Lighting:
    """Light falling on upright things: ambient level, sun (day) and the robot's headlight (night)."""

    night: bool
    ambient: float
    sun: np.ndarray
    sun_strength: float
    headlight_origin: np.ndarray
    headlight_frame: np.ndarray
    headlight_power: float
    lamps: list[tuple[np.ndarray, float]]
    gain: float = 1.0

    def beam(self, to: np.ndarray) -> np.ndarray:
        """Headlight intensity towards offsets ``to`` (..., 3) from the lamp: a wide, low-aimed LED beam."""
        local = to @ self.headlight_frame
        ahead = np.maximum(local[..., 0], 1e-6)
        psi = np.arctan2(local[..., 1], ahead)
        phi = np.arctan2(-local[..., 2], np.hypot(ahead, local[..., 1]))
        shape = np.exp(-((psi / 0.65) ** 2) - ((phi - 0.2) / 0.3) ** 2)
        return self.headlight_power * shape * (local[..., 0] > 0)

    def at(self, point: np.ndarray, normal: np.ndarray | None = None) -> float:
        """Light level (1 = sunny ground) times the camera gain, on a surface at ``point`` facing ``normal``."""
        level = self.ambient
        if not self.night:
            if normal is None:
                return (level + 0.45 * self.sun_strength) * self.gain
            return (level + self.sun_strength * max(0.0, float(normal @ self.sun)) * 0.9) * self.gain
        to = point - self.headlight_origin
        r = float(np.linalg.norm(to))
        if r > 1e-6 and self.headlight_power > 0:
            facing = 0.6 if normal is None else max(0.0, float(-(normal @ to)) / r)
            level += float(self.beam(to)) * facing / max(r * r, 0.5)
        for pos, power in self.lamps:
            d2 = float(((point - pos) ** 2).sum())
            level += power / max(d2, 16.0)
        return level * self.gain


@dataclass(frozen=True)
class PlacedAgent:
    """A person or vehicle where it is at the frame's time: position, heading, distance walked, ground height."""

    agent: Agent
    position: np.ndarray
    heading: float
    walked: float
    z: float


#: Memory budget of the scaled and lit tree sprites kept between frames.
SPRITE_CACHE_BYTES = 48 * 2**20


def clip_near(points: np.ndarray, z_near: float = 0.05) -> np.ndarray:
    """Clip a convex polygon (N, 3) in camera coordinates against the plane ``z = z_near``."""
    front = points[:, 2] >= z_near
    if front.all():
        return points
    if not front.any():
        return points[:0]
    out: list[np.ndarray] = []
    n = len(points)
    for i in range(n):
        a, b = points[i], points[(i + 1) % n]
        ina, inb = a[2] >= z_near, b[2] >= z_near
        if ina:
            out.append(a)
        if ina != inb:
            t = (z_near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.asarray(out).reshape(-1, 3)


class Scenery:
    """Draws sky-line, walls, trees, lamps and moving people and vehicles for one camera."""

    def __init__(self, layout: CampusLayout, seed: int, ground: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
        self.layout = layout
        self.seed = seed
        self.building_z = [float(ground(b.corners[:, 0], b.corners[:, 1]).min()) for b in layout.buildings]
        self.tree_z = (
            ground(np.array([t.position[0] for t in layout.trees]), np.array([t.position[1] for t in layout.trees]))
            if layout.trees
            else np.zeros(0)
        )
        self.lamp_z = (
            ground(np.array([lp.position[0] for lp in layout.lamps]), np.array([lp.position[1] for lp in layout.lamps]))
            if layout.lamps
            else np.zeros(0)
        )
        self._facades: OrderedDict[tuple[int, int, bool, int], np.ndarray] = OrderedDict()
        self._canopies = [_pyramid(self._canopy_sprite(k)) for k in range(4)]
        self._sprite_bytes = 0
        # per canopy variant, each pyramid level as contiguous planes: uint8 colour, float32 alpha
        self._sprite_planes = [
            [
                (np.clip(level[..., :3], 0, 255).astype(np.uint8), np.ascontiguousarray(level[..., 3], np.float32))
                for level in p
            ]
            for p in self._canopies
        ]
        self._scaled_sprites: OrderedDict[tuple[int, int, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = (
            OrderedDict()
        )
        self._canopy_colours = [
            (p[0][..., :3] * p[0][..., 3:]).sum(axis=(0, 1)) / max(float(p[0][..., 3].sum()), 1e-6)
            for p in self._canopies
        ]
        self._trees = np.array(
            [
                [t.position[0], t.position[1], z, t.canopy_height, t.canopy_radius]
                for t, z in zip(layout.trees, self.tree_z, strict=True)
            ]
        ).reshape(-1, 5)
        self._lamps = np.array(
            [[lp.position[0], lp.position[1], z, lp.height] for lp, z in zip(layout.lamps, self.lamp_z, strict=True)]
        ).reshape(-1, 4)
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

    # -- textures ----------------------------------------------------------------------------

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

    def _canopy_sprite(self, variant: int) -> np.ndarray:
        """RGBA sprite of a tree crown: clumps of leaves, lit from above, ragged outline."""
        size = 128
        rng = rng_for(self.seed, 311, variant)
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        c = (size - 1) / 2
        r = np.hypot(xx - c, yy - c) / c
        ragged = lattice_noise(self.seed + 311 + variant, 0.0, float(size), size, size, 1.0, 12.0)
        alpha = np.clip((1.0 - r + 0.18 * ragged) * 8.0, 0.0, 1.0)
        clumps = lattice_noise(self.seed + 313 + variant, 0.0, float(size), size, size, 1.0, 6.0)
        leaves = rng.random((size, size)).astype(np.float32)
        base = np.asarray([(54, 92, 38), (70, 104, 44), (46, 82, 40), (88, 110, 50)][variant], np.float32)
        light = 0.65 + 0.35 * (1.0 - yy / size) + 0.25 * clumps + 0.15 * (leaves - 0.5)
        sprite = np.empty((size, size, 4), np.float32)
        sprite[..., :3] = base * light[..., None]
        sprite[..., 3] = alpha * (0.85 + 0.15 * (leaves > 0.3))
        return sprite

    # -- drawing -------------------------------------------------------------------------------

    def draw(
        self,
        image: np.ndarray,
        occlusion: np.ndarray,
        depth: np.ndarray,
        camera_to_world: np.ndarray,
        K: np.ndarray,
        light: Lighting,
        agents: list[PlacedAgent],
        far_field: bool,
    ) -> None:
        """Draw everything above the ground (far first) into ``image`` (uint8 RGB, already exposed)."""
        world_to_camera = np.linalg.inv(camera_to_world)
        rot, trans = world_to_camera[:3, :3], world_to_camera[:3, 3]
        centre = camera_to_world[:3, 3]
        h, w = image.shape[:2]
        items: list[tuple[float, Callable[[], None]]] = []

        def to_cam(p: np.ndarray) -> np.ndarray:
            return p @ rot.T + trans

        def project(pc: np.ndarray) -> np.ndarray:
            z = np.maximum(pc[:, 2], 1e-6)
            return np.stack([K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]], axis=1)

        def visible(pc: np.ndarray) -> bool:
            if (pc[:, 2] < 0.05).all():
                return False
            front = pc[pc[:, 2] > 0.05]
            uv = project(front)
            return not (
                (uv[:, 0] < -w).all() or (uv[:, 0] > 2 * w).all() or (uv[:, 1] < -h).all() or (uv[:, 1] > 2 * h).all()
            )

        if far_field:
            self._cull_and_queue(items, centre, rot, trans, image, depth, K, light, to_cam, project)
        for placed in agents:
            item = self._agent_item(placed, to_cam, project, image, occlusion, K, light)
            if item is not None:
                items.append(item)
        for _, draw in sorted(items, key=lambda it: -it[0]):
            draw()

    def _in_view(self, pc: np.ndarray, K: np.ndarray, w: int, h: int, pad: np.ndarray) -> np.ndarray:
        """Which points (N, 3) in camera coordinates are in front and within ``pad`` px of the image."""
        z = np.maximum(pc[:, 2], 1e-6)
        u = K[0, 0] * pc[:, 0] / z + K[0, 2]
        v = K[1, 1] * pc[:, 1] / z + K[1, 2]
        return (pc[:, 2] > 0.3) & (u > -pad) & (u < w + pad) & (v > -pad) & (v < h + pad)

    def _cull_and_queue(
        self,
        items: list[tuple[float, Callable[[], None]]],
        centre: np.ndarray,
        rot: np.ndarray,
        trans: np.ndarray,
        image: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        light: Lighting,
        to_cam: Callable[[np.ndarray], np.ndarray],
        project: Callable[[np.ndarray], np.ndarray],
    ) -> None:
        """Queue the walls, trees and lamps that can show in the image (vectorised culling first)."""
        h, w = image.shape[:2]
        layout = self.layout
        if len(self._trees):
            tr = self._trees
            near = np.flatnonzero((tr[:, 0] - centre[0]) ** 2 + (tr[:, 1] - centre[1]) ** 2 < 75.0**2)
            if near.size:
                crowns = np.column_stack([tr[near, 0], tr[near, 1], tr[near, 2] + tr[near, 3]]) @ rot.T + trans
                bases = tr[near, :3] @ rot.T + trans
                pad = K[0, 0] * tr[near, 4] / np.maximum(crowns[:, 2], 0.3)
                show = self._in_view(crowns, K, w, h, pad) | self._in_view(bases, K, w, h, pad)
                show &= crowns[:, 2] >= 0.3
                idx = near[show]
                uv_base, uv_crown = project(bases[show]), project(crowns[show])
                r_px = K[0, 0] * tr[idx, 4] / crowns[show, 2]
                off = (
                    (uv_crown[:, 0] + r_px < 0)
                    | (uv_crown[:, 0] - r_px > w)
                    | (uv_crown[:, 1] - r_px > h)
                    | ((uv_base[:, 1] < 0) & (uv_crown[:, 1] + r_px < 0))
                )
                dist = np.hypot(tr[idx, 0] - centre[0], tr[idx, 1] - centre[1])
                # trunks: quads facing the camera, 0.28 m wide at the foot and 0.17 m under the crown
                foot = tr[idx, :3]
                top = foot + np.column_stack([np.zeros((len(idx), 2)), tr[idx, 3]])
                rel = foot[:, :2] - centre[:2]
                side = np.column_stack([-rel[:, 1], rel[:, 0], np.zeros(len(idx))])
                side *= 0.14 / np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
                trunks = np.stack([foot + side, foot - side, top - 0.6 * side, top + 0.6 * side], axis=1)
                trunks = trunks @ rot.T + trans
                for j in np.flatnonzero(~off):
                    i = int(idx[j])
                    draw = self._tree_item(
                        layout.trees[i],
                        tr[i, :3],
                        trunks[j],
                        uv_crown[j],
                        float(r_px[j]),
                        project,
                        image,
                        light,
                    )
                    items.append((float(dist[j]), draw))
        if len(self._lamps):
            lp = self._lamps
            near = np.flatnonzero((lp[:, 0] - centre[0]) ** 2 + (lp[:, 1] - centre[1]) ** 2 < 60.0**2)
            if near.size:
                tops = np.column_stack([lp[near, 0], lp[near, 1], lp[near, 2] + lp[near, 3]]) @ rot.T + trans
                bases = lp[near, :3] @ rot.T + trans
                show = self._in_view(tops, K, w, h, np.full(near.size, 20.0)) | self._in_view(
                    bases, K, w, h, np.full(near.size, 20.0)
                )
                for i in near[show]:
                    item = self._lamp_item(
                        layout.lamps[i], float(self.lamp_z[i]), to_cam, project, image, depth, K, light
                    )
                    if item is not None:
                        items.append(item)
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

    # -- buildings ---------------------------------------------------------------------------

    def _facade_item(
        self,
        index: int,
        side: int,
        b: Building,
        quad: np.ndarray,
        centre: np.ndarray,
        to_cam: Callable[[np.ndarray], np.ndarray],
        image: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> tuple[float, Callable[[], None]] | None:
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
        _blend_into(roi, warped, alpha, level)

    # -- trees and lamps ---------------------------------------------------------------------

    def _tree_item(
        self,
        tree: Tree,
        base: np.ndarray,
        trunk: np.ndarray,
        crown_px: np.ndarray,
        r_px: float,
        project: Callable[[np.ndarray], np.ndarray],
        image: np.ndarray,
        light: Lighting,
    ) -> Callable[[], None]:
        """The drawing of a tree that shows (culled and projected in ``_cull_and_queue``)."""
        crown = base + np.array([0.0, 0.0, tree.canopy_height])

        def draw() -> None:
            level = light.at(crown) if light.night else (light.ambient + 0.6 * light.sun_strength) * light.gain
            tc = clip_near(trunk)
            if len(tc) >= 3:
                tuv = project(tc)
                col = (78.0 * level, 64.0 * level, 52.0 * level)
                cv2.fillPoly(image, [np.round(tuv * 16).astype(np.int32)], col, cv2.LINE_AA, 4)
            if r_px >= 12.0:
                self._sprite(image, tree.variant, crown_px, r_px, level)
            elif r_px >= 1.0:  # a far crown: a blob of its mean colour (its leaves are below a pixel)
                blob = tuple(float(v) for v in self._canopy_colours[tree.variant] * level)
                centre_px = (round(crown_px[0] * 16), round(crown_px[1] * 16))
                axes = (round(r_px * 16), round(r_px * 0.92 * 16))
                cv2.ellipse(image, centre_px, axes, 0.0, 0, 360, blob, -1, cv2.LINE_AA, 4)

        return draw

    def _lamp_item(
        self,
        lamp: Lamp,
        z0: float,
        to_cam: Callable[[np.ndarray], np.ndarray],
        project: Callable[[np.ndarray], np.ndarray],
        image: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> tuple[float, Callable[[], None]] | None:
        base = np.array([lamp.position[0], lamp.position[1], z0])
        top = base + np.array([0.0, 0.0, lamp.height])
        pc = to_cam(np.stack([base, top]))
        if pc[:, 2].max() < 0.3:
            return None
        dist = float(np.linalg.norm(pc[0]))

        def draw() -> None:
            seg = clip_near(np.stack([pc[0], pc[1], pc[1] + [0.001, 0, 0]]))
            if len(seg) < 2:
                return
            uv = project(seg[:2])
            z = max(float(seg[:2, 2].min()), 0.3)
            thick = max(1, round(K[0, 0] * 0.09 / z))
            level = (light.ambient + (0.0 if light.night else 0.5 * light.sun_strength)) * light.gain
            col = tuple(float(v) for v in np.array([58, 60, 62], np.float32) * level)
            p0 = (round(uv[0, 0] * 16), round(uv[0, 1] * 16))
            p1 = (round(uv[1, 0] * 16), round(uv[1, 1] * 16))
            cv2.line(image, p0, p1, col, thick, cv2.LINE_AA, 4)
            if pc[1, 2] > 0.3:
                head = project(pc[1:2])[0]
                r = max(1, round(K[0, 0] * 0.18 / pc[1, 2]))
                glow = (255.0, 236.0, 190.0) if light.night else tuple(v * light.gain for v in (190.0, 190.0, 180.0))
                cv2.circle(image, (round(head[0] * 16), round(head[1] * 16)), r * 16, glow, -1, cv2.LINE_AA, 4)

        return dist, draw

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
        _blend_into(roi, colour, mask)

    def _sprite(self, image: np.ndarray, variant: int, centre: np.ndarray, r_px: float, level: float) -> None:
        """Blend a tree crown of canopy ``variant``, radius ``r_px`` around ``centre`` (px), lit by ``level``."""
        h, w = image.shape[:2]
        # sizes on a scale of 24 steps per octave (3 %): a tree keeps its cached sprite for a few frames
        size = max(2, round(2.0 ** (round(math.log2(max(2.0 * r_px, 1.0)) * 24.0) / 24.0)))
        planes = self._sprite_planes[variant]
        # the smallest pyramid level at least as large as the sprite (the largest if none is)
        level_index = next((i for i in range(len(planes) - 1, -1, -1) if planes[i][1].shape[0] >= size), 0)
        c0 = round(centre[0] - size / 2)
        r0 = round(centre[1] - size / 2)
        cc0, cc1 = max(0, c0), min(w, c0 + size)
        rr0, rr1 = max(0, r0), min(h, r0 + size)
        if cc1 <= cc0 or rr1 <= rr0:
            return
        # scaled and lit sprites are cached (by day every tree has the same light level)
        key = (variant, size, round(level, 3))
        scaled = self._scaled_sprites.get(key)
        if scaled is not None:
            self._scaled_sprites.move_to_end(key)
        else:
            rgb8, alpha8 = planes[level_index]
            rgb = cv2.resize(rgb8, (size, size), interpolation=cv2.INTER_LINEAR)
            alpha = cv2.resize(alpha8, (size, size), interpolation=cv2.INTER_LINEAR)
            scaled = (cv2.convertScaleAbs(rgb, alpha=level), alpha, 1.0 - alpha)
            self._scaled_sprites[key] = scaled
            self._sprite_bytes += sum(a.nbytes for a in scaled)
            while self._sprite_bytes > SPRITE_CACHE_BYTES and len(self._scaled_sprites) > 1:
                _, dropped = self._scaled_sprites.popitem(last=False)
                self._sprite_bytes -= sum(a.nbytes for a in dropped)
        rgb, alpha, rest = (a[rr0 - r0 : rr1 - r0, cc0 - c0 : cc1 - c0] for a in scaled)
        roi = image[rr0:rr1, cc0:cc1]
        roi[:] = cv2.blendLinear(rgb, np.ascontiguousarray(roi), alpha, rest)

    # -- people and vehicles -------------------------------------------------------------------

    def _agent_item(
        self,
        placed: PlacedAgent,
        to_cam: Callable[[np.ndarray], np.ndarray],
        project: Callable[[np.ndarray], np.ndarray],
        image: np.ndarray,
        occlusion: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> tuple[float, Callable[[], None]] | None:
        agent, heading, walked = placed.agent, placed.heading, placed.walked
        base = np.array([placed.position[0], placed.position[1], placed.z])
        pc = to_cam(base[None] + np.array([[0.0, 0.0, 0.9]]))[0]
        if pc[2] < 0.15 or pc[2] > 70.0:
            return None
        uv = project(pc[None])[0]
        h, w = image.shape[:2]
        reach = K[0, 0] * max(agent.size) / pc[2]
        if uv[0] < -reach or uv[0] > w + reach or uv[1] < -reach or uv[1] > h + reach:
            return None
        dist = float(pc[2])
        if agent.kind == "pedestrian":
            return dist, lambda: self._draw_person(
                agent, base, heading, walked, to_cam, project, image, occlusion, K, light
            )
        return dist, lambda: self._draw_vehicle(agent, base, heading, to_cam, project, image, occlusion, light)

    def _draw_person(
        self,
        agent: Agent,
        base: np.ndarray,
        heading: float,
        walked: float,
        to_cam: Callable[[np.ndarray], np.ndarray],
        project: Callable[[np.ndarray], np.ndarray],
        image: np.ndarray,
        occlusion: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> None:
        height = agent.size[2]
        shirt, trousers, skin, shoes = (np.asarray(c, np.float32) for c in agent.colours)
        f = np.array([math.cos(heading), math.sin(heading), 0.0])
        left = np.array([-f[1], f[0], 0.0])
        up = np.array([0.0, 0.0, 1.0])
        swing = 0.28 * math.sin(2 * math.pi * walked / 1.4) if agent.speed > 0 else 0.0
        hip_h, shoulder_h = 0.52 * height, 0.81 * height
        starts, ends, widths, colours = [], [], [], []

        def limb(a: np.ndarray, b: np.ndarray, width: float, colour: np.ndarray) -> None:
            starts.append(a)
            ends.append(b)
            widths.append(width)
            colours.append(colour)

        for side in (1.0, -1.0):
            hip = base + side * 0.09 * left + hip_h * up
            foot = base + side * 0.1 * left + side * swing * f + 0.05 * up
            knee = 0.5 * (hip + foot) + 0.04 * f + 0.02 * up
            limb(hip, knee, 0.14, trousers)
            limb(knee, foot, 0.12, trousers)
            limb(foot, foot + 0.22 * f, 0.09, shoes)
            shoulder = base + side * 0.19 * left + shoulder_h * up
            hand = base + side * 0.22 * left - side * 0.7 * swing * f + 0.43 * height * up
            limb(shoulder, hand, 0.09, shirt)
            limb(hand, hand - 0.06 * up, 0.08, skin)
        limb(base + (hip_h - 0.02) * up, base + (shoulder_h - 0.03) * up, 0.36, shirt)
        limb(base + 0.87 * height * up, base + 0.96 * height * up, 0.2, skin)
        a = to_cam(np.asarray(starts))
        b = to_cam(np.asarray(ends))
        # clip every limb to the part in front of the camera
        za, zb = a[:, 2], b[:, 2]
        keep = np.maximum(za, zb) >= 0.05
        s = np.clip((0.05 - za) / np.where(np.abs(zb - za) > 1e-9, zb - za, 1e-9), 0.0, 1.0)
        a = np.where((za < 0.05)[:, None], a + s[:, None] * (b - a), a)
        s = np.clip((0.05 - zb) / np.where(np.abs(za - zb) > 1e-9, za - zb, 1e-9), 0.0, 1.0)
        b = np.where((zb < 0.05)[:, None], b + s[:, None] * (a - b), b)
        depth = 0.5 * (a[:, 2] + b[:, 2])
        ua, ub = project(a), project(b)
        lit = light.at(base + 1.0 * up)
        # everything per limb as plain numbers first (one numpy pass), then the far limbs drawn first
        thick = np.maximum(1, np.round(K[0, 0] * np.asarray(widths) / np.maximum(depth, 0.05))).astype(np.int64)
        ends16 = np.round(np.concatenate([ua, ub], axis=1) * 16)
        draw = keep & (thick <= 4000) & (np.abs(ends16).max(axis=1) <= 2_000_000)
        lit_colours = (np.asarray(colours, np.float64) * lit).tolist()
        ends_px = ends16.astype(np.int64).tolist()
        thick_px = thick.tolist()
        order = np.argsort(-depth)
        for i in order[draw[order]].tolist():
            x0, y0, x1, y1 = ends_px[i]
            cv2.line(image, (x0, y0), (x1, y1), lit_colours[i], thick_px[i], cv2.LINE_AA, 4)
            cv2.line(occlusion, (x0, y0), (x1, y1), 255, thick_px[i], cv2.LINE_8, 4)

    def _draw_vehicle(
        self,
        agent: Agent,
        base: np.ndarray,
        heading: float,
        to_cam: Callable[[np.ndarray], np.ndarray],
        project: Callable[[np.ndarray], np.ndarray],
        image: np.ndarray,
        occlusion: np.ndarray,
        light: Lighting,
    ) -> None:
        length, width, height = agent.size
        colour = np.asarray(agent.colours[0], np.float32)
        glass = np.array([44, 54, 64], np.float32)
        tyre = np.array([22, 22, 24], np.float32)
        boxes: list[tuple[tuple[float, float, float, float, float, float], np.ndarray]] = []
        if agent.kind == "car":
            boxes.append(((-length / 2, length / 2, -width / 2, width / 2, 0.28, 0.92), colour))
            boxes.append(((-0.32 * length, 0.2 * length, -0.44 * width, 0.44 * width, 0.92, height), glass))
        elif agent.kind == "van":
            boxes.append(((-length / 2, length / 2, -width / 2, width / 2, 0.3, height), colour))
            boxes.append(((0.36 * length, 0.5 * length, -0.46 * width, 0.46 * width, 1.1, 0.92 * height), glass))
        else:
            boxes.append(((-length / 2, length / 2, -width / 2, width / 2, 0.3, 0.85), colour))
            boxes.append(((-length / 2, length / 2, -width / 2, width / 2, height - 0.08, height), colour * 0.95))
            for px in (-0.45 * length, 0.45 * length):
                for py in (-0.45 * width, 0.45 * width):
                    boxes.append(((px - 0.03, px + 0.03, py - 0.03, py + 0.03, 0.85, height - 0.08), tyre * 2))
        for px in (-0.33 * length, 0.33 * length):
            for py in (-0.5 * width, 0.5 * width - 0.22):
                boxes.append(((px - 0.3, px + 0.3, py, py + 0.22, 0.0, 0.6), tyre))
        c, s = math.cos(heading), math.sin(heading)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        camera = self._camera_world
        faces: list[tuple[float, np.ndarray, np.ndarray]] = []
        for (x0, x1, y0, y1, z0, z1), col in boxes:
            corners = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)])
            world = corners @ rot.T + base
            for idx, n_local in (
                ((0, 1, 3, 2), (0, 0, -1)),
                ((4, 5, 7, 6), (0, 0, 1)),
                ((0, 1, 5, 4), (0, -1, 0)),
                ((2, 3, 7, 6), (0, 1, 0)),
                ((0, 2, 6, 4), (-1, 0, 0)),
                ((1, 3, 7, 5), (1, 0, 0)),
            ):
                quad = world[list(idx)]
                normal = rot @ np.asarray(n_local, np.float64)
                if (camera - quad.mean(axis=0)) @ normal <= 0:
                    continue
                level = light.at(quad.mean(axis=0), normal)
                pc = clip_near(to_cam(quad))
                if len(pc) < 3:
                    continue
                faces.append((float(pc[:, 2].mean()), pc, col * level))
        for _, pc, col in sorted(faces, key=lambda f: -f[0]):
            uv = project(pc)
            if np.abs(uv).max() > 100_000:
                continue
            pts = np.round(uv * 16).astype(np.int32)
            cv2.fillPoly(image, [pts], tuple(float(v) for v in col), cv2.LINE_AA, 4)
            cv2.fillPoly(occlusion, [pts], 255, cv2.LINE_8, 4)

    # -- per-frame state set by the renderer -----------------------------------------------------

    _time: float = 0.0
    _cam_rot: np.ndarray = np.eye(3)
    _cam_trans: np.ndarray = np.zeros(3)
    _camera_world: np.ndarray = np.zeros(3)

    def set_frame(self, time: float, camera_to_world: np.ndarray) -> None:
        """Set the time (for moving agents) and the camera of the frame about to be drawn."""
        self._time = time
        world_to_camera = np.linalg.inv(camera_to_world)
        self._cam_rot = world_to_camera[:3, :3]
        self._cam_trans = world_to_camera[:3, 3]
        self._camera_world = camera_to_world[:3, 3]


def _pyramid(sprite: np.ndarray) -> list[np.ndarray]:
    """A sprite and its halvings down to 4 pixels (area-averaged), largest first."""
    levels = [sprite]
    while levels[-1].shape[0] > 4:
        prev = levels[-1]
        levels.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))
    return levels


def _blend_into(roi: np.ndarray, colour: np.ndarray, alpha: np.ndarray, level: float = 1.0) -> None:
    """Alpha-blend ``colour`` x ``level`` (an RGB image or one RGB triple) into a uint8 image region in place."""
    if np.ndim(colour) == 1:
        src = np.empty_like(roi)
        src[:] = np.clip(np.asarray(colour, np.float32) * level, 0.0, 255.0).astype(np.uint8)
    else:
        src = cv2.convertScaleAbs(colour, alpha=level)  # saturates at 255 (colours are never negative)
    a = np.ascontiguousarray(alpha, np.float32)
    roi[:] = cv2.blendLinear(src, np.ascontiguousarray(roi), a, 1.0 - a)
