"""The reference recursive traversal of a point hierarchy (survey section 2.2.1).

Starting at the root, a node whose image-space error exceeds the threshold eps is refined
(its children are visited), otherwise its splat is drawn; leaves are always drawn. The
image-space error of a node at eye distance r is e_g f / r pixels for a perspective camera
(f = camera.fy: the error is taken view-independent, facing the viewer, as in the paper)
and e_g p for an orthographic one (p pixels per world unit). The recursion is evaluated
breadth first, one vectorised step per tree level.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from .build import LodTree
from .sequential import lod_scale, view_distances


def select_recursive(tree: LodTree, camera: Camera, epsilon: float) -> np.ndarray:
    """Sorted indices of the nodes the recursive traversal draws for `camera` at eps pixels."""
    k = lod_scale(camera, epsilon)
    ortho = camera.ortho_height is not None
    frontier = np.array([tree.root], np.int64)
    drawn = []
    while len(frontier):
        error = tree.e_g[frontier].astype(np.float64) * k
        # refine iff e_g f / r > eps, i.e. r < e_g k (orthographic: e_g p / eps > 1)
        refine = error > 1.0 if ortho else view_distances(tree.positions[frontier], camera) < error
        drawn.append(frontier[~refine])
        frontier = tree.children_of(frontier[refine])
    return np.sort(np.concatenate(drawn))
