"""Coincident points: samples that share a position, estimated once per position.

A mesh stores a vertex once per distinct set of its corner attributes, so its vertices repeat
where texture coordinates or patches meet (a UV seam, the Newell teapot's patch boundaries).
Every estimation reads a point's k nearest neighbours; a copy at distance 0 fills a slot
without adding a direction or a distance, so along a seam whose every vertex is doubled the
16 nearest are only 8 distinct positions. The tangent-plane Voronoi cells then see half the
neighbours they should and grow past the surface: the teapot's seams grew splats 1.6 to 3
times as large as the same points' without their copies, bulging as blobs over the rim of its
lid (`prepare` estimates once per position instead, `complete.py`).

Copies are grouped by their position and, where normals are given, by whether their normals
agree: a vertex split at a crease for flat shading keeps one sample per face.

Measured on the teapot's 3,644 vertices, 403 of them copies (`python benchmarks/scan_fidelity.py
teapot.obj --vertices --oblique --methods deferred,phong`: 18 views at 512 x 512 against the
mesh): `deferred` 30.07 -> 30.77 dB, `phong` 30.12 -> 30.87 dB (with each copy keeping its own
normal, 30.42 and 30.50 dB: copies facing a little apart speckle the shading where they overlap).
The Khronos duck (trimesh's models/Duck.glb), its 2,399 vertices split along its texture seams
(291 copies): `deferred` 31.65 -> 33.37 dB, `phong` 31.83 -> 33.66 dB (its vertices merged
into one per position, as a mesh without seams has them: 33.84 and 34.07 dB).
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from .frames import unit
from .neighbourhood import Neighbourhood
from .sharp_features import SHARP_ANGLE

SAME_SURFACE_ANGLE = SHARP_ANGLE  # degrees: copies whose normals differ by more lie on two faces of a crease
SAME_SURFACE_COS = float(np.cos(np.radians(SAME_SURFACE_ANGLE)))


def coincident_groups(cloud: PointCloud, nbh: Neighbourhood
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """(first, inverse, normals) for the neighbourhood `nbh` of `cloud`: one point of each group
    of coincident points, each point's group (`first[inverse]` stands for every point), and the
    groups' mean given normals (None without given normals); None when no two points form a group.

    Only points with a copy among their nearest neighbours are compared (the lists hold the
    point and its copies first): the rest of a large survey costs one comparison each.
    Copies whose given normals lie within SAME_SURFACE_ANGLE of their position's first copy's
    are one sample of a smooth surface (a mesh whose patches meet at a seam gives each copy its
    own patch's normal: the teapot's differ by up to 30 degrees); the others each keep their own."""
    if nbh.index.shape[1] < 2:
        return None
    second, copied = nbh.index[:, 1], np.ones(len(nbh.points), bool)
    for axis in range(3):  # a column at a time: no (N, 3) temporary for a survey's millions
        copied &= nbh.points[second, axis] == nbh.points[:, axis]
    if not copied.any():
        return None
    candidates = np.sort(nbh.order[copied])
    _, first, inverse = np.unique(cloud.positions[candidates].astype(np.float64), axis=0, return_index=True,
                                  return_inverse=True)
    group = np.arange(len(cloud))
    group[candidates] = candidates[first][inverse.reshape(-1)]
    if cloud.normals is not None:
        normals = cloud.normals.astype(np.float64)
        # a copy facing apart from its position's first is a group of its own
        apart = np.einsum("ij,ij->i", normals, normals[group]) < SAME_SURFACE_COS
        group[apart] = np.flatnonzero(apart)
    first, inverse = np.unique(group, return_inverse=True)
    if len(first) == len(cloud):
        return None
    if cloud.normals is None:
        return first, inverse, None
    summed = np.zeros((len(first), 3))
    np.add.at(summed, inverse, normals)
    return first, inverse, unit(summed)
