"""Octree point hierarchy of a sequential point tree (Dachsbacher, Vogelgsang & Stamminger 2003).

Survey section 2.2.1: the samples are inserted into an octree; every inner node is a disk
(a surfel) approximating its children, with averaged position and normal and a radius
enclosing the children's disks, and two approximation errors.

Construction is bottom-up over Morton codes: positions are quantised to 21 bits per axis
in the bounding cube, interleaved into 63-bit codes and sorted once. Level by level the
codes are shifted right by 3 bits; runs of equal shifted codes are the children of one
octree cell. A cell with a single child is not a new node (the child passes upwards
unchanged), so every inner node has >= 2 children and there are fewer inner nodes than
points. Each level's new nodes are computed by one numba kernel, parallel over cells.

For a parent with children i (centre c_i, unit normal n_i, disk radius r_i, area weight
w_i, and a slab [lo_i, hi_i] along n_i that holds all of the child's leaf disks):

    c   = sum w_i c_i / sum w_i                       (area-weighted mean position)
    n   = normalise(sum w_i s_i n_i)                  (s_i = +-1 aligns n_i with the
                                                       heaviest child: splats are two-sided)
    d_i = c_i - c,  cos_i = n_i . n,  sin_i = |n_i x n|,  a_i = max(|lo_i|, |hi_i|)
    R   = max_i |d_i - (d_i . n) n| + r_i + a_i sin_i (encloses every leaf disk below,
                                                       projected into the parent's plane)
    lo  = min_i d_i . n + min(lo_i cos_i, hi_i cos_i) - r_i sin_i
    hi  = max_i d_i . n + max(lo_i cos_i, hi_i cos_i) + r_i sin_i
    e_p = hi - lo                                     (perpendicular error, survey Fig. 11:
                                                       width of the slab parallel to the
                                                       disk that encloses all child disks)
    e_t = max_k (R - max_i [d_i . u_k + r_i sqrt(1 - (n_i . u_k)^2) + a_i |n_i . u_k|])
                                                      (tangential error, survey Fig. 12: how
                                                       far the parent disk overhangs the
                                                       children's extent, measured in K = 8
                                                       in-plane directions u_k, 45 deg apart)
    e_g = max(sqrt(e_p^2 + e_t^2), max_i e_g_i)       (geometric error; the max with the
                                                       children keeps e_g monotone along
                                                       every root-to-leaf path)

Because R and [lo, hi] bound every leaf disk of the subtree (by induction: a leaf disk lies
within r_i of c_i in its own plane), a parent disk covers all its descendants' disks when
seen along its normal: replacing children by their parent never opens a hole.
Leaves are the input points with their own radii, normals, colours and axes; their errors
are 0 and their area weight is |u| |v| (the ellipse area / pi).

Attributes (surfel.attributes). A parent's continuous attribute a is the area-weighted mean
of its children's, a = sum w_i a_i / sum w_i (the colour's rule; integers are rounded back
to their dtype). A categorical attribute is never averaged, since the mean of two classes is
no class: the parent takes the value of its heaviest child (the largest w_i, the child its
normal is aligned with), which by induction is the value of one leaf below it, its
representative. Derived arrays are not aggregated: the leaves keep their clip lines and inner
nodes cut nothing; the Phong slopes are dropped, since an inner node is a new disk.

Screen-facing splats (surfel.preprocess.structure: points on no surface, drawn as round disks
facing the camera) reach r_i from their centre in every direction: as children they enter the
rule above with the slab [-r_i, r_i]. A parent is screen-facing when most of its children's
area is (sum over the screen-facing children of w_i >= sum w_i / 2), so an inner node of
screen-facing children is screen-facing; its disk then faces the camera too, and must enclose
its children whichever way it is seen: its radius is at least the sphere bound
max_i |d_i| + sqrt(R_i^2 + a_i^2), and the slab it shows its own parent is [-R, R] (its e_p
stays its children's spread, e_t its overhang at that radius).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import numba
import numpy as np
from tqdm import tqdm

from ..attributes import CATEGORICAL
from ..cloud import PointCloud, corners, read_only, stable_order
from ..preprocess import CLIP_LINES, INACTIVE_CLIP, clipped_away
from ..threads import over_rows

MORTON_BITS = 21  # bits per axis: 63-bit codes
# r_max of the root is infinite; it is stored as the largest float32 because point-cloud
# attributes must be finite (on the GPU e * k then overflows to +inf, which is still right)
ROOT_PARENT_ERROR = float(np.finfo(np.float32).max)


@dataclass(frozen=True, eq=False)
class LodTree:
    """A point hierarchy: nodes 0..n_leaves-1 are the input points in Morton order (leaf j is
    input point point_index[j]), the rest are inner nodes; the last node is the root.
    geospatial is carried over from the input cloud (its up axis).

    positions (M, 3) float64, normals (M, 3) float32 unit, colors (M, 3) float32 or None,
    radii (M,) float32 (leaves: max semi-axis; inner: enclosing radius), axes (M, 2, 3)
    float32 (inner nodes: circular, |u| = |v| = radius), e_p, e_t, e_g (M,) float32,
    parent (M,) int64 (-1 for the root), d_parent (M,) float32 |c - c_parent| (0 for the
    root), child_start (M + 1,) int64 and children (M - 1,) int64: the children of node j
    are children[child_start[j]:child_start[j + 1]]. clip_lines (M, 2, 3) float32 or None:
    the leaves' clip lines at sharp features (surfel.preprocess); inner nodes' cut nothing.
    screen_facing (M,) float32 or None: 1 for the nodes drawn facing the camera (module
    docstring).
    attributes: the input's scanner attributes (M, ...) in their dtypes, aggregated for inner
    nodes (module docstring); kinds: their kinds.
    """

    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray | None
    radii: np.ndarray
    axes: np.ndarray
    e_p: np.ndarray
    e_t: np.ndarray
    e_g: np.ndarray
    parent: np.ndarray
    d_parent: np.ndarray
    child_start: np.ndarray
    children: np.ndarray
    point_index: np.ndarray
    geospatial: bool = False
    clip_lines: np.ndarray | None = None
    screen_facing: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def n_leaves(self) -> int:
        return len(self.point_index)

    @property
    def root(self) -> int:
        return len(self.positions) - 1

    def parent_error(self) -> np.ndarray:
        """e_g of each node's parent (ROOT_PARENT_ERROR for the root): the node's r_max / k."""
        out = np.full(len(self), ROOT_PARENT_ERROR, np.float32)
        has = self.parent >= 0
        out[has] = self.e_g[self.parent[has]]
        return out

    def children_of(self, nodes: np.ndarray) -> np.ndarray:
        """The children of `nodes`, concatenated in that order (a CSR gather)."""
        starts = self.child_start[nodes]
        counts = self.child_start[nodes + 1] - starts
        total = int(counts.sum())
        # index within the concatenation minus the run's offset there = index within the run
        shift = np.repeat(starts - (np.cumsum(counts) - counts), counts)
        return self.children[np.arange(total) + shift]


@numba.njit(parallel=True, cache=True)
def _morton_codes(positions, lo, scale):  # pragma: no cover - compiled
    """Interleave the 21-bit quantised x, y, z of each position into a 63-bit code."""
    top = (1 << MORTON_BITS) - 1
    codes = np.empty(len(positions), np.uint64)
    for i in numba.prange(len(positions)):
        code = np.uint64(0)
        for axis in range(3):
            q = min(max(np.int64((positions[i, axis] - lo[axis]) * scale), 0), top)
            x = np.uint64(q)
            # spread the 21 bits two apart (magic-number method)
            x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
            x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
            x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
            x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
            x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
            code |= x << np.uint64(2 - axis)
        codes[i] = code
    return codes


def morton_codes(positions: np.ndarray) -> np.ndarray:
    """63-bit Morton codes of positions quantised to 2^21 cells per axis of the bounding cube."""
    lo, hi = corners(positions)
    extent = max(float((hi - lo).max()), 1e-300)
    return _morton_codes(positions, lo, ((1 << MORTON_BITS) - 1) / extent)


def morton_order(positions: np.ndarray) -> np.ndarray:
    """An order of positions (N, 3) by Morton code (`morton_codes`) but for the codes' last b
    bits (b: those of a row index): their top 63 - b bits and each row's index sorted as one
    int64 (`stable_order`), faster than an argsort of the codes, rows apart by less keeping
    their order. In it, the completion and the tree gather from nearby rows, and `build_lod`
    finds its codes nearly sorted."""
    codes = morton_codes(positions)
    bits = max(len(codes) - 1, 1).bit_length()
    return stable_order((codes >> np.uint64(bits)).astype(np.int64))


def _absent(shape: tuple[int, ...]) -> np.ndarray:
    """An empty float32 stand-in for an array the cloud lacks, read-only like the cloud's own:
    numba compiles one kernel whichever arrays a cloud has."""
    return read_only(np.empty(shape, np.float32))


def _init_leaves(order, in_pos, in_col, in_axes, in_normals, in_radii, in_clip,
                 pos, col, nrm, rad, axes, weight, clip):
    """Leaf j = input point order[j] (Morton order, so that siblings are neighbours in memory):
    axes as given (or circular from the normal), enclosing radius max(|u|, |v|), area weight
    |u| |v| (the ellipse area / pi), its clip lines (if in_clip is not empty); the rows of clip
    past the leaves, the inner nodes', get INACTIVE_CLIP."""
    over_rows(_leaf_rows, len(order), order, in_pos, in_col, in_axes, in_normals, in_radii, in_clip,
              pos, col, nrm, rad, axes, weight, clip)
    clip[len(order):] = INACTIVE_CLIP


@numba.njit(cache=True, nogil=True)
def _leaf_rows(first, stop, order, in_pos, in_col, in_axes, in_normals, in_radii, in_clip,
               pos, col, nrm, rad, axes, weight, clip):  # pragma: no cover - compiled
    """Leaves first:stop of `_init_leaves`."""
    for j in range(first, stop):
        i = order[j]
        nx, ny, nz = in_normals[i, 0], in_normals[i, 1], in_normals[i, 2]
        for c in range(3):
            pos[j, c] = in_pos[i, c]
            nrm[j, c] = in_normals[i, c]
            if len(in_col):
                col[j, c] = in_col[i, c]
            if len(in_clip):
                for line in range(in_clip.shape[1]):
                    clip[j, line, c] = in_clip[i, line, c]
        if len(in_axes):
            for c in range(3):
                axes[j, 0, c] = in_axes[i, 0, c]
                axes[j, 1, c] = in_axes[i, 1, c]
            lu = np.sqrt(in_axes[i, 0, 0] ** 2 + in_axes[i, 0, 1] ** 2 + in_axes[i, 0, 2] ** 2)
            lv = np.sqrt(in_axes[i, 1, 0] ** 2 + in_axes[i, 1, 1] ** 2 + in_axes[i, 1, 2] ** 2)
        else:
            r = in_radii[i]
            tx, ty, tz, bx, by, bz = _tangents(nx, ny, nz)
            axes[j, 0, 0], axes[j, 0, 1], axes[j, 0, 2] = tx * r, ty * r, tz * r
            axes[j, 1, 0], axes[j, 1, 1], axes[j, 1, 2] = bx * r, by * r, bz * r
            lu = lv = r
        rad[j] = max(lu, lv)
        weight[j] = lu * lv


@numba.njit(inline="always")
def _tangents(nx, ny, nz):  # pragma: no cover - compiled
    """An orthonormal tangent pair (t, b) of unit normal n, b = n x t."""
    if abs(nx) < 0.9:
        tx, ty, tz = 0.0, nz, -ny  # n x (1, 0, 0)
    else:
        tx, ty, tz = -nz, 0.0, nx  # n x (0, 1, 0)
    tl = np.sqrt(tx * tx + ty * ty + tz * tz)
    tx, ty, tz = tx / tl, ty / tl, tz / tl
    return tx, ty, tz, ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx


@numba.njit(cache=True)
def _next_level(active, codes, next_id):  # pragma: no cover - compiled
    """One octree level up: runs of equal codes >> 3 are the cells. Returns the nodes of
    the coarser level (a cell with one node keeps it; a cell with more gets the new node
    next_id + g, g counting such cells in order), their cell codes, and for the new nodes
    the start and size of their runs in `active` and the concatenated children."""
    n = len(active)
    out_active = np.empty(n, np.int64)
    out_codes = np.empty(n, np.uint64)
    starts = np.empty(n // 2, np.int64)
    sizes = np.empty(n // 2, np.int64)
    children = np.empty(n, np.int64)
    cells = merged = listed = 0
    i = 0
    while i < n:
        key = codes[i] >> np.uint64(3)
        j = i + 1
        while j < n and codes[j] >> np.uint64(3) == key:
            j += 1
        if j - i >= 2:
            starts[merged] = i
            sizes[merged] = j - i
            for t in range(i, j):
                children[listed] = active[t]
                listed += 1
            out_active[cells] = next_id + merged
            merged += 1
        else:
            out_active[cells] = active[i]
        out_codes[cells] = key
        cells += 1
        i = j
    return out_active[:cells], out_codes[:cells], starts[:merged], sizes[:merged], children[:listed]


@numba.njit(inline="always")
def _reach(dx, dy, dz, nx, ny, nz, ux, uy, uz, radius, slab):  # pragma: no cover - compiled
    """Offset d . u of a child centre along in-plane direction u, and how far beyond it the
    child's disk (radius, tilted by its normal n) and its slab half-width reach along u."""
    nu = nx * ux + ny * uy + nz * uz
    return dx * ux + dy * uy + dz * uz, radius * np.sqrt(max(0.0, 1.0 - nu * nu)) + slab * abs(nu)


def _merge_cells(starts, counts, members, first, pos, nrm, col, rad, axes, weight, lo, hi,
                 e_p, e_t, e_g, parent, d_parent, representative, with_color, facing):
    """Create node first + g from the children members[starts[g]:starts[g] + counts[g]];
    its representative leaf is that of its heaviest child. `facing` (M,) marks the
    screen-facing nodes (empty: none), which a new node joins when most of its children's
    area faces the camera."""
    over_rows(_merge_rows, len(starts), starts, counts, members, first, pos, nrm, col, rad, axes, weight, lo, hi,
              e_p, e_t, e_g, parent, d_parent, representative, with_color, facing)


@numba.njit(cache=True, nogil=True)
def _merge_rows(begin, stop, starts, counts, members, first, pos, nrm, col, rad, axes, weight, lo, hi,
                e_p, e_t, e_g, parent, d_parent, representative, with_color, facing):  # pragma: no cover - compiled
    """Cells begin:stop of `_merge_cells`."""
    for g in range(begin, stop):
        s = starts[g]
        e = s + counts[g]
        out = first + g
        # weights, mean position, heaviest child (orientation reference for the normal)
        wsum = 0.0
        cx = cy = cz = 0.0
        best = members[s]
        for j in range(s, e):
            i = members[j]
            w = weight[i]
            wsum += w
            cx += w * pos[i, 0]
            cy += w * pos[i, 1]
            cz += w * pos[i, 2]
            if w > weight[best]:
                best = i
        cx /= wsum
        cy /= wsum
        cz /= wsum
        nx = ny = nz = 0.0
        r0 = g0 = b0 = 0.0
        for j in range(s, e):
            i = members[j]
            w = weight[i]
            if with_color:
                r0 += w * col[i, 0]
                g0 += w * col[i, 1]
                b0 += w * col[i, 2]
            if nrm[i, 0] * nrm[best, 0] + nrm[i, 1] * nrm[best, 1] + nrm[i, 2] * nrm[best, 2] < 0.0:
                w = -w
            nx += w * nrm[i, 0]
            ny += w * nrm[i, 1]
            nz += w * nrm[i, 2]
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length < 1e-9 * wsum:  # children cancel out (a fold): keep the heaviest one's
            nx, ny, nz = nrm[best, 0], nrm[best, 1], nrm[best, 2]
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / length, ny / length, nz / length
        tx, ty, tz, bx, by, bz = _tangents(nx, ny, nz)
        # the K = 8 in-plane directions are +-t, +-b, +-(t + b)/sqrt2, +-(t - b)/sqrt2: four
        # axes, each giving the extents on both of its sides
        h = np.sqrt(0.5)
        dx1, dy1, dz1 = h * (tx + bx), h * (ty + by), h * (tz + bz)
        dx2, dy2, dz2 = h * (tx - bx), h * (ty - by), h * (tz - bz)
        p0 = p1 = p2 = p3 = m0 = m1 = m2 = m3 = -np.inf
        radius = 0.0
        slo = np.inf
        shi = -np.inf
        child_err = 0.0
        sphere = 0.0  # the sphere about c that holds every child's reach
        facing_weight = 0.0
        for j in range(s, e):
            i = members[j]
            dx, dy, dz = pos[i, 0] - cx, pos[i, 1] - cy, pos[i, 2] - cz
            d_parent[i] = np.sqrt(dx * dx + dy * dy + dz * dz)
            if len(facing):
                slab = max(abs(lo[i]), abs(hi[i]))
                sphere = max(sphere, d_parent[i] + np.sqrt(rad[i] * rad[i] + slab * slab))
                facing_weight += weight[i] * facing[i]
            dn = dx * nx + dy * ny + dz * nz
            px, py, pz = dx - dn * nx, dy - dn * ny, dz - dn * nz
            n0, n1, n2 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
            cos = n0 * nx + n1 * ny + n2 * nz
            # |n_i x n|, not sqrt(1 - cos^2), which cancels for near-parallel normals
            sx, sy, sz = n1 * nz - n2 * ny, n2 * nx - n0 * nz, n0 * ny - n1 * nx
            sin = np.sqrt(sx * sx + sy * sy + sz * sz)
            a = max(abs(lo[i]), abs(hi[i]))
            ri = rad[i]
            radius = max(radius, np.sqrt(px * px + py * py + pz * pz) + ri + a * sin)
            slo = min(slo, dn + min(lo[i] * cos, hi[i] * cos) - ri * sin)
            shi = max(shi, dn + max(lo[i] * cos, hi[i] * cos) + ri * sin)
            child_err = max(child_err, e_g[i])
            du, reach = _reach(dx, dy, dz, n0, n1, n2, tx, ty, tz, ri, a)
            p0, m0 = max(p0, du + reach), max(m0, reach - du)
            du, reach = _reach(dx, dy, dz, n0, n1, n2, bx, by, bz, ri, a)
            p1, m1 = max(p1, du + reach), max(m1, reach - du)
            du, reach = _reach(dx, dy, dz, n0, n1, n2, dx1, dy1, dz1, ri, a)
            p2, m2 = max(p2, du + reach), max(m2, reach - du)
            du, reach = _reach(dx, dy, dz, n0, n1, n2, dx2, dy2, dz2, ri, a)
            p3, m3 = max(p3, du + reach), max(m3, reach - du)
            parent[i] = out
        ep = shi - slo
        if len(facing):
            facing[out] = 1.0 if 2.0 * facing_weight >= wsum else 0.0
            if facing[out] > 0.0:  # a disk facing the camera reaches its radius every way
                radius = max(radius, sphere)
                slo, shi = min(slo, -radius), max(shi, radius)
        extent = min(min(p0, p1, p2, p3), min(m0, m1, m2, m3))
        overhang = max(0.0, radius - extent)
        pos[out, 0], pos[out, 1], pos[out, 2] = cx, cy, cz
        nrm[out, 0], nrm[out, 1], nrm[out, 2] = nx, ny, nz
        if with_color:
            col[out, 0], col[out, 1], col[out, 2] = r0 / wsum, g0 / wsum, b0 / wsum
        rad[out] = radius
        axes[out, 0, 0], axes[out, 0, 1], axes[out, 0, 2] = tx * radius, ty * radius, tz * radius
        axes[out, 1, 0], axes[out, 1, 1], axes[out, 1, 2] = bx * radius, by * radius, bz * radius
        weight[out] = wsum
        representative[out] = representative[best]
        lo[out] = slo
        hi[out] = shi
        e_p[out] = ep
        e_t[out] = overhang
        e_g[out] = max(np.sqrt(ep * ep + overhang * overhang), child_err)


def build_lod(cloud: PointCloud, *, progress: bool | None = None) -> LodTree:
    """The octree point hierarchy of `cloud` (which needs normals, and radii or axes).

    progress: show a tqdm bar over the octree levels (None: only on a terminal).
    Points that their clip lines cut away whole (crease points, surfel.preprocess) are left
    out: they draw nothing, and their averaged disks must not come back in inner nodes.
    """
    if cloud.normals is None or (cloud.radii is None and cloud.axes is None):
        raise ValueError("build_lod needs normals and radii or axes (complete the cloud first)")
    kept = np.flatnonzero(~clipped_away(cloud)) if "clip_lines" in cloud.attributes else np.arange(len(cloud))
    n = len(kept)
    capacity = 2 * n - 1  # every inner node has >= 2 children
    codes = morton_codes(cloud.positions[kept])
    order = np.argsort(codes, kind="stable")  # timsort: codes nearly in order (`morton_order`) in one pass
    point_index = kept[order]
    active_codes = codes[order]
    del codes
    pos = np.empty((capacity, 3), np.float64)
    with_color = cloud.colors is not None
    col = np.empty((capacity if with_color else 1, 3), np.float32)
    nrm = np.empty((capacity, 3), np.float32)
    rad = np.empty(capacity, np.float32)
    axes = np.empty((capacity, 2, 3), np.float32)
    weight = np.empty(capacity, np.float64)
    representative = np.empty(capacity, np.int64)
    representative[:n] = np.arange(n)
    in_clip = cloud.attributes.get("clip_lines", _absent((0, CLIP_LINES, 3)))
    clip_lines = np.empty((capacity if len(in_clip) else 0, *in_clip.shape[1:]), np.float32)
    _init_leaves(point_index, cloud.positions,
                 cloud.colors if with_color else _absent((0, 3)),
                 cloud.axes if cloud.axes is not None else _absent((0, 2, 3)),
                 cloud.normals, cloud.radii if cloud.radii is not None else _absent((0,)), in_clip,
                 pos, col, nrm, rad, axes, weight, clip_lines)
    # slab bounds are build-time state only; float64 keeps the induction exact
    lo = np.zeros(capacity, np.float64)
    hi = np.zeros(capacity, np.float64)
    facing = np.zeros(capacity if "screen_facing" in cloud.attributes else 0, np.float32)
    if len(facing):
        facing[:n] = cloud.attributes["screen_facing"][point_index]
        round_leaves = np.flatnonzero(facing[:n] > 0.5)
        lo[round_leaves], hi[round_leaves] = -rad[round_leaves], rad[round_leaves]  # they reach r every way
    e_p = np.zeros(capacity, np.float32)
    e_t = np.zeros(capacity, np.float32)
    e_g = np.zeros(capacity, np.float32)
    parent = np.full(capacity, -1, np.int64)
    d_parent = np.zeros(capacity, np.float32)
    child_lists, child_counts = [], []

    active = np.arange(n)
    count = n
    show = sys.stderr.isatty() if progress is None else progress
    for _ in tqdm(range(MORTON_BITS), desc="lod build", unit="level", disable=not show):
        if len(active) == 1:
            break
        next_active, active_codes, starts, sizes, children = _next_level(active, active_codes, count)
        if len(starts):
            _merge_cells(starts, sizes, active, count, pos, nrm, col, rad, axes, weight,
                         lo, hi, e_p, e_t, e_g, parent, d_parent, representative, with_color, facing)
            child_lists.append(children)
            child_counts.append(sizes)
            count += len(starts)
        active = next_active

    m = count
    child_start = np.zeros(m + 1, np.int64)
    if m > n:  # inner nodes were numbered in the order their child runs were listed
        child_start[n + 1:] = np.cumsum(np.concatenate(child_counts))
    children = np.concatenate(child_lists) if child_lists else np.empty(0, np.int64)
    del lo, hi
    scanner = cloud.schema.scanner()
    attributes = aggregate_attributes({spec.name: cloud.attributes[spec.name][point_index] for spec in scanner},
                                      {spec.name: spec.kind for spec in scanner}, child_start, children,
                                      weight[:m], representative[:m])
    del weight, representative
    arrays = [pos, nrm, rad, axes, e_p, e_t, e_g, parent, d_parent] + ([col] if with_color else []) + \
        ([clip_lines] if len(clip_lines) else [])
    for array in arrays:
        array.resize((m, *array.shape[1:]), refcheck=False)  # shrink in place, no copy
    return LodTree(pos, nrm, col if with_color else None, rad, axes, e_p, e_t, e_g, parent,
                   d_parent, child_start, children, point_index, cloud.geospatial,
                   clip_lines if len(clip_lines) else None,
                   facing[:m].copy() if len(facing) else None, attributes,
                   {spec.name: spec.kind for spec in scanner})


def aggregate_attributes(leaves: dict[str, np.ndarray], kinds: dict[str, str], child_start: np.ndarray,
                         children: np.ndarray, weight: np.ndarray, representative: np.ndarray
                         ) -> dict[str, np.ndarray]:
    """Every node's attributes (M, ...) from the leaves' (L, ...) (module docstring).

    Nodes 0..L-1 are the leaves, inner nodes follow their children; child_start (M + 1,) and
    children list each node's children, weight (M,) are the area weights and representative
    (M,) each node's representative leaf (`_merge_cells`).
    """
    count = len(representative)
    out = {}
    for name, values in leaves.items():
        if kinds[name] == CATEGORICAL:
            out[name] = values[representative]
            continue
        flat = values.reshape(len(values), -1)
        means = np.empty((count, flat.shape[1]), np.float64)
        means[:len(values)] = flat
        _weighted_means(child_start, children, weight, means, len(values))
        out[name] = from_mean(means, values.dtype).reshape(count, *values.shape[1:])
    return out


@numba.njit(cache=True)
def _weighted_means(child_start, children, weight, values, first):  # pragma: no cover - compiled
    """values[node] = sum w_i values[i] / sum w_i over the children i of each inner node
    first.. (in order: children come before their parents)."""
    components = values.shape[1]
    for node in range(first, len(values)):
        total = 0.0
        for c in range(components):
            values[node, c] = 0.0
        for j in range(child_start[node], child_start[node + 1]):
            child = children[j]
            w = weight[child]
            total += w
            for c in range(components):
                values[node, c] += w * values[child, c]
        for c in range(components):
            values[node, c] /= total


def from_mean(means: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Means (float64) in an attribute's dtype: integers rounded (a mean of values that fit
    fits too), booleans true from one half up."""
    dtype = np.dtype(dtype)
    if dtype.kind == "b":
        return means >= 0.5
    if dtype.kind in "iu":
        return np.rint(means).astype(dtype)
    return means.astype(dtype)
