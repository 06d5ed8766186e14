"""Distance travelled between two sightings, shortened by the loop closures that anchor the estimate.

Odometry drift between two poses grows with the path driven between them. Once a loop closure
joins two frames and the back-end's estimate satisfies it, the estimate's error between them is
reset: the relevant path then runs to the loop's one end and continues from its other end at no
cost. Both the association's spatial gate and the loop stage's prediction gate measure drift
this way. Frames are points on the line of distance travelled; a shortcut joins two such points.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence

import numpy as np


def anchored_distances(start: float, targets: np.ndarray, shortcuts: Sequence[tuple[float, float]]) -> np.ndarray:
    """Shortest path along the line of travelled distance from ``start`` to each of ``targets``.

    ``shortcuts`` are pairs of travelled distances joined at no cost (absorbed loop closures).
    Without shortcuts this is ``|targets - start|``. NaN targets stay NaN.
    """
    targets = np.asarray(targets, dtype=np.float64)
    direct = np.abs(targets - start)
    if not shortcuts:
        return direct
    nodes = np.unique(np.array([start, *(s for pair in shortcuts for s in pair)], dtype=np.float64))
    slot = {float(v): k for k, v in enumerate(nodes)}
    graph: list[list[tuple[int, float]]] = [[] for _ in nodes]
    for k in range(len(nodes) - 1):
        w = float(nodes[k + 1] - nodes[k])
        graph[k].append((k + 1, w))
        graph[k + 1].append((k, w))
    for a, b in shortcuts:
        i, j = slot[float(a)], slot[float(b)]
        graph[i].append((j, 0.0))
        graph[j].append((i, 0.0))
    best = np.full(len(nodes), np.inf)
    source = slot[float(start)]
    best[source] = 0.0
    queue = [(0.0, source)]
    while queue:
        d, n = heapq.heappop(queue)
        if d > best[n]:
            continue
        for m, w in graph[n]:
            if d + w < best[m]:
                best[m] = d + w
                heapq.heappush(queue, (d + w, m))
    # through the best node left of each target (best - node + target) or right of it (best + node - target)
    left = np.minimum.accumulate(best - nodes)
    right = np.minimum.accumulate((best + nodes)[::-1])[::-1]
    k = np.searchsorted(nodes, np.nan_to_num(targets, nan=0.0), side="right")
    via_left = np.where(k > 0, targets + left[np.maximum(k - 1, 0)], np.inf)
    via_right = np.where(k < len(nodes), right[np.minimum(k, len(nodes) - 1)] - targets, np.inf)
    return np.minimum(direct, np.minimum(via_left, via_right))
