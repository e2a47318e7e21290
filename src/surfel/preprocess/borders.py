"""Borders of open surfaces: which points lie on the edge of a sheet, and which way is out.

A disk centred on a sheet's last row of samples spills past the sheet's edge by its radius,
which grows the outline of every open surface (a flat part, cloth, a scanned patch). As in the
boundary clipping of Pauly, Keiser, Kobbelt & Gross 2003 ("Shape modeling with point-sampled
geometry"), splats are cut at the border instead.

A point p is on a border when its neighbours, projected into its tangent plane, leave an
angular gap of at least BORDER_GAP (an interior point of a regular sampling sees gaps of about
60 degrees) and no second gap over INTERIOR_GAP (a scan line seen from one of its points). It is
confirmed among its BORDER_CONFIRM nearest neighbours, because a sampling far denser on one side
(a CAD mesh's vertices crowd at its curves) leaves a gap towards the sparse side among the
nearest ones. Not where a neighbour faces away (n_p . n_q < SHEET_COS: the surface folds back
there, a thin closed part). Its outward direction w_p is the middle of the gap.

Aerial scan lines (geospatial clouds) get no borders (`complete.py`): a line with the next line
on one side only looks like one.

What is done with it is the clip lines' (`cells.py`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .cells import SHEET_COS
from .chunked import map_chunks
from .frames import orthonormal_basis
from .neighbourhood import Neighbourhood

BORDER_GAP = math.radians(120.0)   # neighbours leaving a gap this wide: p is on a border
INTERIOR_GAP = math.radians(100.0)  # ... unless another gap is this wide too (a scan line)
BORDER_CONFIRM = 64                 # neighbours among which a border is confirmed
KERNEL_BLOCK = 1024                 # points per parallel task of the kernel


@numba.njit(parallel=True, cache=True)
def _border_outwards(points, normals, index, rows, frames, sheet_cos):  # pragma: no cover - compiled
    """Per point rows[i], the unit tangent (3,) pointing out of the surface if the point lies on
    the border of an open surface, else zero.

    A point is on a border when its neighbours, projected into its tangent plane (t, s) =
    frames[i], leave one angular gap wider than BORDER_GAP while every other gap stays below
    INTERIOR_GAP (two wide gaps: a scan line, not a border); outwards is the middle of the gap.
    A neighbour facing away (n_p . n_q < sheet_cos) means the surface folds back here (a thin
    closed part, sampled too coarsely to show its rim): no border, the splat keeps its overlap."""
    m, k = index.shape
    outwards = np.zeros((m, 3))
    for block in numba.prange((m + KERNEL_BLOCK - 1) // KERNEL_BLOCK):
        angles = np.empty(k)  # one buffer per block of points: an allocation per point costs as much as its work
        for i in range(block * KERNEL_BLOCK, min(m, (block + 1) * KERNEL_BLOCK)):
            _point_outwards(points, normals, index, rows, frames, sheet_cos, i, angles, outwards)
    return outwards


@numba.njit(cache=True, inline="always")
def _point_outwards(points, normals, index, rows, frames, sheet_cos, i, angles, out):  # pragma: no cover - compiled
    """out[i]: row i of `_border_outwards`, with angles (k,) as scratch."""
    k = index.shape[1]
    p = rows[i]
    used = 0
    folded = False
    for j in range(k):
        q = index[i, j]
        facing = 0.0
        x = 0.0
        y = 0.0
        for a in range(3):
            facing += normals[q, a] * normals[p, a]
            d = points[q, a] - points[p, a]
            x += d * frames[i, 0, a]
            y += d * frames[i, 1, a]
        if facing < sheet_cos:
            folded = True
            break
        if q == p or (x == 0.0 and y == 0.0):
            continue
        # insertion sort as they come: a dozen angles, no allocation
        angle = math.atan2(y, x)
        slot = used
        while slot > 0 and angles[slot - 1] > angle:
            angles[slot] = angles[slot - 1]
            slot -= 1
        angles[slot] = angle
        used += 1
    if used < 3 or folded:
        return
    widest = 0.0
    second = 0.0
    middle = 0.0
    for j in range(used):
        following = angles[j + 1] if j + 1 < used else angles[0] + 2.0 * math.pi
        gap = following - angles[j]
        if gap > widest:
            second = widest
            widest = gap
            middle = angles[j] + 0.5 * gap
        elif gap > second:
            second = gap
    if widest >= BORDER_GAP and second <= INTERIOR_GAP:
        co = math.cos(middle)
        si = math.sin(middle)
        for a in range(3):
            out[i, a] = co * frames[i, 0, a] + si * frames[i, 1, a]


def border_outwards(nbh: Neighbourhood, normals: np.ndarray, index: np.ndarray, progress: bool | None) -> np.ndarray:
    """(N, 3): the outward unit tangent of each point on the border of an open surface, zero
    elsewhere, in the neighbourhood's order. Points that look like borders among their nearest
    neighbours `index` are confirmed among their BORDER_CONFIRM nearest: in a sampling much denser
    on one side (a CAD mesh's vertices crowd at its curves), the nearest neighbours alone leave a
    gap towards the sparse side where the surface goes on."""
    n = len(nbh.points)
    outwards = map_chunks(lambda start, stop: _border_outwards(nbh.points, normals, index[start:stop],
                                                               np.arange(start, stop),
                                                               orthonormal_basis(normals[start:stop]), SHEET_COS),
                          n, progress, "borders")
    candidates = np.flatnonzero(outwards.any(axis=1))
    if len(candidates) and n > index.shape[1]:
        wide = nbh.nearest(candidates, BORDER_CONFIRM)
        outwards[candidates] = _border_outwards(nbh.points, normals, wide, candidates,
                                                orthonormal_basis(normals[candidates]), SHEET_COS)
    return outwards
