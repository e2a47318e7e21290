"""The k nearest neighbours of the points that the grid search (`grid_knn.py`) leaves unsettled:
outliers far from the rest, whose shells of cells hold too few points, and every point of a
grid with a cell of many coincident points.

Few of them (at most SCAN_ALL_ROWS) each scan every point (`scan_all_nearest`, linear in the
points), offering their k best only those no farther than the k points beside them in the
points' (Morton) order, which bound the k nearest: a k-d tree over a million points takes as
long to build as some hundred such scans, and a partition of an out-of-core build leaves two
or so of its border candidates' wider queries unsettled (its corners), where building the tree
took a tenth of the partition's completion. More of them query a k-d tree (scipy's cKDTree).
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..threads import over_rows

SCAN_ALL_ROWS = 64  # at most this many unsettled points scan all points instead of a k-d tree


def scan_all_nearest(points, k, rows):
    """(len(rows), k) int32: the k nearest of each of the points `rows` (1 <= k <= N; nearest
    first, the point itself first, equal distances in index order), offering every point. The
    insertion is grid_knn's `_insert` written again: a kernel here reads no helper of another
    module, whose change numba's cache would not see (docs/architecture.md)."""
    m = len(rows)
    index = np.empty((m, k), np.int32)
    over_rows(_scan_all_nearest_rows, m, points, k, rows, index, grain=1)  # a row scans every point
    return index


@numba.njit(cache=True, inline="always")
def _distance2(points, p, j):  # pragma: no cover - compiled
    dx = points[j, 0] - points[p, 0]
    dy = points[j, 1] - points[p, 1]
    dz = points[j, 2] - points[p, 2]
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _scan_all_nearest_rows(first, stop, points, k, rows, index):  # pragma: no cover - compiled
    """Rows first:stop of `scan_all_nearest`."""
    n = len(points)
    for r in range(first, stop):
        p = rows[r]
        best_d = np.full(k, np.inf)
        best_i = np.zeros(k, np.int64)
        best_d[0] = -1.0
        best_i[0] = p
        # the k - 1 nearest lie no farther than any k - 1 others: none farther than those is
        # offered (an offer costs up to k moves; 5.3 -> 1.2 ms a row at k = 256, 850k points)
        low = max(min(p - k // 2, n - k), 0)  # k points, p among them (all of them if fewer)
        bound = 0.0
        for j in range(low, min(low + k, n)):
            bound = max(bound, _distance2(points, p, j))
        for j in range(n):
            d = _distance2(points, p, j)
            if j == p or d >= best_d[k - 1] or d > bound:
                continue
            slot = k - 1
            while best_d[slot - 1] > d:  # stops at the point itself, at -1
                best_d[slot] = best_d[slot - 1]
                best_i[slot] = best_i[slot - 1]
                slot -= 1
            best_d[slot] = d
            best_i[slot] = j
        for c in range(k):
            index[r, c] = best_i[c]


def unsettled_nearest(points: np.ndarray, rows: np.ndarray, k: int, workers: int) -> np.ndarray:
    """(len(rows), k): the k nearest of the points `rows` (module docstring), the point itself
    first, as the grid has it (a coincident point may come first); workers: the k-d tree's threads."""
    rows = np.asarray(rows, np.int64)
    if len(rows) <= SCAN_ALL_ROWS:
        return scan_all_nearest(points, k, rows)
    _, found = cKDTree(points).query(points[rows], k=k, workers=workers)
    found = found.reshape(len(rows), k)
    itself = found == rows[:, None]
    has_self = itself.any(axis=1)
    at = np.argmax(itself, axis=1)
    swap = np.flatnonzero(has_self)
    found[swap, at[swap]] = found[swap, 0]
    found[:, 0] = rows
    return found
