"""What stands above the ground in a camera view: building walls, trees, lamps, people and vehicles.

Everything here draws into a float image with painter's order (far first) and a depth test
against the ground where it matters (walls and trees behind a rise). People and vehicles also
draw into an occlusion mask, so that the marking ids they hide become 0.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sgf_plugins.world.buildings import Buildings
from sgf_plugins.world.drawing import CameraView, Item, Lighting, PlacedAgent, ToCamera, clip_near
from sgf_plugins.world.lamps import Lamps
from sgf_plugins.world.layout import CampusLayout
from sgf_plugins.world.pedestrians import draw_person
from sgf_plugins.world.trees import Trees
from sgf_plugins.world.vehicles import draw_vehicle

__all__ = ["Lighting", "PlacedAgent", "Scenery", "clip_near"]


class Scenery:
    """Draws sky-line, walls, trees, lamps and moving people and vehicles for one camera.

    Each kind of object has its builder (:class:`Buildings`, :class:`Trees`, :class:`Lamps`, and the
    drawing of people and vehicles); the scenery culls, queues them far first and draws.
    """

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
        self.buildings = Buildings(layout, seed, self.building_z)
        self.trees = Trees(layout, seed, self.tree_z)
        self.lamps = Lamps(layout, self.lamp_z)

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
        items: list[Item] = []

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
            view = CameraView(centre, rot, trans, image, depth, K, light, to_cam, project)
            for builder in (self.trees, self.lamps, self.buildings):  # each culls (vectorised) and queues its own
                builder.queue(items, view)
        for placed in agents:
            item = self._agent_item(placed, to_cam, project, image, occlusion, K, light)
            if item is not None:
                items.append(item)
        for _, draw in sorted(items, key=lambda it: -it[0]):
            draw()

    def _agent_item(
        self,
        placed: PlacedAgent,
        to_cam: ToCamera,
        project: ToCamera,
        image: np.ndarray,
        occlusion: np.ndarray,
        K: np.ndarray,
        light: Lighting,
    ) -> Item | None:
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
            return dist, lambda: draw_person(agent, base, heading, walked, to_cam, project, image, occlusion, K, light)
        return dist, lambda: draw_vehicle(
            agent, base, heading, self._camera_world, to_cam, project, image, occlusion, light
        )

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
        self.buildings.set_camera(self._cam_rot, self._cam_trans)
