"""Pinholes: single samples (supersampled, holes of up to a pixel) through which a splatted
surface shows what lies behind it.

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
front. In a categorical colour mode, whose colours never mix, it takes the values of the
first of them that shows the category most of them show. Two rounds: a pinhole of two
samples has its second sample's neighbours complete after the first round. The second round
tests only the samples within one of those filled in the first, as no other sample's
neighbourhood changed (8.5 to 6.2 ms for the two rounds of a 1024 x 1024 bunny, 1M splats;
4.7 ms with the positions gathered per row and the values written in compiled code).

A supersampled render's pixel is s x s samples, and a hole of a few samples, which no
sample's 8 neighbours surround, still shows as a speck after the box filter (a raw range scan
of rocker-arm with `phong`'s 2 x 2 samples: dark dots over its flat faces). So the rule runs
two more rounds with the neighbours s samples away, a pixel: a hole of up to s x s samples is
filled from the samples a pixel around it, and a groove or outline is left alone as at one
sample (six raw scans, `phong`, two views each: 111 more samples in the rocker-arm's view,
PSNR within -0.01 and +0.28 dB of before).

RenderResult.from_samples applies this to the samples of the splatting methods, on every
backend, before eye-dome lighting and the box filter; the CPU splatting path, which
composites one-sample renders in its kernels, applies it to their output. The exported page
runs the same rule in web/pinholes.glsl.
"""

from __future__ import annotations

import numba
import numpy as np

from .threads import IMAGE_GRAIN, over_rows

MIN_FRONT = 7  # of the 8 neighbours: the eighth may be the other half of a two-sample pinhole
ROUNDS = 2
RELATIVE_TOLERANCE = 1e-5
PINHOLE_GRAIN = 4096  # the fewest pinholes of a thread's piece (threads.IMAGE_GRAIN: why)

_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


@numba.njit(cache=True, inline="always")
def _depth(depth, coverage, y, x):  # pragma: no cover - compiled
    """The sample's depth, inf where nothing covers it (what depth holds there varies by backend)."""
    return depth[y, x] if coverage[y, x] > 0 else np.float32(np.inf)


@numba.njit(cache=True, inline="always")
def _is_pinhole(depth, coverage, y, x, step):  # pragma: no cover - compiled
    """The rule of the module docstring, with the neighbours `step` samples away."""
    h, w = depth.shape
    if y < step or x < step or y >= h - step or x >= w - step:
        return False
    z = _depth(depth, coverage, y, x)
    behind, near, far = 0, np.inf, -np.inf
    for dy, dx in _NEIGHBOURS:
        q = _depth(depth, coverage, y + step * dy, x + step * dx)
        if q < z:
            near, far = min(near, q), max(far, q)
        else:
            behind += 1
            if behind > 8 - MIN_FRONT:  # most samples fail here, after a few neighbours
                return False
    return z - far > (far - near) + RELATIVE_TOLERANCE * abs(far)


@numba.njit(cache=True, inline="always")
def _front_count(depth, coverage, y, x, s):  # pragma: no cover - compiled
    """How many of the 8 neighbours s samples away of the inner sample (y, x) lie in front of
    it: the count `_is_pinhole` tests first, without its branches, so that a row's loop
    compiles to SIMD."""
    z = _depth(depth, coverage, y, x)
    return ((_depth(depth, coverage, y - s, x - s) < z) + (_depth(depth, coverage, y - s, x) < z)
            + (_depth(depth, coverage, y - s, x + s) < z) + (_depth(depth, coverage, y, x - s) < z)
            + (_depth(depth, coverage, y, x + s) < z) + (_depth(depth, coverage, y + s, x - s) < z)
            + (_depth(depth, coverage, y + s, x) < z) + (_depth(depth, coverage, y + s, x + s) < z))


def _find(depth, coverage, found, step):
    """(ys, xs): the pinholes' positions, row by row, with the neighbours `step` samples away;
    found[y, x] marks them. Each row's are counted as they are found and gathered from the
    rows that have any (np.nonzero's scan of every sample took as long as finding them)."""
    h = depth.shape[0]
    counts = np.empty(h, np.int64)
    over_rows(_find_rows, h, depth, coverage, found, counts, step, grain=IMAGE_GRAIN)
    starts = np.zeros(h + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    ys, xs = np.empty(starts[-1], np.int64), np.empty(starts[-1], np.int64)
    over_rows(_gather_rows, h, found, counts, starts, ys, xs, grain=IMAGE_GRAIN)
    return ys, xs


@numba.njit(cache=True, nogil=True)
def _find_rows(first, stop, depth, coverage, found, counts, step):  # pragma: no cover - compiled
    """Rows first:stop of `_find`, and how many pinholes each holds. A row's samples are
    counted first (`_front_count`, no pinhole within `step` of the image's border), in
    unsigned indices (a negative index's wrap-around would keep the loop scalar); only those
    with MIN_FRONT neighbours in front, a few, take the whole test."""
    h, w = depth.shape
    front = np.zeros(w, np.uint8)
    unsigned_step = np.uint64(step)
    for y in range(first, stop):
        counts[y] = 0
        found[y] = False
        if y < step or y >= h - step:
            continue
        row = np.uint64(y)
        for i in range(w - 2 * step):
            x = np.uint64(i) + unsigned_step
            front[x] = _front_count(depth, coverage, row, x, unsigned_step)
        for x in range(step, w - step):
            if front[x] >= MIN_FRONT and _is_pinhole(depth, coverage, y, x, step):
                found[y, x] = True
                counts[y] += 1


@numba.njit(cache=True, nogil=True)
def _gather_rows(first, stop, found, counts, starts, ys, xs):  # pragma: no cover - compiled
    """The positions of rows first:stop's pinholes, at their rows' offsets `starts`."""
    for y in range(first, stop):
        if counts[y] == 0:
            continue
        k = starts[y]
        for x in range(found.shape[1]):
            if found[y, x]:
                ys[k], xs[k] = y, x
                k += 1


def _find_near(filled_ys, filled_xs, depth, coverage, found, step):
    """(ys, xs): the pinholes among the samples `step` or 0 samples along each axis from those
    just filled, the only ones whose neighbourhoods changed (every other sample was no pinhole
    before and is none now); found (all False on entry) marks them, so that none is counted
    twice. A pinhole lies at least `step` samples inside the image's border, so the samples
    around one are all inside it."""
    hole = np.empty((len(filled_ys), 9), np.bool_)
    over_rows(_near_rows, len(filled_ys), filled_ys, filled_xs, depth, coverage, hole, step, grain=PINHOLE_GRAIN)
    return _mark_once(filled_ys, filled_xs, hole, found, step)


@numba.njit(cache=True, nogil=True)
def _near_rows(first, stop, filled_ys, filled_xs, depth, coverage, hole, step):  # pragma: no cover - compiled
    """hole[k, c]: whether the sample c (of the 3 x 3, `step` apart, around filled sample k) is
    a pinhole, for k in first:stop. Counted first, as in `_find_rows` (the 10k pinholes of a
    1M-splat bunny at 1024 x 1024: 1.9 -> 1.4 ms on one thread)."""
    h, w = depth.shape
    for k in range(first, stop):
        for c in range(9):
            y, x = filled_ys[k] + step * (c // 3 - 1), filled_xs[k] + step * (c % 3 - 1)
            inner = step <= y < h - step and step <= x < w - step
            front = inner and _front_count(depth, coverage, np.uint64(y), np.uint64(x), np.uint64(step)) >= MIN_FRONT
            hole[k, c] = front and _is_pinhole(depth, coverage, y, x, step)


@numba.njit(cache=True)
def _mark_once(filled_ys, filled_xs, hole, found, step):  # pragma: no cover - compiled
    """The samples `hole` marks, each once (in found), as (ys, xs)."""
    most = hole.sum()
    ys, xs = np.empty(most, np.int64), np.empty(most, np.int64)
    count = 0
    for k in range(len(filled_ys)):
        for c in range(9):
            y, x = filled_ys[k] + step * (c // 3 - 1), filled_xs[k] + step * (c % 3 - 1)
            if hole[k, c] and not found[y, x]:
                found[y, x] = True
                ys[count], xs[count] = y, x
                count += 1
    return ys[:count], xs[:count]


def _fill(ys, xs, shaded, coverage, depth, normals, indices, categorical, step):
    """Each pinhole (ys, xs) filled in place from its front neighbours `step` samples away. All
    are computed before any is written, so that the order of the pinholes does not matter."""
    values = np.zeros((len(ys), 8), np.float32)  # colour, coverage, depth, normal
    labels = np.empty(len(ys), np.int32)
    over_rows(_fill_values, len(ys), ys, xs, shaded, coverage, depth, normals, indices, categorical, step, values,
              labels, grain=PINHOLE_GRAIN)
    _write_values(ys, xs, values, labels, shaded, coverage, depth, normals, indices, categorical)


@numba.njit(cache=True, nogil=True)
def _fill_values(first, stop, ys, xs, shaded, coverage, depth, normals, indices, categorical, step, values,
                 labels):  # pragma: no cover - compiled
    """The values (colour, coverage, depth, normal) and labels of pinholes first:stop."""
    for k in range(first, stop):
        y, x = ys[k], xs[k]
        z = _depth(depth, coverage, y, x)
        source = -1  # in a categorical mode: the first front neighbour showing the commonest category
        if categorical:
            best_votes = 0
            for i in range(8):
                qy, qx = y + step * _NEIGHBOURS[i][0], x + step * _NEIGHBOURS[i][1]
                if _depth(depth, coverage, qy, qx) >= z:
                    continue
                votes = 0
                for dy, dx in _NEIGHBOURS:
                    ry, rx = y + step * dy, x + step * dx
                    if _depth(depth, coverage, ry, rx) < z and indices[ry, rx] == indices[qy, qx]:
                        votes += 1
                if votes > best_votes:
                    best_votes, source = votes, i
            labels[k] = indices[y + step * _NEIGHBOURS[source][0], x + step * _NEIGHBOURS[source][1]]
        count = 0
        for i in range(8):
            qy, qx = y + step * _NEIGHBOURS[i][0], x + step * _NEIGHBOURS[i][1]
            if (categorical and i != source) or _depth(depth, coverage, qy, qx) >= z:
                continue
            count += 1
            for c in range(3):
                values[k, c] += shaded[qy, qx, c]
                values[k, 5 + c] += normals[qy, qx, c]
            values[k, 3] += coverage[qy, qx]
            values[k, 4] += depth[qy, qx]
        for c in range(5):
            values[k, c] /= count
        length = np.sqrt(values[k, 5] ** 2 + values[k, 6] ** 2 + values[k, 7] ** 2)
        for c in range(5, 8):
            values[k, c] = values[k, c] / length if length > 0 else values[k, c]


@numba.njit(cache=True)
def _write_values(ys, xs, values, labels, shaded, coverage, depth, normals, indices,
                  categorical):  # pragma: no cover - compiled
    """Each pinhole's values and label written to its sample (numpy's fancy-index writes, one
    per buffer, took twice as long as computing them)."""
    for k in range(len(ys)):
        y, x = ys[k], xs[k]
        for c in range(3):
            shaded[y, x, c] = values[k, c]
            normals[y, x, c] = values[k, 5 + c]
        coverage[y, x], depth[y, x] = values[k, 3], values[k, 4]
        if categorical:
            indices[y, x] = labels[k]


def fill_pinholes(shaded: np.ndarray, coverage: np.ndarray, depth: np.ndarray, normals: np.ndarray,
                  indices: np.ndarray | None = None, pixel: int = 1):
    """(shaded, coverage, depth, normals, indices, filled) with the pinholes of the module
    docstring filled, in place where the buffers are already float32, of any strides (int32 for
    `indices`): shaded (H, W, 3), coverage (H, W), depth (H, W) (any value where coverage is
    0), normals (H, W, 3), indices (H, W) or None; `filled` counts the samples filled. With
    `pixel` > 1, the samples a pixel side of a supersampled render, then also the holes of up to
    a pixel."""
    shaded, coverage = np.asarray(shaded, np.float32), np.asarray(coverage, np.float32)
    depth, normals = np.asarray(depth, np.float32), np.asarray(normals, np.float32)
    categorical = indices is not None
    labels = np.ascontiguousarray(indices, np.int32) if categorical else np.zeros((1, 1), np.int32)
    filled = _fill_rounds(shaded, coverage, depth, normals, labels, categorical, 1)
    if pixel > 1:  # a hole of up to a pixel: the samples a pixel around it surround it (module docstring)
        filled += _fill_rounds(shaded, coverage, depth, normals, labels, categorical, pixel)
    return shaded, coverage, depth, normals, labels if categorical else None, filled


def _fill_rounds(shaded, coverage, depth, normals, labels, categorical, step) -> int:
    """The ROUNDS rounds of the module docstring with the neighbours `step` samples away, in
    place; how many samples they filled."""
    found = np.empty(depth.shape, np.bool_)  # every sample's mark written by _find
    ys, xs = _find(depth, coverage, found, step)
    filled = 0
    for round_index in range(ROUNDS):
        if round_index > 0:  # only samples next to those just filled can have become pinholes
            found[ys, xs] = False
            ys, xs = _find_near(ys, xs, depth, coverage, found, step)
        if len(ys) == 0:
            break
        filled += len(ys)
        _fill(ys, xs, shaded, coverage, depth, normals, labels, categorical, step)
    return filled
