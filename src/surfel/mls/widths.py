"""The sampling that sizes the adaptive MLS kernels: each sample's spacing s_i.

The kernel width of surface.py is h_i = h_scale * s_i, with

    s_i = max(m_i, GAP_FRACTION * g_i)

  m_i  the local spacing: the mean distance to the SPACING_K = 8 nearest neighbours, then the
       median of that over the sample and those neighbours, so that an isolated outlier takes
       the spacing of the surface near it (the k-nearest neighbourhood sizes the kernel as in
       Pauly, Gross & Kobbelt, "Efficient simplification of point-sampled surfaces", 2002, and
       the per-sample widths h_i = t r_i of Guennebaud & Gross, "Algebraic point set
       surfaces", 2007);
  g_i  the tangent gap: the smallest radius within which every 90-degree window of the
       sample's tangent plane (around GAP_DIRECTIONS = 16 directions) holds a neighbour, counting
       only the windows where one of its GAP_NEIGHBOURS nearest neighbours lies at all, and only
       neighbours on its side of the surface (n_i . n_j > 0). Where two opposite windows hold
       some of the GAP_NEIGHBOURS and two others none (they lie along one row through the
       sample), g_i is at least the gap among its WIDE_NEIGHBOURS nearest whose normals and
       offsets lie within acos(NEXT_ROW_FACING) of its normal and tangent plane, if at most
       NEXT_ROW times the farthest of the GAP_NEIGHBOURS (the next row of the sheet, not
       another part).

Why the gap. The mean distance measures the sampling where it is densest. A coarse thin part
modelled as rings of vertices far apart (a cow's tail: 12 vertices 0.05 apart round each ring,
rings 0.5 apart) has m_i of the ring, 0.12; the surface midway between two rings lies 0.25
from every sample, outside every sample's domain (2 m_i = 0.24, surface.py), where every
kernel's weight has fallen to exp(-(0.25 / 0.13)^2) = 0.03: the MLS surface breaks up between
the rings. The flat triangles of a coarse CAD part, whose interiors only their corners reach,
are the same case. A gap g puts its midpoint g / 2 from the samples around it; with s_i >=
GAP_FRACTION g_i the domain 2 s_i >= g_i holds the midpoint, and the samples on both sides weigh
there half their peak (exp(-(0.5 / 0.6)^2), h_scale x GAP_FRACTION = 1.1 x 0.55 = 0.6: at 0.5
x 1.1 they weighed 0.44, and the GPU caster's fixed projection steps swung between two depths
at such midpoints). Where the sampling is even, g_i is 1.1 to 1.35 m_i (medians over meshes of
2.9k to 62k vertices), so the gap term stays below m_i: it widens 0.2 to 12% of the samples of
the figures measured (a coarse cow's), 27% of a coarse CAD part's (a rocker arm's).

Rows farther apart than GAP_NEIGHBOURS / 2 points along them (a CAD tessellation's long thin
triangles, 20 to one) hide the next row from the nearest neighbours: every window holding one
lies along the row, and the sheet fell apart into its rows (a sheet of rows 0.1 apart, points
0.005 along them: none of its interior covered at 256 x 256, all of it with the wider search).
A wire, searched wider, stays one row and keeps its local spacing.

A window without any neighbour on the sample's side is no gap: the sheet ends there (a rim,
a border, a crease: the edge tests of edges.py decide where), and widening
the kernel there would only round the edge off. Neighbours with n_i . n_j <= 0 are the other
side of a thin part and do not close a gap of this side. Windows rather than the four
quadrants of the tangent frame keep g_i (nearly) independent of how the frame is turned.

The area a sample stands for (the half-disc test's weight, edges.py) is s_i squared: where the
gap widens the kernel, the sample stands for the strip out to the next row as well.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial import cKDTree

from .polynomial import tangent_frame

SPACING_K = 8        # local spacing: mean distance to the 8 nearest neighbours, median-smoothed
GAP_NEIGHBOURS = 24  # neighbours searched for the tangent gap: past a ring of 12 to the next
GAP_FRACTION = 0.55  # s_i >= this x the gap: the domain (2 s_i) holds a gap's midpoint
GAP_DIRECTIONS = 16  # tangent directions whose 90-degree windows the gap must close
WIDE_NEIGHBOURS = 64  # neighbours searched where the GAP_NEIGHBOURS nearest lie along one row
NEXT_ROW = 2.0        # ... for a gap across at most this x the farthest of those
NEXT_ROW_FACING = 0.9  # ... to neighbours whose normals and offsets lie within 25 degrees of
                       # the point's normal and tangent plane: the next row of the same sheet
QUERY_CHUNK = 65536  # points per neighbour query: bounds the (chunk, GAP_NEIGHBOURS) arrays


@numba.njit(parallel=True, cache=True)
def tangent_gaps(points, normals, dist, idx, rows, min_facing, max_rise2):
    """(g, one_row): g_i of the points rows[r] for each row r of the (len(rows), k + 1)
    neighbour query (dist, idx), nearest first, the point itself in column 0, counting the
    neighbours whose normals face the point's by more than min_facing (n_i . n_j) and whose
    offsets rise off its tangent plane by at most max_rise2 (sin² of the angle), 0 where none
    does; one_row[r] where two opposite windows hold some and two others none (the neighbours
    lie along one line through the point: a row of a sampling whose next row lies farther, or
    a wire)."""
    count, columns = idx.shape
    out = np.zeros(count)
    one_row = np.zeros(count, np.bool_)
    for r in numba.prange(count):
        i = rows[r]
        n = normals[i]
        if n[0] * n[0] + n[1] * n[1] + n[2] * n[2] < 0.25:
            continue  # no normal: no tangent plane
        e1 = np.empty(3)
        e2 = np.empty(3)
        tangent_frame(n, e1, e2)
        nearest = np.full(GAP_DIRECTIONS, -1.0)  # per direction; -1: no neighbour yet
        for c in range(1, columns):
            j = idx[r, c]
            if n[0] * normals[j, 0] + n[1] * normals[j, 1] + n[2] * normals[j, 2] <= min_facing:
                continue
            dx, dy, dz = points[j, 0] - points[i, 0], points[j, 1] - points[i, 1], points[j, 2] - points[i, 2]
            rise = dx * n[0] + dy * n[1] + dz * n[2]
            if rise * rise > max_rise2 * (dx * dx + dy * dy + dz * dz):
                continue
            angle = math.atan2(dx * e2[0] + dy * e2[1] + dz * e2[2], dx * e1[0] + dy * e1[1] + dz * e1[2])
            if angle < 0.0:
                angle += 2.0 * math.pi  # [0, 2 pi), as the directions
            for q in range(GAP_DIRECTIONS):
                off = abs(angle - q * (2.0 * math.pi / GAP_DIRECTIONS))
                off = min(off, 2.0 * math.pi - off)  # the angle between them, [0, pi]
                if off <= 0.25 * math.pi and nearest[q] < 0.0:
                    nearest[q] = dist[r, c]  # neighbours come nearest first
        out[r] = max(0.0, nearest.max())
        # a row: neighbours both ways along it, none either way across it (not a tip, a corner)
        along = across = False
        for q in range(GAP_DIRECTIONS // 2):
            along |= nearest[q] >= 0.0 and nearest[q + GAP_DIRECTIONS // 2] >= 0.0
            across |= nearest[q] < 0.0 and nearest[q + GAP_DIRECTIONS // 2] < 0.0
        one_row[r] = along and across
    return out, one_row


def sample_spacing(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s, m): the spacing s_i that sizes each kernel and the local spacing m_i (module
    docstring), for points (N, 3) and their unit oriented normals (zero rows: none)."""
    n = len(points)
    k = min(SPACING_K, n - 1)
    if k < 1:
        return np.ones(n), np.ones(n)
    columns = min(GAP_NEIGHBOURS, n - 1) + 1
    tree = cKDTree(points)
    mean = np.empty(n)
    near = np.empty((n, k + 1), np.int64)
    gap = np.empty(n)
    one_row = np.zeros(n, np.bool_)
    farthest = np.empty(n)
    for start in range(0, n, QUERY_CHUNK):
        dist, idx = tree.query(points[start:start + QUERY_CHUNK], columns, workers=-1)
        rows = np.arange(start, start + len(idx))
        mean[rows] = dist[:, 1:k + 1].mean(axis=1)
        near[rows] = idx[:, :k + 1]
        farthest[rows] = dist[:, -1]
        gap[rows], one_row[rows] = tangent_gaps(points, normals, dist, idx, rows, 0.0, 1.0)
    # rows of a sampling far apart (a CAD tessellation's long thin triangles): the next row lies
    # past the nearest, whose windows then hold no gap across; a wire stays one row
    wide = min(WIDE_NEIGHBOURS, n - 1) + 1
    narrow = np.flatnonzero(one_row) if wide > columns else np.empty(0, np.int64)
    for start in range(0, len(narrow), QUERY_CHUNK // 2):  # about the memory of the chunks above
        rows = narrow[start:start + QUERY_CHUNK // 2]
        dist, idx = tree.query(points[rows], wide, workers=-1)
        found, still = tangent_gaps(points, normals, dist, idx, rows, NEXT_ROW_FACING,
                                    1.0 - NEXT_ROW_FACING ** 2)
        # the next row just past the nearest, not another part of the model
        across = ~still & (found <= NEXT_ROW * farthest[rows])
        gap[rows[across]] = np.maximum(gap[rows[across]], found[across])
    local = np.median(mean[near], axis=1)
    positive = local[local > 0]
    floor = 1e-6 * float(np.median(positive)) if positive.size else 1.0
    local = np.maximum(local, floor)  # duplicates: no zero-width kernel
    return np.maximum(local, GAP_FRACTION * gap), local
