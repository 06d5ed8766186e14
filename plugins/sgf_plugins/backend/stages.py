"""Back-ends of eq. 11: GTSAM batch Levenberg-Marquardt, iSAM2, and odometry only (the baseline).

Every variant adds each processed frame's odometry, publishes a :class:`PoseEstimate` of every
processed frame on every frame (online), writes the final trajectory as ``trajectory_sgf.tum``
and, with ``save_map``, the run's SGF map (``sgf_map.safetensors``: the groups seen by the loop
stage, from the optimized poses; :mod:`~sgf_plugins.backend.map_writer`). The graph back-ends
share :mod:`~sgf_plugins.backend.graph_backend` (the pose graph, a prior map, ``pose_graph.g2o``);
their parameters are in :mod:`~sgf_plugins.backend.params`.

This module is the plugin: it registers the variants.
"""

from __future__ import annotations

from sgf_pipeline import StageRegistry, hookimpl
from sgf_plugins.backend.isam2 import Isam2Backend
from sgf_plugins.backend.lm import GtsamLmBackend
from sgf_plugins.backend.odometry_only import OdometryBackend


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the back-end variants."""
    registry.add(OdometryBackend)
    registry.add(GtsamLmBackend)
    registry.add(Isam2Backend)
