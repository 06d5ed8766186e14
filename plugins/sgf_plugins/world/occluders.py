"""People and vehicles in front of the camera: who is near the robot at a time, and their shadows."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sgf_plugins.world.conditions import RenderConditions
from sgf_plugins.world.drawing import PlacedAgent, clip_near
from sgf_plugins.world.layout import Agent, CampusLayout
from sgf_plugins.world.noise import rng_for
from sgf_plugins.world.sun import Sun
from sgf_plugins.world.terrain import Terrain

#: A person's footprint (16 points on a circle of 0.18 m), for their shadow.
_BODY = 0.18 * np.stack([np.cos(np.arange(16) * math.pi / 8), np.sin(np.arange(16) * math.pi / 8)], axis=1)


class Occluders:
    """The agents of the layout (and any extra passers-by) near the camera, placed, and their shadows."""

    def __init__(
        self,
        layout: CampusLayout,
        terrain: Terrain,
        sun: Sun,
        seed: int,
        camera_to_base: np.ndarray,
        K: np.ndarray,
        size: tuple[int, int],
    ) -> None:
        self.layout = layout
        self.terrain = terrain
        self.sun = sun
        self.seed = seed
        self.camera_to_base = camera_to_base
        self.K = K
        self.width, self.height = size
        self._boxes: np.ndarray | None = None

    def agents(self, conditions: RenderConditions, pose: np.ndarray) -> list[PlacedAgent]:
        """The people and vehicles near the camera at this time, where they are."""
        candidates: list[Agent] = []
        x, y = pose[0, 3], pose[1, 3]
        if conditions.occluders and self.layout.agents:
            if self._boxes is None:
                self._boxes = np.array(
                    [[*a.points.min(axis=0), *a.points.max(axis=0)] for a in self.layout.agents], np.float64
                )
            box = self._boxes
            near = (box[:, 0] < x + 60) & (box[:, 2] > x - 60) & (box[:, 1] < y + 60) & (box[:, 3] > y - 60)
            candidates = [self.layout.agents[int(i)] for i in np.flatnonzero(near)]
        if conditions.extra_occluders:
            rng = rng_for(self.seed, 411, conditions.noise_seed)
            heading = math.atan2(pose[1, 0], pose[0, 0])
            for _ in range(conditions.extra_occluders):
                fwd, side = rng.uniform(1.2, 7.0), rng.uniform(-2.5, 2.5)
                px = x + fwd * math.cos(heading) - side * math.sin(heading)
                py = y + fwd * math.sin(heading) + side * math.cos(heading)
                a = rng.uniform(-math.pi, math.pi)
                pts = np.array([[px, py], [px + math.cos(a) * 0.01, py + math.sin(a) * 0.01]])
                colours = (
                    tuple(int(v) for v in rng.integers(20, 230, 3)),
                    tuple(int(v) for v in rng.integers(20, 160, 3)),
                    tuple(int(v) for v in rng.integers(140, 235, 3)),
                    (30, 30, 30),
                )
                size = (0.3, 0.45, float(rng.uniform(1.55, 1.9)))
                candidates.append(Agent("pedestrian", pts, 0.0, 0.0, 0.0, size, colours))  # type: ignore[arg-type]
        states = [a.state(conditions.time) for a in candidates]
        cam_xy = (pose @ self.camera_to_base)[:2, 3]
        kept = [
            (a, s)
            for a, s in zip(candidates, states, strict=True)
            # within 60 m, and people step aside: nobody is closer than 1.2 m to the camera
            if abs(s[0][0] - x) < 60 and abs(s[0][1] - y) < 60 and math.hypot(*(s[0] - cam_xy)) > 1.2
        ]
        if not kept:
            return []
        xy = np.array([s[0] for _, s in kept])
        z = self.terrain.height(xy[:, 0], xy[:, 1])
        return [PlacedAgent(a, s[0], s[1], s[2], float(zz)) for (a, s), zz in zip(kept, z, strict=True)]

    def shadows(self, agents: list[PlacedAgent], cam: np.ndarray, sunlit: np.ndarray) -> None:
        """Darken the sunlit fraction (uint8) where people and vehicles shade the ground."""
        h, w = self.height, self.width
        world_to_cam = np.linalg.inv(cam)
        off = self.sun.shadow_offset
        for placed in agents:
            agent, p, heading, z0 = placed.agent, placed.position, placed.heading, placed.z
            length, width, height = agent.size
            if agent.kind == "pedestrian":
                body = _BODY
                ground = np.concatenate([p + body, p + off * height * 0.92 + body * 0.8])
            else:
                c, s = math.cos(heading), math.sin(heading)
                fp = np.array(
                    [
                        [length / 2, width / 2],
                        [-length / 2, width / 2],
                        [-length / 2, -width / 2],
                        [length / 2, -width / 2],
                    ]
                ) @ np.array([[c, s], [-s, c]])
                ground = np.concatenate([p + fp, p + fp + off * height])
            hull = cv2.convexHull(ground.astype(np.float32))[:, 0, :].astype(np.float64)
            pts = np.column_stack([hull, np.full(len(hull), z0 + 0.01), np.ones(len(hull))])
            pc = (pts @ world_to_cam.T)[:, :3]
            pc = clip_near(pc)
            if len(pc) < 3:
                continue
            uv = np.stack(
                [self.K[0, 0] * pc[:, 0] / pc[:, 2] + self.K[0, 2], self.K[1, 1] * pc[:, 1] / pc[:, 2] + self.K[1, 2]],
                1,
            )
            if np.abs(uv).max() > 1e5:
                continue
            c0, c1 = max(0, math.floor(uv[:, 0].min())), min(w, math.ceil(uv[:, 0].max()) + 1)
            r0, r1 = max(0, math.floor(uv[:, 1].min())), min(h, math.ceil(uv[:, 1].max()) + 1)
            if c1 <= c0 or r1 <= r0:
                continue
            mask = np.zeros((r1 - r0, c1 - c0), np.float32)
            cv2.fillPoly(mask, [np.round((uv - [c0, r0]) * 16).astype(np.int32)], 1.0, cv2.LINE_AA, 4)
            roi = sunlit[r0:r1, c0:c1]
            roi[:] = cv2.multiply(roi, 1.0 - 0.85 * mask, dtype=cv2.CV_8U)
