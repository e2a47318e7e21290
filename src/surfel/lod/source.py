"""Lazy level-of-detail sources: hierarchies read only as far as a view needs them.

A `LodSource` stands in for a PointCloud wherever a cloud is too large for memory: it knows
its bounds without loading its points, and `select` returns the cut of its sequential point
tree (Dachsbacher et al. 2003, survey section 2.2) for one camera at eps pixels of error,
as an ordinary cloud any splat method renders. Implementations: `lazy.LazyHierarchy` (the
directory `surfel lod build -o NAME.lod` writes) and `copc.CopcSource` (COPC files).
"""

from __future__ import annotations

import os
from typing import Protocol, runtime_checkable

import numpy as np

from ..camera import Camera
from ..cloud import PointCloud


@runtime_checkable
class LodSource(Protocol):
    path: str
    geospatial: bool          # up axis +Z (LAS/LAZ/COPC)
    total_points: int         # leaf (input) points in the whole hierarchy
    bounds: tuple[np.ndarray, np.ndarray]   # world AABB lo, hi (float64 (3,))
    center: np.ndarray        # bbox centre, for auto framing (docs/conventions.md)
    bounding_radius: float    # half the bbox diagonal, like PointCloud

    def select(self, camera: Camera, epsilon: float, point_budget: int | None = None
               ) -> tuple[PointCloud, dict]:
        """The cut of the hierarchy for this view: a PointCloud with normals, radii, axes
        (and colours when the source has them) holding only what the view needs at eps
        pixels of error (eps raised, and reported, if more than point_budget points would be
        selected). Stats: nodes_loaded, bytes_read, points_selected, epsilon_used."""
        ...


def is_source(value: object) -> bool:
    """True for a LodSource (anything with select and bounds that is not a PointCloud)."""
    return not isinstance(value, PointCloud) and isinstance(value, LodSource)


def open_source(path: str | os.PathLike) -> LodSource | None:
    """A lazy source for a surfel LOD directory or a COPC file (*.copc.laz), else None."""
    name = os.fspath(path)
    from .lazy import LazyHierarchy, is_lod_dir

    if is_lod_dir(name):
        return LazyHierarchy(name)
    if name.lower().endswith(".copc.laz") and os.path.isfile(name):
        from .copc import CopcSource

        return CopcSource(name)
    return None


def with_sensor(cloud: PointCloud | LodSource, sensor: tuple[float, float, float] | None):
    """The cloud, or LOD source, with `sensor` as the position of the scanner of all its points
    (None: as it is). A source passes it to the clouds it selects when it estimates them (COPC);
    a .lod hierarchy was estimated when it was built."""
    if sensor is None:
        return cloud
    sensors = np.array([sensor], np.float64)
    if isinstance(cloud, PointCloud):
        return cloud.with_(sensors=sensors)
    if hasattr(cloud, "sensors"):
        cloud.sensors = sensors
    return cloud
