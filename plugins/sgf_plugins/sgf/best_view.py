"""The best view of a tracked feature (paper Sec. III-B, steps 3-4): Hu-moment groups of views, then the SGF's view."""

from __future__ import annotations

from typing import Literal

import numpy as np

from sgf_plugins.sgf.hu import HuScale, hu_distance
from sgf_plugins.sgf.tracking import FeatureView


def group_views(views: list[FeatureView], threshold: float, scale: HuScale) -> list[list[FeatureView]]:
    """Runs of consecutive non-border views whose Hu distance (eq. 8) stays below ``threshold`` (step 3)."""
    groups: list[list[FeatureView]] = []
    current: list[FeatureView] = []
    for view in views:
        if view.region.touches_border:
            if current:
                groups.append(current)
            current = []
            continue
        if current and hu_distance(current[-1].region.hu, view.region.hu, scale) >= threshold:
            groups.append(current)
            current = []
        current.append(view)
    if current:
        groups.append(current)
    return groups


def _mean_saliency(group: list[FeatureView]) -> float:
    return float(np.mean([v.region.saliency for v in group]))


def best_view(
    groups: list[list[FeatureView]],
    group_choice: Literal["largest", "most_salient"],
    view_choice: Literal["most_salient", "salient_near", "track_near"],
    near_margin: float,
) -> FeatureView:
    """The view that becomes the SGF (step 4), from the non-empty ``groups`` of one track.

    ``group_choice``: the largest group (ties: higher mean saliency) or the most salient one.
    ``view_choice``: the chosen group's most salient view; or, among the views within ``near_margin``
    of its saliency, the nearest to the camera in the chosen group (``salient_near``) or in the
    whole track (``track_near``).
    """
    if group_choice == "largest":
        chosen = max(groups, key=lambda g: (len(g), _mean_saliency(g)))
    else:
        chosen = max(groups, key=_mean_saliency)
    best = max(chosen, key=lambda v: v.region.saliency)
    if view_choice != "most_salient":
        pool = chosen if view_choice == "salient_near" else [v for g in groups for v in g]
        near = [v for v in pool if v.region.saliency >= best.region.saliency - near_margin]
        best = max(near, key=lambda v: float(v.region.pixels[:, 1].mean()))  # rows grow towards the robot
    return best
