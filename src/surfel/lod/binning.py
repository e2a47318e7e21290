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

    d < 0:  f + (-d - 1) <= h,     d = 0: always,     d > 0:  (1 - f) + (d - 1) <= h,

so a point farther than h from every face of its cell is in no halo.

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


@numba.njit(inline="always")
def _halo_of(position, lo, scale, res, lookup, own, halo, reach, found):  # pragma: no cover - compiled
    """The partitions (other than `own`) whose cells lie within `halo` cell widths of the
    position, into found[:count]; returns count."""
    x = (position[0] - lo[0]) * scale
    y = (position[1] - lo[1]) * scale
    z = (position[2] - lo[2]) * scale
    qx = min(max(np.int64(math.floor(x)), 0), res - 1)
    qy = min(max(np.int64(math.floor(y)), 0), res - 1)
    qz = min(max(np.int64(math.floor(z)), 0), res - 1)
    fx = min(max(x - qx, 0.0), 1.0)
    fy = min(max(y - qy, 0.0), 1.0)
    fz = min(max(z - qz, 0.0), 1.0)
    if min(fx, 1.0 - fx, fy, 1.0 - fy, fz, 1.0 - fz) > halo:
        return 0  # the cube [p - h, p + h]^3 stays inside p's own cell
    count = 0
    for dx in range(-reach, reach + 1):
        cx = qx + dx
        gx = 0.0 if dx == 0 else (fx - dx - 1.0 if dx < 0 else dx - fx)
        if cx < 0 or cx >= res or gx > halo:
            continue
        for dy in range(-reach, reach + 1):
            cy = qy + dy
            gy = 0.0 if dy == 0 else (fy - dy - 1.0 if dy < 0 else dy - fy)
            if cy < 0 or cy >= res or gy > halo:
                continue
            for dz in range(-reach, reach + 1):
                cz = qz + dz
                gz = 0.0 if dz == 0 else (fz - dz - 1.0 if dz < 0 else dz - fz)
                if cz < 0 or cz >= res or gz > halo or (dx == 0 and dy == 0 and dz == 0):
                    continue
                part = lookup[(cx * res + cy) * res + cz]
                if part < 0 or part == own:
                    continue
                seen = False
                for j in range(count):
                    seen = seen or found[j] == part
                if not seen:
                    found[count] = part
                    count += 1
    return count


@numba.njit(parallel=True, cache=True)
def halo_pairs(positions, lo, scale, res, lookup, own, halo):  # pragma: no cover - compiled
    """(point index, partition) of every halo membership (module docstring), halo in cell widths."""
    reach = max(1, int(math.ceil(halo)))
    n = len(positions)
    block = 4096
    blocks = (n + block - 1) // block
    per_block = np.zeros(blocks + 1, np.int64)
    for b in numba.prange(blocks):
        found = np.empty((2 * reach + 1) ** 3, np.int32)
        for i in range(b * block, min(n, (b + 1) * block)):
            per_block[b + 1] += _halo_of(positions[i], lo, scale, res, lookup, own[i], halo, reach, found)
    for b in range(blocks):
        per_block[b + 1] += per_block[b]
    points = np.empty(per_block[blocks], np.int64)
    parts = np.empty(per_block[blocks], np.int32)
    for b in numba.prange(blocks):
        found = np.empty((2 * reach + 1) ** 3, np.int32)
        out = per_block[b]
        for i in range(b * block, min(n, (b + 1) * block)):
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
