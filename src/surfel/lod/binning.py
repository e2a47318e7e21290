"""Binning kernels of the out-of-core build (outofcore.py): fine cells, halos, grouping.

The bounding cube lo + [0, size]^3 is cut into res^3 fine cells (res = 2^HISTOGRAM_BITS); a
point p falls in cell q = clamp(floor((p - lo) res / size), 0, res - 1) per axis, flattened
x-major, (q_x res + q_y) res + q_z. Each partition is a union of fine cells (an octree cell).

Halo (the points a partition borrows from its neighbours, so that the neighbour queries of its
border points find what the whole cloud would give them): point p is in the halo of every
partition P other than its own that holds a fine cell within Chebyshev distance h of p, i.e.
whose box meets the cube [p - h, p + h]^3. With f = (p - lo) res / size - q the offset of p in
its cell (in cell widths) and h in cell widths, the cell q + d (d in {-H..H}^3, H = ceil(h))
meets that cube when along every axis

    d < 0:  f + (-d - 1) <= h,     d = 0: always,     d > 0:  (1 - f) + (d - 1) <= h.

Grouping: a stable counting sort of small integer keys (partition indices), the order and the
start of each key's run, so that each partition's points are written in one piece.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(parallel=True, cache=True)
def fine_cells(positions, lo, scale, res):  # pragma: no cover - compiled
    """Flattened fine cell (int64) of each position; scale = res / size."""
    n = len(positions)
    cells = np.empty(n, np.int64)
    for i in numba.prange(n):
        flat = 0
        for axis in range(3):
            q = min(max(np.int64(math.floor((positions[i, axis] - lo[axis]) * scale)), 0), res - 1)
            flat = flat * res + q
        cells[i] = flat
    return cells


@numba.njit(cache=True)
def _halo_of(position, lo, scale, res, lookup, own, halo, reach, found):  # pragma: no cover - compiled
    """The partitions (other than `own`) whose cells lie within `halo` cell widths of the
    position, into found[:count]; returns count."""
    q = np.empty(3, np.int64)
    f = np.empty(3)
    for axis in range(3):
        x = (position[axis] - lo[axis]) * scale
        q[axis] = min(max(np.int64(math.floor(x)), 0), res - 1)
        f[axis] = min(max(x - q[axis], 0.0), 1.0)
    count = 0
    for dx in range(-reach, reach + 1):
        for dy in range(-reach, reach + 1):
            for dz in range(-reach, reach + 1):
                if dx == 0 and dy == 0 and dz == 0:
                    continue
                flat = 0
                inside = True
                for axis, d in ((0, dx), (1, dy), (2, dz)):
                    c = q[axis] + d
                    gap = 0.0 if d == 0 else (f[axis] - d - 1.0 if d < 0 else (1.0 - f[axis]) + d - 1.0)
                    if c < 0 or c >= res or gap > halo:
                        inside = False
                        break
                    flat = flat * res + c
                if not inside:
                    continue
                part = lookup[flat]
                if part < 0 or part == own:
                    continue
                seen = False
                for j in range(count):
                    seen = seen or found[j] == part
                if not seen:
                    found[count] = part
                    count += 1
    return count


@numba.njit(cache=True)
def halo_pairs(positions, lo, scale, res, lookup, own, halo):  # pragma: no cover - compiled
    """(point index, partition) of every halo membership (module docstring), halo in cell widths."""
    reach = max(1, int(math.ceil(halo)))
    found = np.empty((2 * reach + 1) ** 3, np.int32)
    total = 0
    for i in range(len(positions)):
        total += _halo_of(positions[i], lo, scale, res, lookup, own[i], halo, reach, found)
    points = np.empty(total, np.int64)
    parts = np.empty(total, np.int32)
    out = 0
    for i in range(len(positions)):
        count = _halo_of(positions[i], lo, scale, res, lookup, own[i], halo, reach, found)
        for j in range(count):
            points[out] = i
            parts[out] = found[j]
            out += 1
    return points, parts


@numba.njit(cache=True)
def group_by(keys, groups):  # pragma: no cover - compiled
    """Stable counting sort of keys in [0, groups): (order, starts), key g's items being
    order[starts[g]:starts[g + 1]]."""
    starts = np.zeros(groups + 1, np.int64)
    for key in keys:
        starts[key + 1] += 1
    for g in range(groups):
        starts[g + 1] += starts[g]
    cursor = starts[:-1].copy()
    order = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        order[cursor[keys[i]]] = i
        cursor[keys[i]] += 1
    return order, starts
