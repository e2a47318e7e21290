"""Sharp features: which points are faces of a piecewise smooth shape, which lie on its creases.

Circular or elliptical splats are smooth; at the crease of a piecewise smooth shape (a CAD part,
a building) every splat near the edge sticks out past it, and the silhouette grows a scalloped
rim. Following the clipped splats of Zwicker, Pauly, Knoll & Gross 2002 ("Pointshop 3D") and
Pauly, Keiser, Kobbelt & Gross 2003 ("Shape modeling with point-sampled geometry"), splats are
cut at creases. This module finds where:

  * flat points: those whose neighbours with normals within SHARP_ANGLE lie within FLAT_SIN2
    of their tangent plane (faces; not coarsely sampled curved surfaces, whose neighbours'
    planes would facet them);
  * a point p and a flat neighbour q with normals more than SHARP_ANGLE apart lie across a
    crease, the line where their tangent planes meet, whether p is flat too or lies on a
    coarsely sampled curved surface meeting q's face (only a face's plane makes an edge);
  * a flat point p and a neighbour q in its plane (within FLAT_SIN2) with normals more than
    SHARP_ANGLE apart lie across the rim of p's face, where a coarse curved surface meets it
    (a bolt hole, a rounded outer edge): q is not flat, and it is on the crease line;
  * crease points, which lie (within ON_PLANE_SIN2) in the planes of two flat neighbours more
    than SHARP_ANGLE apart (on the edge itself, their normals averaged over both faces), stick
    out of one face or the other whatever their orientation: they are dropped;
  * a flat neighbour whose oriented normal faces away from the point's (n_p . n_q < SHEET_COS)
    samples the same surface from its other side when it lies in the point's face (within
    FLAT_SIN2 of its plane; a scan that sees an open shell from inside and out: denoised, the
    two sides' samples interleave in one plane). It makes no crease: it would cut the point's
    splat near its centre, and two such neighbours would drop the point. A thin sheet's other
    side, off that plane, still clips.

What is done with it is the cells' (`cells.py`): a point's cell ends at such a crease instead
of at the bisector, and its clip lines are the nearest such creases, or rims (moved out a
little); crease points are cut away whole and bound no cell. Those kernels share the crease
geometry, so they live in one module (numba's on-disk cache does not see a change to a function
in another file).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from ..threads import over_rows
from .chunked import map_chunks
from .frames import unit
from .neighbourhood import Neighbourhood

SHARP_ANGLE = 45.0   # degrees between neighbouring normals that make a sharp feature:
                     # a 90 degree crease tilts its averaged vertex normals 45 degrees
SHARP_COS = math.cos(math.radians(SHARP_ANGLE))
FLAT_SIN2 = math.sin(math.radians(10.0)) ** 2     # a face: its neighbours this close to its plane
ON_PLANE_SIN2 = math.sin(math.radians(3.0)) ** 2  # a point this close to a neighbour's plane lies in it
SHEET_COS = -0.5     # neighbours' normals more than 120 degrees apart: two sides of a sheet
NEAR_COS = math.cos(math.radians(0.5 * SHARP_ANGLE) - 1e-6)  # within half SHARP_ANGLE, rounding aside
CREASE_BLOCK = 1024  # the fewest points per thread's piece of `_crease_points`


class SharpFeatures(NamedTuple):
    """Where the cells end (a numba argument: masks in the neighbourhood's sorted order)."""

    flat: np.ndarray      # (N,) bool: faces, whose planes end their neighbours' cells at creases
    crease: np.ndarray    # (N,) bool: crease points, dropped
    sharp_cos: float      # normals of two faces with a smaller dot product meet at a crease
    on_plane_sin2: float  # squared sine within which a point lies in a plane
    sheet_cos: float      # a neighbour facing away more than this is another side: no crease
    flat_sin2: float      # squared sine within which a neighbour lies in a face's plane

    @classmethod
    def none(cls, n: int) -> SharpFeatures:
        """No sharp features: no point is flat, none is dropped."""
        return cls(np.zeros(n, bool), np.zeros(n, bool), SHARP_COS, ON_PLANE_SIN2, SHEET_COS, FLAT_SIN2)


def _flat_points(points, index, start, normals):
    """Whether each point start + i is flat: its neighbours with normals within SHARP_ANGLE of
    its own lie in its tangent plane (within FLAT_SIN2)."""
    m = len(index)
    flat = np.ones(m, np.bool_)
    over_rows(_flat_points_rows, m, points, index, start, normals, flat)
    return flat


@numba.njit(cache=True, nogil=True)
def _flat_points_rows(first, stop, points, index, start, normals, flat):  # pragma: no cover - compiled
    """Rows first:stop of `_flat_points`."""
    k = index.shape[1]
    for i in range(first, stop):
        p = start + i
        for j in range(k):
            q = index[i, j]
            height = 0.0
            facing = 0.0
            distance2 = 0.0
            for a in range(3):
                offset = points[q, a] - points[p, a]
                height += offset * normals[p, a]
                facing += normals[q, a] * normals[p, a]
                distance2 += offset * offset
            if facing >= SHARP_COS and height * height > FLAT_SIN2 * distance2:
                flat[i] = False
                break


def _crease_points(points, index, start, normals, flat):
    """Whether each point start + i lies on a crease itself: in the tangent planes (within
    ON_PLANE_SIN2) of two flat neighbours whose normals are more than SHARP_ANGLE apart, neither
    facing away from the point's (n_p . n_q < SHEET_COS: its surface seen from behind)."""
    m = len(index)
    crease = np.zeros(m, np.bool_)
    over_rows(_crease_points_rows, m, points, index, start, normals, flat, crease, grain=CREASE_BLOCK)
    return crease


@numba.njit(cache=True, nogil=True)
def _crease_points_rows(first, stop, points, index, start, normals, flat, crease):  # pragma: no cover - compiled
    """Rows first:stop of `_crease_points`."""
    k = index.shape[1]
    # flat neighbours in whose tangent plane the point lies, those with normals within half
    # SHARP_ANGLE of p's (NEAR_COS) and the others; one buffer per call: an allocation
    # per point costs as much as its work
    near, far = np.empty(k, np.int64), np.empty(k, np.int64)
    gathered = np.empty((7, k))  # a point's neighbours' offsets to it, normals and flat marks, in rows
    for i in range(first, stop):
        p = start + i
        for j in range(k):
            q = index[i, j]
            for a in range(3):
                gathered[a, j] = points[p, a] - points[q, a]
                gathered[3 + a, j] = normals[q, a]
            gathered[6, j] = 1.0 if flat[q] and q != p else 0.0
        if _far_flat_neighbours(gathered, k, normals[p, 0], normals[p, 1], normals[p, 2]) == 0:
            continue  # every flat neighbour within half SHARP_ANGLE of p: no pair to compare (most points)
        nears = fars = 0
        for j in range(k):
            q = index[i, j]
            if q == p or not flat[q]:
                continue
            side = 0.0
            distance2 = 0.0
            towards_p = 0.0
            for a in range(3):
                offset = points[p, a] - points[q, a]
                side += offset * normals[q, a]
                distance2 += offset * offset
                towards_p += normals[q, a] * normals[p, a]
            if side * side > ON_PLANE_SIN2 * distance2 or towards_p < SHEET_COS:
                continue
            # two normals within half SHARP_ANGLE of p's lie less than SHARP_ANGLE apart (the
            # triangle inequality of angles): on a flat face no pair needs comparing
            is_near = towards_p >= NEAR_COS
            for other in range(fars + (0 if is_near else nears)):
                o = far[other] if other < fars else near[other - fars]
                across = 0.0
                for a in range(3):
                    across += normals[q, a] * normals[o, a]
                if across < SHARP_COS:
                    crease[i] = True
            if crease[i]:
                break
            if is_near:
                near[nears] = q
                nears += 1
            else:
                far[fars] = q
                fars += 1


@numba.njit(cache=True, nogil=True)
def _far_flat_neighbours(gathered, k, nx, ny, nz):  # pragma: no cover - compiled
    """How many of p's k neighbours (offsets to p gathered[0:3], normals gathered[3:6], flat and
    not p gathered[6]; p's normal n) `_crease_points_rows` compares and files as far: flat, p in
    their plane, not facing away, normals more than half SHARP_ANGLE from p's. Without one, no
    two it compares lie SHARP_ANGLE apart. A loop without branches over contiguous rows, which
    compiles to SIMD code (a 1.4M-point build partition on one core: `find_sharp_features`
    0.32-0.41 -> 0.25-0.28 s)."""
    count = 0
    for j in range(k):
        dx, dy, dz = gathered[0, j], gathered[1, j], gathered[2, j]
        qx, qy, qz = gathered[3, j], gathered[4, j], gathered[5, j]
        side = dx * qx + dy * qy + dz * qz
        distance2 = dx * dx + dy * dy + dz * dz
        towards_p = qx * nx + qy * ny + qz * nz
        count += ((gathered[6, j] != 0.0) & (not side * side > ON_PLANE_SIN2 * distance2)
                  & (not towards_p < SHEET_COS) & (not towards_p >= NEAR_COS))
    return count


def find_sharp_features(nbh: Neighbourhood, normals: np.ndarray, k: int) -> SharpFeatures:
    """The flat points and crease points among each point's k nearest neighbours."""
    n = len(nbh.points)
    index = nbh.first(k)
    normals = unit(normals)
    flat = map_chunks(lambda start, stop: _flat_points(nbh.points, index[start:stop], start, normals), n)
    crease = map_chunks(lambda start, stop: _crease_points(nbh.points, index[start:stop], start, normals, flat), n)
    return SharpFeatures(flat, crease, SHARP_COS, ON_PLANE_SIN2, SHEET_COS, FLAT_SIN2)
