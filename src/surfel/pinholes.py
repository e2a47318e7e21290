"""Pinholes: single samples through which a splatted surface shows what lies behind it.

A cloud's splats are sized to cover their cells in the tangent plane (preprocess.cells), so
a surface's splats overlap. On a raw range scan, though, neighbouring splats are tilted
against one another by the normals' noise, and where the surface turns oblique to the view
their thin projected ellipses can miss a sample between them. That sample then shows the
far side of the object, lit from behind, or the background: dark specks along a scan's
outline, ears and folds (issue 17: 170 of them in a 1024 x 1024 render of a bunny scan).

A sample p is a pinhole when at least 7 of its 8 neighbours lie in front of it by more
than the depth spread of those in front:

    F = {q in N8(p) : z_q < z_p},   |F| >= 7,
    z_p - max_F z  >  (max_F z - min_F z) + 1e-5 max_F z,

with z the eye depth (inf where nothing is covered). A smooth surface through the
neighbours puts z_p within their range, so a slope never qualifies; a crease seen along its
valley has its two neighbours along the valley no nearer than p, and an outline has
uncovered neighbours, so neither does. The tolerance keeps float rounding of a flat surface
out. A pinhole takes the mean colour, coverage, depth and (unit) normal of its neighbours in
front; in a categorical colour mode, whose colours never mix, the values of the first of them
that shows the category most of them show. Two rounds: a
pinhole of two samples has its second sample's neighbours complete after the first round.

RenderResult.from_samples applies this to the samples of the splatting methods, on every
backend, before eye-dome lighting and the box filter (the CPU splatting kernels, which
composite one-sample renders themselves, apply it to their output).
"""

from __future__ import annotations

import numba
import numpy as np

MIN_FRONT = 7  # of the 8 neighbours: the eighth may be the other half of a two-sample pinhole
ROUNDS = 2
RELATIVE_TOLERANCE = 1e-5

_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


@numba.njit(cache=True, inline="always")
def _is_pinhole(depth, y, x):  # pragma: no cover - compiled
    h, w = depth.shape
    if y == 0 or x == 0 or y == h - 1 or x == w - 1:
        return False
    z = depth[y, x]
    behind, near, far = 0, np.inf, -np.inf
    for dy, dx in _NEIGHBOURS:
        q = depth[y + dy, x + dx]
        if q < z:
            near, far = min(near, q), max(far, q)
        else:
            behind += 1
            if behind > 8 - MIN_FRONT:  # most samples fail here, after a few neighbours
                return False
    return z - far > (far - near) + RELATIVE_TOLERANCE * abs(far)


@numba.njit(parallel=True, cache=True)
def _find(depth, found):  # pragma: no cover - compiled
    """found[y, x] = whether sample (y, x) is a pinhole; how many are."""
    h, w = depth.shape
    count = 0
    for y in numba.prange(h):
        for x in range(w):
            hole = _is_pinhole(depth, y, x)
            found[y, x] = hole
            if hole:
                count += 1
    return count


@numba.njit(cache=True)
def _fill(found, shaded, coverage, depth, normals, indices, categorical):  # pragma: no cover - compiled
    """Each pinhole of `found` filled in place from its front neighbours. All are computed
    before any is written, so that the order of the pinholes does not matter."""
    ys, xs = np.nonzero(found)
    values = np.empty((len(ys), 8), np.float32)  # colour, coverage, depth, normal
    labels = np.empty(len(ys), np.int32)
    for k in range(len(ys)):
        y, x = ys[k], xs[k]
        z = depth[y, x]
        row = values[k]
        if categorical:  # a copy of the first front neighbour showing the most common category
            best_votes = 0
            for dy, dx in _NEIGHBOURS:
                qy, qx = y + dy, x + dx
                if depth[qy, qx] >= z:
                    continue
                votes = 0
                for ey, ex in _NEIGHBOURS:
                    if depth[y + ey, x + ex] < z and indices[y + ey, x + ex] == indices[qy, qx]:
                        votes += 1
                if votes > best_votes:
                    best_votes, labels[k] = votes, indices[qy, qx]
                    row[:3], row[3], row[4], row[5:] = shaded[qy, qx], coverage[qy, qx], depth[qy, qx], normals[qy, qx]
            continue
        row[:] = 0
        count = 0
        for dy, dx in _NEIGHBOURS:
            qy, qx = y + dy, x + dx
            if depth[qy, qx] < z:
                count += 1
                row[:3] += shaded[qy, qx]
                row[3] += coverage[qy, qx]
                row[4] += depth[qy, qx]
                row[5:] += normals[qy, qx]
        row[:5] /= count
        length = np.sqrt(np.sum(row[5:] * row[5:]))
        if length > 0:
            row[5:] /= length
    for k in range(len(ys)):
        y, x = ys[k], xs[k]
        row = values[k]
        shaded[y, x], coverage[y, x], depth[y, x], normals[y, x] = row[:3], row[3], row[4], row[5:]
        if categorical:
            indices[y, x] = labels[k]


def fill_pinholes(shaded: np.ndarray, coverage: np.ndarray, depth: np.ndarray, normals: np.ndarray,
                  indices: np.ndarray | None = None):
    """(shaded, coverage, depth, normals, indices, filled) with the pinholes of the module
    docstring filled, in place where the buffers are already contiguous float32 (int32 for
    `indices`): shaded (H, W, 3), coverage (H, W), depth (H, W), normals (H, W, 3), indices
    (H, W) or None. Depth comes back inf where nothing is covered; `filled` counts the
    samples filled."""
    depth = np.ascontiguousarray(np.where(coverage > 0, depth, np.inf), np.float32)
    shaded, coverage = np.ascontiguousarray(shaded, np.float32), np.ascontiguousarray(coverage, np.float32)
    normals = np.ascontiguousarray(normals, np.float32)
    categorical = indices is not None
    labels = np.ascontiguousarray(indices, np.int32) if categorical else np.zeros((1, 1), np.int32)
    found = np.empty(depth.shape, np.bool_)
    filled = 0
    for _ in range(ROUNDS):
        count = _find(depth, found)
        if count == 0:
            break
        filled += count
        _fill(found, shaded, coverage, depth, normals, labels, categorical)
    return shaded, coverage, depth, normals, labels if categorical else None, filled
