"""Street lamps in the camera view: a pole and a head that glows at night."""

from __future__ import annotations

import cv2
import numpy as np

from sgf_plugins.world.drawing import CameraView, Item, Lighting, ToCamera, clip_near, in_view
from sgf_plugins.world.layout import CampusLayout, Lamp


class Lamps:
    """The campus street lamps standing on the ground, and their drawing."""

    def __init__(self, layout: CampusLayout, lamp_z: np.ndarray) -> None:
        self.layout = layout
        self.lamp_z = lamp_z
        self._lamps = np.array(
            [[lp.position[0], lp.position[1], z, lp.height] for lp, z in zip(layout.lamps, lamp_z, strict=True)]
        ).reshape(-1, 4)

    def queue(self, items: list[Item], view: CameraView) -> None:
        """Queue the lamps within 60 m whose foot or head can show in the image."""
        centre, rot, trans, image = view.centre, view.rot, view.trans, view.image
        depth, K, light, to_cam, project = view.depth, view.K, view.light, view.to_cam, view.project
        h, w = image.shape[:2]
        layout = self.layout
        if len(self._lamps):
            lp = self._lamps
            near = np.flatnonzero((lp[:, 0] - centre[0]) ** 2 + (lp[:, 1] - centre[1]) ** 2 < 60.0**2)
            if near.size:
                tops = np.column_stack([lp[near, 0], lp[near, 1], lp[near, 2] + lp[near, 3]]) @ rot.T + trans
                bases = lp[near, :3] @ rot.T + trans
                show = in_view(tops, K, w, h, np.full(near.size, 20.0)) | in_view(
                    bases, K, w, h, np.full(near.size, 20.0)
                )
                for i in near[show]:
                    item = self._lamp_item(
                        layout.lamps[i], float(self.lamp_z[i]), to_cam, project, image, depth, K, light
                    )
                    if item is not None:
                        items.append(item)

    def _lamp_item(
        self,
        lamp: Lamp,
        z0: float,
        to_cam: ToCamera,
        project: ToCamera,
        image: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> Item | None:
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
