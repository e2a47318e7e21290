"""Bundled data: Spot (Keenan Crane, CC0), the demo model.

spot.npz holds the referenced vertices of ../shared/data/spot.obj (float32, turned 150
degrees about +Y so that the default front view shows her face), their area-weighted
vertex normals and the triangles, compressed; no pickles.
"""

from __future__ import annotations

from importlib.resources import files

import numpy as np

from ..cloud import PointCloud

# Spot's own colour for the demo picture (the OBJ's texture is not bundled).
DEMO_COLOR = (0.93, 0.62, 0.36)


def demo_path():
    return files(__name__) / "spot.npz"


def demo_cloud() -> PointCloud:
    with np.load(str(demo_path()), allow_pickle=False) as data:
        n = len(data["positions"])
        return PointCloud(data["positions"], normals=data["normals"], faces=data["faces"],
                          colors=np.tile(np.float32(DEMO_COLOR), (n, 1)), source="spot (bundled demo)")
