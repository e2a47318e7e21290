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
       neighbours on its side of the surface (n_i . n_j > 0).

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

A window without any neighbour on the sample's side is no gap: the sheet ends there (a rim,
a border, a crease: the edge tests of edges.py decide where), and widening
the kernel there would only round the edge off. Neighbours with n_i . n_j <= 0 are the other
side of a thin part and do not close a gap of this side. Windows rather than the four
quadrants of the tangent frame keep g_i (nearly) independent of how the frame is turned.

The area a sample stands for (the half-disc test's weight) is m_i squared: the sampling density,
which the gap does not change.
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
QUERY_CHUNK = 65536  # points per neighbour query: bounds the (chunk, GAP_NEIGHBOURS) arrays


@numba.njit(parallel=True, cache=True)
def tangent_gaps(points, normals, dist, idx, start):
    """g_i of points start + r for each row r of the (chunk, k + 1) neighbour query (dist, idx),
    nearest first, the point itself in column 0; 0 where no neighbour lies on its side."""
    rows, columns = idx.shape
    out = np.zeros(rows)
    for r in numba.prange(rows):
        i = start + r
        n = normals[i]
        if n[0] * n[0] + n[1] * n[1] + n[2] * n[2] < 0.25:
            continue  # no normal: no tangent plane
        e1 = np.empty(3)
        e2 = np.empty(3)
        tangent_frame(n, e1, e2)
        nearest = np.full(GAP_DIRECTIONS, -1.0)  # per direction; -1: no neighbour yet
        for c in range(1, columns):
            j = idx[r, c]
            if n[0] * normals[j, 0] + n[1] * normals[j, 1] + n[2] * normals[j, 2] <= 0.0:
                continue
            dx, dy, dz = points[j, 0] - points[i, 0], points[j, 1] - points[i, 1], points[j, 2] - points[i, 2]
            angle = math.atan2(dx * e2[0] + dy * e2[1] + dz * e2[2], dx * e1[0] + dy * e1[1] + dz * e1[2])
            if angle < 0.0:
                angle += 2.0 * math.pi  # [0, 2 pi), as the directions
            for q in range(GAP_DIRECTIONS):
                off = abs(angle - q * (2.0 * math.pi / GAP_DIRECTIONS))
                off = min(off, 2.0 * math.pi - off)  # the angle between them, [0, pi]
                if off <= 0.25 * math.pi and nearest[q] < 0.0:
                    nearest[q] = dist[r, c]  # neighbours come nearest first
        out[r] = max(0.0, nearest.max())
    return out


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
    for start in range(0, n, QUERY_CHUNK):
        dist, idx = tree.query(points[start:start + QUERY_CHUNK], columns, workers=-1)
        mean[start:start + len(idx)] = dist[:, 1:k + 1].mean(axis=1)
        near[start:start + len(idx)] = idx[:, :k + 1]
        gap[start:start + len(idx)] = tangent_gaps(points, normals, dist, idx, start)
    local = np.median(mean[near], axis=1)
    positive = local[local > 0]
    floor = 1e-6 * float(np.median(positive)) if positive.size else 1.0
    local = np.maximum(local, floor)  # duplicates: no zero-width kernel
    return np.maximum(local, GAP_FRACTION * gap), local
