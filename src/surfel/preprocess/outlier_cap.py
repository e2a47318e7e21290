"""The outlier cap of the splat radii (`cells.py`): a point whose covering radius exceeds
ISOLATED_FACTOR times the median radius of its neighbours on its own surface is capped there,
so that a stray point, whose Voronoi cell reaches far, does not become a blob:

    cap_p = min(1, ISOLATED_FACTOR median{r_q : q among p's k nearest, n_p . n_q >= cos 45°} / r_p)

the median taken over all k neighbours where none lies on p's surface. Only p's own surface
counts because over all neighbours a sheet's densely sampled rim, its normals turning every
way, capped the splats of the body the sheet lies on (holes along ogre's belt). Unoriented
normals cannot tell a sheet's two sides apart: with them every neighbour counts.
"""

from __future__ import annotations

import numba
import numpy as np

from ..threads import over_rows
from .chunked import map_chunks
from .sharp_features import SHARP_COS

ISOLATED_FACTOR = 2.0  # a radius at most this x the median of its neighbours' radii
CAP_BLOCK = 1024       # the fewest points per thread's piece


def outlier_cap(raw: np.ndarray, index: np.ndarray, normals: np.ndarray, oriented: bool) -> np.ndarray:
    """(N,) cap factors in (0, 1] of the raw radii `raw` (N,), given each point's neighbours
    `index` (N, k) (itself first) and unit `normals` (N, 3), oriented or not."""
    if index.shape[1] == 1:  # no neighbours: nothing to compare with
        return np.ones(len(raw))
    same_cos = SHARP_COS if oriented else -2.0
    return map_chunks(lambda start, stop: _outlier_cap(raw, index[start:stop], start, normals, same_cos), len(raw))


@numba.njit(cache=True, inline="always")
def _median(values, n):  # pragma: no cover - compiled
    """The median of values[:n], n > 0: the mean of the values at the sorted positions
    (n - 1) // 2 and n // 2 (one middle twice if n is odd). A value lies at sorted position t
    when fewer than t + 1 values are below it and more than t are at most it: counts that
    compile to SIMD compares, where sorting a dozen values by insertion mispredicted a branch
    per value."""
    low = 0.0
    high = 0.0
    for a in range(n):
        value = values[a]
        below = 0
        at_most = 0
        for b in range(n):
            below += values[b] < value
            at_most += values[b] <= value
        if below <= (n - 1) // 2 < at_most:
            low = value
        if below <= n // 2 < at_most:
            high = value
    return (low + high) / 2


@numba.njit(cache=True, inline="always")
def _median_at_least(values, n, bound):  # pragma: no cover - compiled
    """Whether the median of values[:n] is at least `bound`: true when no more than (n - 1) // 2
    values lie below it (both middles are then at least it). One pass where `_median` takes n:
    most points are no outliers, and their cap is 1 whatever the median's exact value."""
    below = 0
    for a in range(n):
        below += values[a] < bound
    return below <= (n - 1) // 2


def _outlier_cap(raw, index, start, normals, same_cos):
    """cap_p of each point p = start + i, p's surface being its neighbours with n_p . n_q >= same_cos."""
    m = len(index)
    cap = np.empty(m)
    over_rows(_outlier_cap_rows, m, raw, index, start, normals, same_cos, cap, grain=CAP_BLOCK)
    return cap


@numba.njit(cache=True, nogil=True)
def _outlier_cap_rows(first, stop, raw, index, start, normals, same_cos, cap):  # pragma: no cover - compiled
    """Rows first:stop of `_outlier_cap`."""
    k = index.shape[1]
    values = np.empty(k - 1)  # one buffer per call: an allocation per point costs as much as its work
    for i in range(first, stop):
        p, count = start + i, 0
        for j in range(1, k):
            q = index[i, j]
            facing = normals[q, 0] * normals[p, 0] + normals[q, 1] * normals[p, 1] + normals[q, 2] * normals[p, 2]
            values[count] = raw[q]
            count += facing >= same_cos  # kept when on p's surface, without a branch
        if not count:  # none on p's surface (rare): all of them count
            for j in range(1, k):
                values[j - 1] = raw[index[i, j]]
            count = k - 1
        cap[i] = 1.0 if _median_at_least(values, count, raw[p] / ISOLATED_FACTOR) else \
            min(1.0, ISOLATED_FACTOR * _median(values, count) / raw[p])
