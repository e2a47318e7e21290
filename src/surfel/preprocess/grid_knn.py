"""Exact k nearest neighbours on a uniform grid of Morton-ordered cells, compiled with numba.

The cell technique of Bentley, Stanat & Williams (1977, "The complexity of finding fixed-radius
near neighbors"), with the cells in Morton (Z) order (Morton 1966) so that neighbouring cells,
and the points in them, lie close together in memory.

Cells: with cell width h and lo the minimum corner of the points, point p lies in the cell
q = floor((p - lo) / h) (per axis, 0 <= q < 2^21), keyed by the Morton code of q (its bits
interleaved). The points are sorted by key, so each occupied cell is one run of them; a hash
table of the occupied cells' keys (open addressing) finds a cell's run.

Search: a point p of cell q scans the 3 x 3 x 3 block of cells around q (gathered once per cell
for all its points; the runs of the cells it shares with the block gathered before are taken
from that one, not looked up again) and keeps its k nearest candidates. It computes the
distances to all of them at once (a loop that compiles to SIMD), and offers only the candidates
within a bound: whenever k - 1 others lie within it, the k nearest are among them, offered in
the order they are found, so ties are broken as offering all would break them. The bound is
d + s / 4, else d + s, else none, with d the distance from the point before (in cell order) to
its k-th nearest and s the step between the two points: by the triangle inequality the k nearest
of the point before lie within d + s. On a scanned surface about 24 of 105 candidates are
offered; each insertion into a sorted list costs a mispredicted branch, so a search of 16
nearest took 60-65% of the time that offering every candidate took. Up to RANKED offered
candidates are instead placed by their ranks (how many lie nearer, or as near and before),
counted in a loop that compiles to SIMD and stored without a branch: the whole search of a
1.4M-point scanned surface in 0.88 s instead of 1.03 (`_ranked`).

Every point not scanned lies outside the block, at least

    m = min over axes a of min(p_a - lo_a - (q_a - 1) h, lo_a + (q_a + 2) h - p_a)

away, so the k found are the k nearest when the k-th lies within m. Otherwise the shells of
cells at Chebyshev distance r = 2, 3, ... RINGS are scanned too (m grows by h each), and a
point still unresolved after them (an outlier far from the rest) is searched otherwise
(`unsettled.py`), as is every point when some cell holds more than MAX_CELL points (many
coincident points, which no cell width separates).

Queries of some of the points (`Grid.nearest`, e.g. a wider neighbourhood of a few of them)
reuse the grid: a point scans its own cell, then the shells r = 1, 2, ... QUERY_RINGS around
it, skipping cells farther than the k-th found, until the k-th found lies within the margin
m + (r - 1) h (the k-d tree takes the rest).

Cell width: the mean number of points per occupied cell c(h) is measured at two coarse widths
h0 and h0 / 2; c grows as h^e (e = 2 on a surface, 3 in a volume), so e = log2(c(h0) / c(h0/2))
(clamped to [1, 3]), and h is chosen so that c(h) = k / CELL_SHARE: about the k nearest within
one cell width of a point on a surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ..cloud import corners, stable_order, take_rows
from ..threads import over_rows
from .unsettled import unsettled_nearest

MORTON_BITS = 21       # bits of a cell coordinate per axis (3 x 21 in an int64 key)
CELL_SHARE = 2.0       # points per occupied cell: k / this (measured fastest on scanned surfaces)
COARSE_CELLS = 64      # cells along the longest side of the first occupancy measurement
RINGS = 3              # shells of cells scanned around a point before the k-d tree takes over
RUN_BATCH = 256        # the fewest cells per thread's piece of the search
MAX_CELL = 4096        # more points in one cell (coincident points): the k-d tree for all
HASH_MULTIPLIER = 0x5851F42D4C957F2D  # odd, below 2^63: the hash of a cell key is its product's bits 32+
QUERY_RINGS = 4        # shells of cells a query (Grid.nearest) scans before the k-d tree takes over
QUERY_BATCH = 64       # the fewest points per thread's piece of a query
RANKED = 40            # the most offered candidates placed by rank (their count squared compares)
SURE_SHRINK = 1e-6     # cell widths by which `grid_within` shrinks its reach: far above roundings
# the 3 x 3 x 3 block's cell offsets, nearest first: the nearest fill the k first
BLOCK_OFFSETS = np.array(sorted(((x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)),
                                key=lambda o: abs(o[0]) + abs(o[1]) + abs(o[2])), np.int64)


@numba.njit(cache=True, inline="always")
def _spread(v):  # pragma: no cover - compiled
    """The 21 low bits of v moved to every third bit."""
    v &= 0x1FFFFF
    v = (v | v << 32) & 0x1F00000000FFFF
    v = (v | v << 16) & 0x1F0000FF0000FF
    v = (v | v << 8) & 0x100F00F00F00F00F
    v = (v | v << 4) & 0x10C30C30C30C30C3
    v = (v | v << 2) & 0x1249249249249249
    return v


@numba.njit(cache=True, inline="always")
def _key(qx, qy, qz):  # pragma: no cover - compiled
    return (_spread(qx) << 2) | (_spread(qy) << 1) | _spread(qz)


@numba.njit(cache=True, inline="always")
def _cell(value, lo, inv_h):  # pragma: no cover - compiled
    return min(max(np.int64(math.floor((value - lo) * inv_h)), 0), (1 << MORTON_BITS) - 1)


@numba.njit(cache=True, inline="always")
def _cell_of(points, p, lo, h, inv_h):  # pragma: no cover - compiled
    """Point p's cell (qx, qy, qz) and its offsets (fx, fy, fz) from the cell's lower corner."""
    qx = _cell(points[p, 0], lo[0], inv_h)
    qy = _cell(points[p, 1], lo[1], inv_h)
    qz = _cell(points[p, 2], lo[2], inv_h)
    return qx, qy, qz, (points[p, 0] - lo[0]) - qx * h, (points[p, 1] - lo[1]) - qy * h, (points[p, 2] - lo[2]) - qz * h


@numba.njit(parallel=True, cache=True)
def cell_keys(points, lo, inv_h):  # pragma: no cover - compiled
    """Morton key (int64) of the cell of each point."""
    keys = np.empty(len(points), np.int64)
    for i in numba.prange(len(points)):
        keys[i] = _key(_cell(points[i, 0], lo[0], inv_h), _cell(points[i, 1], lo[1], inv_h),
                       _cell(points[i, 2], lo[2], inv_h))
    return keys


@numba.njit(cache=True)
def _occupied(points, lo, inv_h, res):  # pragma: no cover - compiled
    """Number of occupied cells of a res^3 grid."""
    seen = np.zeros(res * res * res, np.uint8)
    count = 0
    for i in range(len(points)):
        flat = 0
        for axis in range(3):
            flat = flat * res + min(max(np.int64(math.floor((points[i, axis] - lo[axis]) * inv_h)), 0), res - 1)
        count += 1 - seen[flat]
        seen[flat] = 1
    return count


def _runs(keys: np.ndarray) -> np.ndarray:
    """Start of each run of equal sorted keys (and len(keys) last)."""
    return np.concatenate(([0], np.flatnonzero(keys[1:] != keys[:-1]) + 1, [len(keys)])).astype(np.int64)


@numba.njit(cache=True, inline="always")
def _slot(cell_key, mask):  # pragma: no cover - compiled
    """The first slot of a cell key in the hash table (multiplicative hashing; int64 products wrap)."""
    return ((cell_key * HASH_MULTIPLIER) >> 32) & mask


@numba.njit(cache=True)
def cell_table(run_keys):  # pragma: no cover - compiled
    """Open-addressing hash table (linear probing, at most half full) of the occupied cells:
    the run index of each key in its slot, -1 in empty slots."""
    size = 2
    while size < 2 * len(run_keys):
        size *= 2
    slots = np.full(size, -1, np.int64)
    for run in range(len(run_keys)):
        at = _slot(run_keys[run], size - 1)
        while slots[at] >= 0:
            at = (at + 1) & (size - 1)
        slots[at] = run
    return slots


@numba.njit(cache=True, inline="always")
def _find(cell_key, run_keys, slots):  # pragma: no cover - compiled
    """Run index of a cell key, -1 if that cell is empty: one or two probes of the hash table,
    where a binary search of the keys took a dozen and more."""
    mask = len(slots) - 1
    at = _slot(cell_key, mask)
    while True:
        run = slots[at]
        if run < 0 or run_keys[run] == cell_key:
            return run
        at = (at + 1) & mask


@numba.njit(cache=True, inline="always")
def _gap(offset, d, h):  # pragma: no cover - compiled
    """Squared distance along one axis from a point at `offset` in its cell to the cell d away."""
    if d == 0:
        return 0.0
    g = offset - (d + 1) * h if d < 0 else d * h - offset
    return g * g if g > 0.0 else 0.0


@numba.njit(cache=True, inline="always")
def _rank_sort(best_d, best_i, spare_d, spare_i, k):  # pragma: no cover - compiled
    """Sort best_d[1:k] ascending, best_i along, equal distances in their order (the order an
    insertion sort gives): each goes to its rank, the number of distances below it and of
    equal ones before it. The counts compile to SIMD compares, where inserting one at a time
    mispredicted a branch per candidate. spare_d, spare_i (k,): scratch."""
    for a in range(1, k):
        spare_d[a] = best_d[a]
        spare_i[a] = best_i[a]
    for a in range(1, k):
        key = spare_d[a]
        rank = 1
        for b in range(1, k):
            rank += (spare_d[b] < key) | ((spare_d[b] == key) & (b < a))
        best_d[rank] = key
        best_i[rank] = spare_i[a]


@numba.njit(cache=True, inline="always")
def _fill(d, j, best_d, best_i, spare_d, spare_i, count, k):  # pragma: no cover - compiled
    """Keep (d, j) as the k best's entry `count` < k, sorting them once there are k
    (`_rank_sort`); returns the new count."""
    best_d[count] = d
    best_i[count] = j
    count += 1
    if count == k:
        _rank_sort(best_d, best_i, spare_d, spare_i, k)
    return count


@numba.njit(cache=True, inline="always")
def _ranked(near_d, near_c, near, take, best_d, best_i):  # pragma: no cover - compiled
    """The `take` nearest of the offered candidates near_d[:near] (near >= take), sorted, ties in
    their order, into best_d[1:take + 1], best_i along: each goes to 1 + its rank (the number
    nearer, and as near before it), or to the scratch entry take + 1 when its rank is take or
    more (best_d, best_i: room for k + 1)."""
    for c in range(near):
        key = near_d[c]
        rank = 0
        for b in range(near):
            rank += (near_d[b] < key) | ((near_d[b] == key) & (b < c))
        slot = min(rank, take) + 1
        best_d[slot] = key
        best_i[slot] = near_c[c]


@numba.njit(cache=True, inline="always")
def _insert(d, j, best_d, best_i, k):  # pragma: no cover - compiled
    """Insert (d, j), d below the k-th distance, into the sorted k best, after the equal
    distances before it; returns the new k-th distance."""
    slot = k - 1
    while slot > 0 and best_d[slot - 1] > d:
        best_d[slot] = best_d[slot - 1]
        best_i[slot] = best_i[slot - 1]
        slot -= 1
    best_d[slot] = d
    best_i[slot] = j
    return best_d[k - 1]


@numba.njit(cache=True, inline="always")
def _scan(points, i, start, stop, best_d, best_i, spare_d, spare_i, count, k):  # pragma: no cover - compiled
    """Offer points start:stop (but i) to point i's k best, kept as they come until there are
    k (`_fill`), then inserted where nearer than the k-th (`_insert`); returns the new count."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    worst = best_d[k - 1] if count == k else 0.0
    for j in range(start, stop):
        if j == i:
            continue
        dx = points[j, 0] - px
        dy = points[j, 1] - py
        dz = points[j, 2] - pz
        d = dx * dx + dy * dy + dz * dz
        if count < k:
            count = _fill(d, j, best_d, best_i, spare_d, spare_i, count, k)
            if count == k:
                worst = best_d[k - 1]
            continue
        if d >= worst:
            continue
        worst = _insert(d, j, best_d, best_i, k)
    return count


@numba.njit(cache=True)
def _gather_block(points, starts, run_keys, slots, qx, qy, qz, block, runs):  # pragma: no cover - compiled
    """The points of the 3 x 3 x 3 cells around cell (qx, qy, qz), the cell itself first, in
    the order the block offsets give: coordinates into block[0:3], indices into block[3];
    returns their number. runs (2, 31), row 0: the block gathered before, its cell in entries
    27:30 (entry 30 set once there is one) and at 9 (x + 1) + 3 (y + 1) + z + 1 the run (-1:
    none) of its cell at offset (x, y, z); row 1: scratch. The runs of cells it shares with that
    block (18 for an adjacent cell) are taken from there, not probed in the hash table (4 MB at
    a 1.3M-point partition, mostly missing the cache): half the probes, the search 8% faster."""
    top = (1 << MORTON_BITS) - 1
    sx, sy, sz = qx - runs[0, 27], qy - runs[0, 28], qz - runs[0, 29]  # the step from the cell before
    m = 0
    for o in range(27):
        ox, oy, oz = BLOCK_OFFSETS[o, 0], BLOCK_OFFSETS[o, 1], BLOCK_OFFSETS[o, 2]
        cx, cy, cz = qx + ox, qy + oy, qz + oz
        ex, ey, ez = ox + sx, oy + sy, oz + sz  # the cell's offset from the cell before
        if min(cx, cy, cz) < 0 or max(cx, cy, cz) > top:
            run = -1
        elif runs[0, 30] == 1 and max(abs(ex), abs(ey), abs(ez)) <= 1:
            run = runs[0, (ex + 1) * 9 + (ey + 1) * 3 + ez + 1]
        else:
            run = _find(_key(cx, cy, cz), run_keys, slots)
        runs[1, (ox + 1) * 9 + (oy + 1) * 3 + oz + 1] = run
        if run < 0:
            continue
        for j in range(starts[run], starts[run + 1]):
            for a in range(3):
                block[a, m] = points[j, a]
            block[3, m] = j
            m += 1
    for c in range(27):
        runs[0, c] = runs[1, c]
    runs[0, 27], runs[0, 28], runs[0, 29], runs[0, 30] = qx, qy, qz, 1
    return m


@numba.njit(cache=True, inline="always")
def _within(dist, m, bound, near_d, near_c):  # pragma: no cover - compiled
    """The candidates c < m with dist[c] <= bound, in order, into near_d, near_c; their number."""
    near = 0
    for c in range(m):
        near_d[near] = dist[c]
        near_c[near] = c
        near += dist[c] <= bound
    return near


@numba.njit(cache=True)
def _search_run(points, starts, run_keys, slots, run, lo, h, k, index, best_d, best_i, spare_d, spare_i, block,
                runs, dist, near_d, near_c, previous):  # pragma: no cover - compiled
    """Rows of index for the points of one cell (a run of the sorted points): the 3 x 3 x 3
    block around it, gathered once into `block` (`_gather_block`, with `runs`), then shells of
    cells while the k-th found may lie nearer outside (module docstring); -1 in column 0 where
    the shells up to RINGS do not settle it. `previous` (reach, x, y, z), carried from point to point:
    the distance to the k-th nearest of the point before, and that point."""
    inv_h = 1.0 / h
    first = starts[run]
    qx = _cell(points[first, 0], lo[0], inv_h)
    qy = _cell(points[first, 1], lo[1], inv_h)
    qz = _cell(points[first, 2], lo[2], inv_h)
    m = _gather_block(points, starts, run_keys, slots, qx, qy, qz, block, runs)
    wanted = min(k, m) - 1  # neighbours besides the point itself
    xs, ys, zs = block[0], block[1], block[2]
    for i in range(first, starts[run + 1]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for c in range(m):
            ex = xs[c] - px
            ey = ys[c] - py
            ez = zs[c] - pz
            dist[c] = ex * ex + ey * ey + ez * ez
        dist[i - first] = np.nan  # the point itself comes first, by hand; NaN is within no bound
        # offer those within d + s / 4, else d + s, else all: the first bound that holds k - 1
        # of them holds the k nearest (module docstring: d, s from the point before)
        near = 0
        if previous[0] >= 0.0:
            ex = px - previous[1]
            ey = py - previous[2]
            ez = pz - previous[3]
            step = math.sqrt(ex * ex + ey * ey + ez * ez)
            near = _within(dist, m, (previous[0] + 0.25 * step) ** 2, near_d, near_c)
            if near < wanted:
                near = _within(dist, m, (previous[0] + step) ** 2, near_d, near_c)
        if near < wanted:
            near = _within(dist, m, np.inf, near_d, near_c)
        best_d[0] = -1.0
        best_i[0] = i
        count = 1
        worst = 0.0
        if near <= RANKED:
            _ranked(near_d, near_c, near, wanted, best_d, best_i)
            count += wanted
            near = 0  # all placed
        for c in range(near):
            d = near_d[c]
            if count < k:
                count = _fill(d, near_c[c], best_d, best_i, spare_d, spare_i, count, k)
                if count == k:
                    worst = best_d[k - 1]
                continue
            if d >= worst:
                continue
            worst = _insert(d, near_c[c], best_d, best_i, k)
        for c in range(1, count):
            best_i[c] = np.int64(block[3, best_i[c]])
        fx = (px - lo[0]) - qx * h  # the point's offset in its cell
        fy = (py - lo[1]) - qy * h
        fz = (pz - lo[2]) - qz * h
        margin = min(fx + h, 2.0 * h - fx, fy + h, 2.0 * h - fy, fz + h, 2.0 * h - fz)
        ring = 1
        while (count < k or best_d[k - 1] > margin * margin) and ring < RINGS:
            ring += 1
            count = _scan_shell(points, i, qx, qy, qz, ring, fx, fy, fz, h, False, starts, run_keys, slots,
                                best_d, best_i, spare_d, spare_i, count, k)
            margin += h
        previous[0] = math.sqrt(best_d[k - 1]) if count == k else -1.0
        previous[1], previous[2], previous[3] = px, py, pz
        if count < k or best_d[k - 1] > margin * margin:
            index[i, 0] = -1
            continue
        for j in range(k):
            index[i, j] = best_i[j]


def grid_neighbours(points, starts, run_keys, slots, lo, h, k, largest):
    """The k nearest (nearest first, the point itself first) of each of the key-sorted points,
    as int32 indices into them; rows of points the grid could not resolve are -1 (module
    docstring). largest: the most points of one cell."""
    index = np.empty((len(points), k), np.int32)
    over_rows(_neighbour_runs, len(starts) - 1, points, starts, run_keys, slots, lo, h, k, largest, index,
              grain=RUN_BATCH)
    return index


@numba.njit(cache=True, nogil=True)
def _neighbour_runs(first, stop, points, starts, run_keys, slots, lo, h, k, largest,
                    index):  # pragma: no cover - compiled
    """The rows of `grid_neighbours` of the points of runs first:stop."""
    most = 27 * largest  # points a block can hold
    # k + 1: `_ranked`'s scratch entry
    best_d, best_i, spare_d, spare_i = np.empty(k + 1), np.empty(k + 1, np.int64), np.empty(k), np.empty(k, np.int64)
    block = np.empty((4, most), np.float64)
    dist, near_d, near_c = np.empty(most), np.empty(most), np.empty(most, np.int64)
    runs = np.zeros((2, 31), np.int64)  # no block gathered yet
    previous = np.full(4, -1.0)
    for run in range(first, stop):
        _search_run(points, starts, run_keys, slots, run, lo, h, k, index, best_d, best_i, spare_d, spare_i, block,
                    runs, dist, near_d, near_c, previous)


def cell_width(points: np.ndarray, k: int, lo: np.ndarray, hi: np.ndarray) -> float:
    """The cell width h of the module docstring (points (N, 3) float64, N > 0, within the
    corners lo, hi)."""
    extent = float((hi - lo).max())
    if extent == 0.0:
        return 1.0
    mean = []
    for res in (COARSE_CELLS, 2 * COARSE_CELLS):
        mean.append(len(points) / _occupied(points, lo, res / extent, res))
    exponent = min(max(math.log2(mean[0] / mean[1]), 1.0), 3.0)
    h = extent / (2 * COARSE_CELLS) * (k / CELL_SHARE / mean[1]) ** (1.0 / exponent)
    # the grid spans at most 2^MORTON_BITS cells per axis
    return max(h, extent / ((1 << MORTON_BITS) - 2))


@numba.njit(cache=True, inline="always")
def _scan_shell(points, p, qx, qy, qz, ring, fx, fy, fz, h, prune, starts, run_keys, slots, best_d, best_i, spare_d,
                spare_i, count, k):  # pragma: no cover - compiled
    """Scan the occupied cells of the shell `ring` cells around point p's cell (qx, qy, qz)
    into its k best; with `prune`, skip a cell farther than the k-th found (p at offset
    (fx, fy, fz) in its cell of side h). Returns the new count."""
    top = (1 << MORTON_BITS) - 1
    for dx in range(-ring, ring + 1):
        for dy in range(-ring, ring + 1):
            for dz in range(-ring, ring + 1):
                cx, cy, cz = qx + dx, qy + dy, qz + dz
                if max(abs(dx), abs(dy), abs(dz)) != ring or min(cx, cy, cz) < 0 or max(cx, cy, cz) > top:
                    continue
                if prune and count == k and _gap(fx, dx, h) + _gap(fy, dy, h) + _gap(fz, dz, h) >= best_d[k - 1]:
                    continue
                found = _find(_key(cx, cy, cz), run_keys, slots)
                if found >= 0:
                    count = _scan(points, p, starts[found], starts[found + 1], best_d, best_i, spare_d, spare_i,
                                  count, k)
    return count


@numba.njit(cache=True)
def _query_point(points, starts, run_keys, slots, lo, h, k, p, best_d, best_i, spare_d,
                 spare_i):  # pragma: no cover - compiled
    """The k nearest of point p (the point itself first) into best_i, scanning its cell and
    the shells around it (module docstring); False where QUERY_RINGS shells do not settle it."""
    qx, qy, qz, fx, fy, fz = _cell_of(points, p, lo, h, 1.0 / h)
    best_d[0] = -1.0
    best_i[0] = p
    count = 1
    margin = min(fx, h - fx, fy, h - fy, fz, h - fz)
    for ring in range(QUERY_RINGS + 1):
        count = _scan_shell(points, p, qx, qy, qz, ring, fx, fy, fz, h, True, starts, run_keys, slots,
                            best_d, best_i, spare_d, spare_i, count, k)
        if count == k and best_d[k - 1] <= margin * margin:
            return True
        margin += h
    return False


def grid_query(points, starts, run_keys, slots, lo, h, k, rows):
    """The k nearest (nearest first, the point itself first) of each of the key-sorted points
    `rows`, as int32 indices; rows of points the shells could not settle are -1."""
    index = np.empty((len(rows), k), np.int32)
    over_rows(_query_rows, len(rows), points, starts, run_keys, slots, lo, h, k, rows, index, grain=QUERY_BATCH)
    return index


@numba.njit(cache=True, nogil=True)
def _query_rows(first, stop, points, starts, run_keys, slots, lo, h, k, rows, index):  # pragma: no cover - compiled
    """Rows first:stop of `grid_query`."""
    best_d, best_i, spare_d, spare_i = np.empty(k), np.empty(k, np.int64), np.empty(k), np.empty(k, np.int64)
    for r in range(first, stop):
        if _query_point(points, starts, run_keys, slots, lo, h, k, rows[r], best_d, best_i, spare_d, spare_i):
            for j in range(k):
                index[r, j] = best_i[j]
        else:
            index[r, 0] = -1


def grid_within(points, starts, run_keys, slots, lo, h, k, rows):
    """Per point p = rows[r], the points nearer to p than m - SURE_SHRINK h (m: its distance to
    the faces of the 3 x 3 x 3 block of cells around its cell; the margin keeps out what a
    rounding might bring in), p itself included, into index[r, :count[r]] when there are at
    most k of them; count[r] = -1 when there are more. All points that near lie in the block,
    so, at most k of them, each is among p's k nearest, whichever way ties are broken."""
    index = np.empty((len(rows), k), np.int32)
    count = np.empty(len(rows), np.int64)
    over_rows(_within_rows, len(rows), points, starts, run_keys, slots, lo, h, k, rows, index, count)
    return index, count


@numba.njit(cache=True, nogil=True)
def _within_rows(first, stop, points, starts, run_keys, slots, lo, h, k, rows, index,
                 count):  # pragma: no cover - compiled
    """Rows first:stop of `grid_within`."""
    top = (1 << MORTON_BITS) - 1
    inv_h = 1.0 / h
    for r in range(first, stop):
        p = rows[r]
        qx, qy, qz, fx, fy, fz = _cell_of(points, p, lo, h, inv_h)
        reach = min(fx + h, 2.0 * h - fx, fy + h, 2.0 * h - fy, fz + h, 2.0 * h - fz) - SURE_SHRINK * h
        reach2 = reach * reach if reach > 0.0 else -1.0
        c = 0
        for o in range(27):
            dx, dy, dz = BLOCK_OFFSETS[o, 0], BLOCK_OFFSETS[o, 1], BLOCK_OFFSETS[o, 2]
            cx, cy, cz = qx + dx, qy + dy, qz + dz
            if c < 0 or min(cx, cy, cz) < 0 or max(cx, cy, cz) > top or \
                    _gap(fx, dx, h) + _gap(fy, dy, h) + _gap(fz, dz, h) >= reach2:
                continue
            run = _find(_key(cx, cy, cz), run_keys, slots)
            if run < 0:
                continue
            for j in range(starts[run], starts[run + 1]):
                ex = points[j, 0] - points[p, 0]
                ey = points[j, 1] - points[p, 1]
                ez = points[j, 2] - points[p, 2]
                if ex * ex + ey * ey + ez * ez < reach2:
                    if c == k:
                        c = -1
                        break
                    index[r, c] = j
                    c += 1
        count[r] = c


@dataclass(frozen=True, eq=False)
class Grid:
    """The points sorted by cell key (module docstring), with the cell width h, the minimum
    corner lo, and the start and key of each occupied cell's run; `dense` when some cell holds
    more than MAX_CELL points (the k-d tree then answers every query)."""

    points: np.ndarray     # (N, 3) float64, sorted by cell key
    lo: np.ndarray
    h: float
    starts: np.ndarray     # (runs + 1,) int64
    run_keys: np.ndarray   # (runs,) int64
    slots: np.ndarray      # `cell_table` of run_keys
    dense: bool

    def nearest(self, rows: np.ndarray, k: int, workers: int = -1) -> np.ndarray:
        """(len(rows), k) int32: the k nearest of the points `rows` (nearest first, the point
        itself first), 1 <= k <= N; workers: threads of the k-d tree fallback."""
        rows = np.asarray(rows, np.int64)
        if self.dense:
            index = np.empty((len(rows), k), np.int32)
            unresolved = np.arange(len(rows))
        else:
            index = grid_query(self.points, self.starts, self.run_keys, self.slots, self.lo, self.h, k, rows)
            unresolved = np.flatnonzero(index[:, 0] < 0)
        if len(unresolved):
            index[unresolved] = unsettled_nearest(self.points, rows[unresolved], k, workers)
        return index

    def within(self, rows: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(index (len(rows), k) int32, count (len(rows),)): points certainly among the k nearest
        of each of the points `rows`, index[r, :count[r]], count -1 where none are known
        (`grid_within`; a dense grid knows none), 1 <= k <= N."""
        rows = np.asarray(rows, np.int64)
        if self.dense:
            return np.empty((len(rows), k), np.int32), np.full(len(rows), -1, np.int64)
        return grid_within(self.points, self.starts, self.run_keys, self.slots, self.lo, self.h, k, rows)


def sorted_k_nearest(points: np.ndarray, k: int, workers: int = -1) -> tuple[np.ndarray, np.ndarray, Grid]:
    """(order, index, grid): the points' Morton cell order, the k nearest neighbours (int32,
    nearest first, the point itself first) of each point points[order[i]] as indices i into
    that order, and the grid of the sorted points. points: (N, 3) float64, 1 <= k <= N < 2^31;
    workers: threads of the k-d tree fallback."""
    if len(points) >= 2**31:
        raise ValueError(f"{len(points)} points: the neighbour search indexes fewer than 2^31")
    lo, hi = corners(points)
    h = cell_width(points, k, lo, hi)
    keys = cell_keys(points, lo, 1.0 / h)
    order = stable_order(keys)
    keys = keys[order]
    sorted_points = take_rows(points, order)
    starts = _runs(keys)
    run_keys = keys[starts[:-1]]
    largest = int(np.diff(starts).max())
    grid = Grid(sorted_points, lo, h, starts, run_keys, cell_table(run_keys), largest > MAX_CELL)
    if grid.dense:
        unresolved = np.arange(len(points))
        index = np.empty((len(points), k), np.int32)
    else:
        index = grid_neighbours(sorted_points, starts, grid.run_keys, grid.slots, lo, h, k, largest)
        unresolved = np.flatnonzero(index[:, 0] < 0)
    if len(unresolved):
        index[unresolved] = unsettled_nearest(sorted_points, unresolved, k, workers)
    return order, index, grid
