"""Turning mesh inputs into points: polygons and triangle strips made triangles, referenced
vertices, vertex normals.

The rendering contract says a mesh yields its referenced vertices as points, with
area-weighted vertex normals from the faces; the OBJ and PLY readers share these steps.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from ._parse import ragged_arange


def triangles_from_polygons(counts: np.ndarray, indices: np.ndarray, vertex_count: int,
                            path: str) -> np.ndarray:
    """(F, 3) int64 triangles from polygons given as vertex counts and concatenated indices.

    Indices are 0-based. Polygons are fan-triangulated around their first vertex. A polygon
    with fewer than 3 vertices, or an index outside [0, vertex_count), raises InputError.
    """
    counts = np.asarray(counts, dtype=np.int64)
    indices = _whole(indices, path)
    if len(counts) and counts.min() < 3:
        raise InputError(path, f"{int((counts < 3).sum())} faces have fewer than 3 vertices")
    outside = (indices < 0) | (indices >= vertex_count)
    if outside.any():
        raise InputError(path, f"{int(outside.sum())} face corners refer to vertices that do not "
                               f"exist (the file has {vertex_count})")
    if (counts == 3).all():
        return indices.reshape(-1, 3)
    # Polygon k (vertices a0..a{n-1}) becomes triangles (a0, ai, ai+1) for i = 1..n-2.
    fan = counts - 2
    first = np.repeat(np.cumsum(counts) - counts, fan)
    step = ragged_arange(fan) + 1
    return np.stack([indices[first], indices[first + step], indices[first + step + 1]], axis=1)


def triangles_from_strips(indices: np.ndarray, vertex_count: int, path: str) -> np.ndarray:
    """(F, 3) int64 triangles from triangle strips given as one list of vertex indices in which
    -1 ends a strip (the PLY ``tristrips`` element of Stanford's and VCG's scans; a strip also
    ends where one of the element's lists does, which the caller marks with a -1).

    Strip a0 a1 a2 a3 ... makes (a0, a1, a2), (a2, a1, a3), (a2, a3, a4), ...: every second
    triangle's first two corners swapped, so that all wind as the first does. Triangles with a
    repeated corner (how strips are stitched together) are dropped. An index below -1 or at or
    beyond vertex_count raises InputError."""
    indices = _whole(indices, path)
    outside = (indices < -1) | (indices >= vertex_count)
    if outside.any():
        raise InputError(path, f"{int(outside.sum())} triangle strip corners refer to vertices that do not "
                               f"exist (the file has {vertex_count})")
    if len(indices) < 3:
        return np.empty((0, 3), np.int64)
    a, b, c = indices[:-2], indices[1:-1], indices[2:]
    # each corner's place in its strip: its index less that of the strip's first corner
    breaks = np.flatnonzero(indices < 0)
    strip_first = np.zeros(len(indices), np.int64)
    strip_first[breaks[breaks + 1 < len(indices)] + 1] = breaks[breaks + 1 < len(indices)] + 1
    place = np.arange(len(indices)) - np.maximum.accumulate(strip_first)
    odd = (place[:-2] % 2 == 1)
    keep = (a >= 0) & (b >= 0) & (c >= 0) & (a != b) & (b != c) & (a != c)
    first, second = np.where(odd, b, a), np.where(odd, a, b)
    return np.stack([first[keep], second[keep], c[keep]], axis=1)


def _whole(indices: np.ndarray, path: str) -> np.ndarray:
    """Vertex indices as int64; float-typed ones (a PLY's ascii body, or a float list) must be
    whole numbers."""
    indices = np.asarray(indices)
    if indices.dtype.kind == "f" and not (np.isfinite(indices) & (indices == np.round(indices))
                                          & (np.abs(indices) < 2.0 ** 62)).all():
        raise InputError(path, "face indices are not integers")
    return indices.astype(np.int64)


def merged_vertices(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions that are equal made one vertex (exact equality, -0 and +0 alike), as a format
    that stores each triangle's corners apart (STL) needs for its triangles to share vertices:
    (the first of each position, in the order of first use; each position's vertex)."""
    positions = np.asarray(positions, np.float64) + 0.0  # -0.0 becomes 0.0, equal as bytes in np.unique
    _, first, inverse = np.unique(positions, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse.reshape(-1)]


def referenced_vertices(faces: np.ndarray, vertex_count: int) -> tuple[np.ndarray, np.ndarray]:
    """The vertices the faces use (ascending ids) and the faces re-indexed into that subset."""
    used = np.zeros(vertex_count, dtype=bool)
    used[faces.ravel()] = True
    keep = np.flatnonzero(used)
    new_id = np.cumsum(used) - 1
    return keep, new_id[faces]


def mesh_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """The vertex normals of a mesh read from a file: `area_weighted_vertex_normals`, or
    None when no face has any area (the vertices are then points whose normals are
    estimated, as for a cloud without normals), as also when a position is not finite (the
    cloud then refuses the file, naming what is wrong)."""
    if not np.isfinite(positions).all():
        return None
    normals = area_weighted_vertex_normals(positions, faces)
    return normals if normals.any() else None


def face_vectors(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) float64: each face's normal scaled by twice its area, the cross product of two of
    its edges (counter-clockwise faces, seen from outside, give outward normals)."""
    corners = np.asarray(positions, dtype=np.float64)[faces]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def edge_runs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The half-edges of triangles `faces` (F, 3) grouped by their edge: half-edge h = 3 f + k
    runs from corner k of face f to corner k + 1, and an edge is its two vertices in either
    order. Returns (order, first, uses): the half-edges order[first[e]:first[e] + uses[e]] are
    those of edge e, in ascending order, the edges ordered by their vertices."""
    start, end = faces, np.roll(faces, -1, axis=1)
    span = int(faces.max()) + 1 if faces.size else 1
    keys = (np.minimum(start, end) * span + np.maximum(start, end)).reshape(-1)
    order = np.argsort(keys, kind="stable")
    _, first, uses = np.unique(keys[order], return_index=True, return_counts=True)
    return order, first, uses


def opening(positions: np.ndarray, faces: np.ndarray) -> float:
    """How far a mesh is from closed: |sum of its faces' area vectors| / sum of their areas.
    0 for a closed surface (the flux of a constant field through it is 0), the share of an
    opening's projected area otherwise: 0.012 to 0.020 for the bunny, the teapot and suzanne,
    whose holes are small, 0.36 for a room without its ceiling, 1 for a flat sheet."""
    vectors = face_vectors(positions, faces)
    total = float(np.linalg.norm(vectors, axis=1).sum())
    return float(np.linalg.norm(vectors.sum(axis=0))) / total if total > 0 else 1.0


def area_weighted_vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit vertex normals: each the sum of its faces' normals weighted by area.

    The cross product of two triangle edges is the face normal scaled by twice the area, so
    summing the raw cross products gives the area weighting. Counter-clockwise faces (seen
    from outside) give outward normals. A vertex whose faces have no area (degenerate
    triangles, or faces cancelling exactly) takes the summed normals of its face neighbours,
    repeatedly; one left without (a degenerate face apart from the rest of the mesh) takes
    that of the nearest vertex that has one, so that one degenerate face never leaves a
    valid mesh with vertices that have no normal. Vertices no face touches, and all vertices
    when no face has any area, are left as zero vectors.
    """
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(positions)
    normals = _sum_per_vertex(faces, face_vectors(positions, faces), n)
    length = np.linalg.norm(normals, axis=1)
    defined = length > 0
    normals[defined] /= length[defined, None]
    undefined = ~defined & (np.bincount(faces.ravel(), minlength=n) > 0)
    while undefined.any():
        neighbours = _sum_per_vertex(faces, normals[faces].sum(axis=1), n)
        length = np.linalg.norm(neighbours, axis=1)
        fixed = undefined & (length > 0)
        if not fixed.any():
            break
        normals[fixed] = neighbours[fixed] / length[fixed, None]
        undefined &= ~fixed
    if undefined.any() and defined.any():
        distances, nearest = cKDTree(positions[defined]).query(positions[undefined])
        # coordinates whose squares overflow (beyond 1e154) find no neighbour: left as zeros
        found = np.isfinite(distances)
        normals[np.flatnonzero(undefined)[found]] = normals[defined][nearest[found]]
    return normals


def _sum_per_vertex(faces: np.ndarray, per_face: np.ndarray, n: int) -> np.ndarray:
    """(n, 3): for each vertex, the sum of the (F, 3) per-face vectors of the faces using it."""
    corner_vertex = faces.ravel()
    per_corner = np.repeat(per_face, 3, axis=0)
    return np.stack([np.bincount(corner_vertex, weights=per_corner[:, k], minlength=n)
                     for k in range(3)], axis=1)
