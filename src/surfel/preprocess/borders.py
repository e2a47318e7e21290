"""Borders of open surfaces: which points lie on the edge of a sheet, and which way is out.

A disk centred on a sheet's last row of samples spills past the sheet's edge by its radius,
which grows the outline of every open surface (a flat part, cloth, a scanned patch). As in the
boundary clipping of Pauly, Keiser, Kobbelt & Gross 2003 ("Shape modeling with point-sampled
geometry"), splats are cut at the border instead.

A point p is on a border when its neighbours, projected into its tangent plane, leave an
angular gap of at least BORDER_GAP (an interior point of a regular sampling sees gaps of about
60 degrees) and no second gap over INTERIOR_GAP (a scan line seen from one of its points). It is
confirmed among its BORDER_CONFIRM nearest neighbours, because a sampling far denser on one side
(a CAD mesh's vertices crowd at its curves) leaves a gap towards the sparse side among the
nearest ones. Neighbours on another layer lying close (a body under a sheet, `thickness.py`) do
not close a gap. Its outward direction w_p is the middle of the gap among its nearest
neighbours, also where the wider ones confirmed it.

Where a far denser sampling lies to one side of p (a CAD part's fillet, its vertices crowded
along the curve, beside a flat face tessellated by rows far apart), even the BORDER_CONFIRM
nearest may all lie within p's closing distance (below) on that side, and leave the face a
gap. Such a border is dropped where one of its BORDER_WIDE nearest continues p's sheet ahead
of it, within its closing distance (`_sheet_beyond`): facing its way, on its layer
(within SHEET_SPACINGS spacings, by thickness.py's measure) and within 45 degrees of w_p. On a
rocker arm's vertices seen from its side (512 x 512, azimuth 270, elevation 10) the false
borders had cut a star-shaped hole of 76 pixels into a face: holes 0.165% -> 0.067% and
+1.7 dB (`phong`); over 11 models' vertices in six views each, no render lost more than
0.03 dB, and raw scans moved by no more than that.

A neighbour q farther from p in the tangent plane than CLOSING_SPACINGS times the larger of
their spacings (spacing.py) lies across a gap and closes none: in a concave notch of an outline
(a figure's armpit, the fork of its legs), the samples across the notch would otherwise close
the gap of the edge's last samples, and their splats would fill the notch. Two samplings keep
their far neighbours: where p's near ones lie along one line through it (one row of a strip
whose rows lie farther apart than its samples along them), and, where the near ones leave a
border, the neighbours within CLOSING_SPACINGS times the depth of the nearest row behind p
(a neighbour at least 30 degrees, ROW_DEPTH, off the border line): rows spaced unevenly, the
next one out farther than the one in (the rings of a coarse tail), are no border.
(On the vertices of 13 models outside ../shared, `benchmarks/scan_fidelity.py --vertices`:
median PSNR 33.8 -> 35.8 dB for `deferred` and 35.1 -> 36.7 dB for `phong`, a car's body
with its window openings +3 to +5 dB, flat cut-out figures +0.3 to +1.3 dB, no render with
more holes. 3 spacings gave the cut-outs +3 dB more, but a sampling at random has voids that
wide: 0.7% of the points of a sphere became borders, and its splats left holes.)

Neighbours facing away (n_p . n_q < SHEET_COS) are of two kinds:
  * in p's plane (within FLAT_SIN2): the same surface seen from behind (a shell scanned from
    inside and out, whose normals point either way); they close gaps like any neighbour;
  * off it: the far side of a thin part folding back at its rim (a tail, an ear, a cut-out
    figure, a car's sill). They close no gap: each side ends at its own last samples, where
    the rim begins, instead of spilling past the rim by a splat radius. The rim lies at least
    as far out as the far side's samples reach, so the border line moves out to the farthest of
    them along w_p, the fold's reach f_p = max(0, max_q (q - p) . w_p) (0 on an open sheet).
    (Measured on the raw range scans of 13 models, `benchmarks/scan_fidelity.py`: median PSNR
    +2.3 dB for `deferred` and +2.7 dB for `phong`, up to +9 dB on flat cut-out figures, where
    the spill along the rims had been the largest error.)

A mesh's vertices lie on its edges, but a raw scan's last samples lie short of its edges:
range noise scatters them, and the samples nearest an edge are the ones lost at grazing angles.
So the border lines of a noisy cloud (normals estimated, and noisy by the test of their
neighbourhood scale selection, normals.py) move out by NOISY_MARGIN of the splat's extent
across them. (On the raw scans of 13 models: worst holes 0.197% -> 0.091% for `phong`, median
PSNR 31.3 -> 30.9 dB; 0.1 left 0.144% of holes.) A scan denoised by `prepare --smooth` keeps
the margin, though its normals no longer look noisy: its samples lost at grazing angles stay
lost. (Scans of five models, prepared with --smooth, then rendered: worst holes 0.157% ->
0.152% for `phong`, casting.obj obliquely 0.097% -> 0.064%, median PSNR unchanged.)

A mesh says where its borders are: its boundary edges, those of one face only (its vertices
welded by position first, so that a seam, a crease split for flat shading or the corners a CAD
export rounds apart are no boundary: within WELD_TOLERANCE of its size). Its vertices there are
borders whatever their neighbours show, facing out of their faces: the sum over its boundary
edges of each edge's unit normal in its face, pointing away from the face's third corner,
projected into the vertex's tangent plane (`mesh_border_outwards`). The neighbours cannot tell a
narrow notch of a cut-out's outline (the fork of a figure's legs, an armpit) from the sheet
going on, and the middle of their gap tilts along a curving outline. The borders the neighbours
find elsewhere stay (a closed mesh's thin rims, which fold, with their reach). A boundary vertex
lying within CRACK_SHARE of its edges' length from a boundary edge not its own is a crack's
side, no border: two patches meeting at T-junctions (a decimation's, a CAD export's) leave edges
of one face each along their seam, with the surface going on across it; a crack wider than that
is open, and a border on both sides. An outline's corner has one line, half-way between its
edges' directions: past a convex corner its splat reaches a little beyond both edges (a concave
corner's edges' lines stop at it, cells.py). (18 views at 512 x 512 against the mesh, median
PSNR `phong` / `deferred`: libigl's woody, a flat figure whose legs fork in a notch two spacings
wide, 25.7 / 25.6 -> 34.5 / 33.9 dB; the alligator cut-out 33.7 / 33.2 -> 40.2 / 37.6 dB; the
Newell teapot 34.3 / 33.9 -> 36.6 / 35.8 dB; a car body with its windows open, beetle-alt.obj,
37.6 / 35.9 -> 40.3 / 36.6 dB; the Stanford bunny, open at its base, 41.3 / 39.7 -> 42.1 / 39.8
dB; three decimated figures within -0.01 to +0.24 dB, no view over 0.1% holes; closed meshes
prepare exactly as before.)

Aerial scan lines (geospatial clouds) get no borders (`complete.py`): a line with the next line
on one side only looks like one.

What is done with it is the clip lines' (`cells.py`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..cloud import any_per_row
from ..io.mesh import edge_runs
from ..threads import over_rows
from .chunked import map_chunks
from .frames import orthonormal_basis, unit
from .neighbourhood import Neighbourhood
from .sharp_features import FLAT_SIN2, SHEET_COS

BORDER_GAP = math.radians(120.0)   # neighbours leaving a gap this wide: p is on a border
INTERIOR_GAP = math.radians(100.0)  # ... unless another gap is this wide too (a scan line)
BORDER_CONFIRM = 64                 # neighbours among which a border is confirmed
BORDER_WIDE = 256                   # where those lie within its closing distance: the sheet ahead among these
SHEET_SPACINGS = 0.25               # a neighbour this many spacings off p's layer is another sheet
BEYOND_COS2 = math.cos(math.radians(45.0)) ** 2  # ... ahead of a border: within 45 degrees of w_p
BEYOND_BLOCK = 1024                 # borders checked at once (bounds the (rows, BORDER_WIDE) arrays)
KERNEL_BLOCK = 1024                 # the fewest points per thread's piece of the kernels
CLOSING_SPACINGS = 4.0              # neighbours farther than this many spacings lie across a gap
WELD_TOLERANCE = 1e-7               # of a mesh's size: vertices this close are one (a CAD export's rounding)
CRACK_SHARE = 0.1                   # of its edges' length from another boundary edge: a crack's side, no border
CRACK_STEPS = 8                     # ... the edges taken at this many steps
CRACK_NEIGHBOURS = 32               # ... among this many points of edges nearest it
NOISY_MARGIN = 0.2                  # a noisy cloud's border lines move out by this much of the splat
# pseudo-angle bins (of [-2, 2], circular) of which no EMPTY_RUN + 1 consecutive ones are empty
# leave no gap of (EMPTY_RUN + 2) KEY_BIN between keys, less than INTERIOR_GAP / 2: no gap counts,
# found without sorting the neighbours; no BORDER_RUN + 1 empty ones leave none of BORDER_GAP / 2
# in pseudo-angle, so none of BORDER_GAP (an angle is at most twice its pseudo-angle): no border
KEY_BINS = 64
KEY_BIN = 4.0 / KEY_BINS
EMPTY_RUN = 11
BORDER_RUN = 14
ALL_BINS = np.uint64(0xFFFFFFFFFFFFFFFF)
# The angles of a point's near neighbours in ANGLE_BINS bins of the circle, computed within
# ATAN_ERROR radians: a gap of BORDER_GAP between them leaves at least ANGLE_RUN + 1 consecutive
# bins empty (those wholly inside it, less the error at each end)
ANGLE_BINS = 64
ATAN_SLOPE = 0.273
ATAN_ERROR = 0.005
ANGLE_RUN = int((BORDER_GAP - 2.0 * ATAN_ERROR) / (2.0 * math.pi / ANGLE_BINS)) - 2
ROW_SECTORS = 8                     # sectors of the pseudo-angle in which near neighbours lie in a row
ROW_DEPTH = 0.5                     # a neighbour 30 degrees or more off the border line: a row inside


def _border_outwards(points, normals, index, rows, frames, sheet_cos, flat_sin2, layers, closing2):
    """Per point rows[i], the unit tangent (3,) pointing out of the surface if the point lies on
    the border of an open surface, else zero, and the fold's reach f_p (0 elsewhere).

    A point is on a border when its neighbours, projected into its tangent plane (t, s) =
    frames[i], leave one angular gap wider than BORDER_GAP while every other gap stays below
    INTERIOR_GAP (two wide gaps: a scan line, not a border); outwards is the middle of the gap.
    Neither the far side of a fold (neighbours facing away, n_p . n_q < sheet_cos, off p's
    plane by more than flat_sin2) nor another layer (separated by more than layers[p],
    thickness.py) closes a gap, nor a neighbour q farther than the square root of
    max(closing2[p], closing2[q]) unless the rows of `_point_outwards` say so (module docstring)."""
    outwards = np.zeros((len(rows), 3))
    reach = np.zeros(len(rows))
    over_rows(_outwards_rows, len(rows), points, normals, index, rows, frames, sheet_cos, flat_sin2, layers,
              closing2, outwards, reach, grain=KERNEL_BLOCK)
    return outwards, reach


@numba.njit(cache=True, nogil=True)
def _outwards_rows(first, stop, points, normals, index, rows, frames, sheet_cos, flat_sin2, layers, closing2,
                   outwards, reach):  # pragma: no cover - compiled
    """Rows first:stop of `_border_outwards`. A point whose near neighbours' directions leave
    no ANGLE_RUN + 1 consecutive ANGLE_BINS empty is no border (`_point_outwards` counts those
    neighbours and more): known from its neighbours gathered into rows and binned in SIMD code
    (`_near_angles`), before the per-neighbour branches of `_point_outwards` (a partition of
    1.4M points sampled at random from a surface, on one core: the pass 0.60 -> 0.38 s)."""
    k = index.shape[1]
    # one set of buffers per call: an allocation per point costs as much as its work
    found = np.empty((5, k))  # key, x, y, squared distance and closing distance as they come
    keys = np.empty(k)
    xs = np.empty(k)
    ys = np.empty(k)
    far = np.empty((2, k))  # x, y of the fold's far side
    gathered = np.empty((7, k))  # a point's neighbours' offsets, normals and closing distances, in rows
    for i in range(first, stop):
        p = rows[i]
        for j in range(k):
            q = index[i, j]
            for a in range(3):
                gathered[a, j] = points[q, a] - points[p, a]
                gathered[3 + a, j] = normals[q, a]
            gathered[6, j] = closing2[q] if q != p else -1.0
        bins = _near_angles(gathered, k, frames[i, 0, 0], frames[i, 0, 1], frames[i, 0, 2], frames[i, 1, 0],
                            frames[i, 1, 1], frames[i, 1, 2], normals[p, 0], normals[p, 1], normals[p, 2],
                            layers[p], closing2[p], sheet_cos, flat_sin2)
        if _no_wide_gap(bins, ANGLE_RUN):
            continue
        _point_outwards(points, normals, index, rows, frames, sheet_cos, flat_sin2, layers, closing2, i, found,
                        keys, xs, ys, far, outwards, reach)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _near_angles(gathered, k, tx, ty, tz, sx, sy, sz, mx, my, mz, layer, own, sheet_cos,
                 flat_sin2):  # pragma: no cover - compiled
    """The ANGLE_BINS bins holding the directions of the neighbours that `_point_outwards`
    counts as near, as bits, from their offsets gathered[0:3], normals gathered[3:6] and closing
    distances gathered[6] (negative: the point itself); p's tangent frame (t, s), normal m, layer
    and own closing distance. A loop without branches over contiguous rows, which compiles to
    SIMD code; the angles within ATAN_ERROR."""
    bins = np.uint64(0)
    for j in range(k):
        dx, dy, dz = gathered[0, j], gathered[1, j], gathered[2, j]
        facing = gathered[3, j] * mx + gathered[4, j] * my + gathered[5, j] * mz
        x = dx * tx + dy * ty + dz * tz
        y = dx * sx + dy * sy + dz * sz
        antisymmetric = dx * (mx + gathered[3, j]) + dy * (my + gathered[4, j]) + dz * (mz + gathered[5, j])
        height = dx * mx + dy * my + dz * mz
        distance2 = x * x + y * y
        near = ((not _far_side(facing, x, y, height, sheet_cos, flat_sin2)) & (gathered[6, j] >= 0.0)
                & ((x != 0.0) | (y != 0.0)) & (not 0.5 * abs(antisymmetric) > layer)
                & (distance2 <= max(own, gathered[6, j])))
        ax = abs(x)
        ay = abs(y)
        t = min(ax, ay) / max(ax, ay, 1e-300)
        octant = t * (0.25 * math.pi + ATAN_SLOPE * (1.0 - t))  # atan(t) within ATAN_ERROR
        angle = octant if ax >= ay else 0.5 * math.pi - octant
        angle = angle if x >= 0.0 else math.pi - angle
        angle = angle if y >= 0.0 else 2.0 * math.pi - angle
        bit = np.uint64(1) << np.uint64(int(angle * (ANGLE_BINS / (2.0 * math.pi)) + ANGLE_BINS) & (ANGLE_BINS - 1))
        bins |= bit if near else np.uint64(0)
    return bins


@numba.njit(cache=True, inline="always")
def _in_frame(points, normals, frames, i, p, q):  # pragma: no cover - compiled
    """Neighbour q of point p in p's tangent frame frames[i]: (n_p . n_q, x, y, (q - p) . (n_p +
    n_q), (q - p) . n_p), the fourth twice q's separation from p's layer."""
    facing = 0.0
    x = 0.0
    y = 0.0
    antisymmetric = 0.0
    height = 0.0
    for a in range(3):
        facing += normals[q, a] * normals[p, a]
        d = points[q, a] - points[p, a]
        x += d * frames[i, 0, a]
        y += d * frames[i, 1, a]
        antisymmetric += d * (normals[p, a] + normals[q, a])
        height += d * normals[p, a]
    return facing, x, y, antisymmetric, height


@numba.njit(cache=True, inline="always")
def _far_side(facing, x, y, height, sheet_cos, flat_sin2):  # pragma: no cover - compiled
    """Whether a neighbour at (x, y, height) in p's frame, its normal at cosine `facing` to p's,
    is the far side of a fold: facing away, and off p's plane (module docstring)."""
    return facing < sheet_cos and height * height > flat_sin2 * (x * x + y * y + height * height)


@numba.njit(cache=True, inline="always")
def _key_bit(key):  # pragma: no cover - compiled
    """The bit of the one of KEY_BINS bins of [-2, 2] that holds the pseudo-angle `key`."""
    return np.uint64(1) << np.uint64(min(int((key + 2.0) * (1.0 / KEY_BIN)), KEY_BINS - 1))


@numba.njit(cache=True, inline="always")
def _no_wide_gap(bins, empty_run):  # pragma: no cover - compiled
    """Whether every empty_run + 1 circularly consecutive bins of `bins` hold a key: then any two
    keys next to each other lie less than (empty_run + 2) KEY_BIN apart (the bins between them,
    at most empty_run, and their own two)."""
    covered = bins
    for shift in range(1, empty_run + 1):
        covered |= (bins << np.uint64(shift)) | (bins >> np.uint64(KEY_BINS - shift))
    return covered == ALL_BINS


@numba.njit(cache=True, inline="always")
def _one_row(bins):  # pragma: no cover - compiled
    """Whether the keys in `bins` lie along one line through the point: two opposite sectors
    (of ROW_SECTORS) hold some, and two opposite others none."""
    along = False
    across = False
    width = KEY_BINS // ROW_SECTORS
    mask = (np.uint64(1) << np.uint64(width)) - np.uint64(1)
    for s in range(ROW_SECTORS // 2):
        one = (bins >> np.uint64(s * width)) & mask
        other = (bins >> np.uint64((s + ROW_SECTORS // 2) * width)) & mask
        along |= one != 0 and other != 0
        across |= one == 0 and other == 0
    return along and across


@numba.njit(cache=True, inline="always")
def _widest_gap(found, used, inner2, keys, xs, ys):  # pragma: no cover - compiled
    """(widest, second, middle): the two widest angular gaps between the neighbours found[:, :used]
    that close gaps (their squared distance found[3] within the squared closing distance found[4]
    or `inner2`), and the direction of the widest's middle; (0, 0, 0) when no gap is wider than
    INTERIOR_GAP / 2 in pseudo-angle.

    The neighbours are sorted by the pseudo-angle a = 1 - x / (|x| + |y|), signed as y, in
    [-2, 2]: it orders directions as their angle does, without an arctangent, and
    da / dangle = 1 / (|cos| + |sin|)^2 lies in [1/2, 1], so a gap of less than INTERIOR_GAP / 2
    in a is less than INTERIOR_GAP in angle: only the other gaps, a few, take arctangents. When
    no EMPTY_RUN + 1 consecutive ones of the KEY_BINS bins of a are empty, every gap is narrower
    than (EMPTY_RUN + 2) KEY_BIN, below INTERIOR_GAP / 2 (a test's assertion): the point is
    interior, known without the sort."""
    bins = np.uint64(0)  # bit b set: some key lies in [-2 + b KEY_BIN, -2 + (b + 1) KEY_BIN)
    count = 0
    for a in range(used):
        if found[3, a] <= max(found[4, a], inner2):
            bins |= _key_bit(found[0, a])
            count += 1
    if count < 3 or _no_wide_gap(bins, EMPTY_RUN):
        return 0.0, 0.0, 0.0
    # sorted by key, equal keys in their order: each direction goes to its rank, the number of
    # keys below it and of equal ones before it (counts that compile to SIMD compares, where an
    # insertion sort mispredicted a branch per direction)
    for a in range(used):
        if found[3, a] > max(found[4, a], inner2):
            continue
        key = found[0, a]
        rank = 0
        for b in range(used):
            counted = found[3, b] <= max(found[4, b], inner2)
            rank += counted & ((found[0, b] < key) | ((found[0, b] == key) & (b < a)))
        keys[rank] = key
        xs[rank] = found[1, a]
        ys[rank] = found[2, a]
    widest = 0.0
    second = 0.0
    middle = 0.0
    for j in range(count):
        following = j + 1 if j + 1 < count else 0
        turn = 4.0 if following == 0 else 0.0  # the last gap wraps around
        if keys[following] + turn - keys[j] < 0.5 * INTERIOR_GAP:
            continue  # narrower than INTERIOR_GAP
        start = math.atan2(ys[j], xs[j])
        gap = math.atan2(ys[following], xs[following]) + (2.0 * math.pi if following == 0 else 0.0) - start
        if gap > widest:
            second = widest
            widest = gap
            middle = start + 0.5 * gap
        elif gap > second:
            second = gap
    return widest, second, middle


# inlined into its loop: a call per point, with its 17 arguments, took a sixth of the pass
@numba.njit(cache=True, inline="always")
def _point_outwards(points, normals, index, rows, frames, sheet_cos, flat_sin2, layers, closing2, i, found, keys,
                    xs, ys, far, out, reach):  # pragma: no cover
    """out[i], reach[i]: row i of `_border_outwards`, with found (5, k), keys, xs, ys (k,) and far
    (2, k) as scratch. The gaps are those of `_widest_gap`: among the neighbours within their
    closing distance, unless those lie along one row (then among all), and, where that leaves
    a border, again among those within CLOSING_SPACINGS times the depth of the nearest row
    inside it (module docstring)."""
    k = index.shape[1]
    p = rows[i]
    used = 0
    folded = 0
    near_bins = np.uint64(0)
    for j in range(k):
        q = index[i, j]
        facing, x, y, antisymmetric, height = _in_frame(points, normals, frames, i, p, q)
        if _far_side(facing, x, y, height, sheet_cos, flat_sin2):
            far[0, folded] = x
            far[1, folded] = y
            folded += 1
            continue
        if q == p or (x == 0.0 and y == 0.0) or 0.5 * abs(antisymmetric) > layers[p]:
            continue
        key = math.copysign(1.0 - x / (abs(x) + abs(y)), y)
        found[0, used] = key
        found[1, used] = x
        found[2, used] = y
        found[3, used] = x * x + y * y
        # p's own closing distance settles most: q's is read only past it
        found[4, used] = closing2[p] if found[3, used] <= closing2[p] else max(closing2[p], closing2[q])
        if found[3, used] <= found[4, used]:
            near_bins |= _key_bit(key)
        used += 1
    if _no_wide_gap(near_bins, BORDER_RUN):
        return  # the near neighbours leave no gap of BORDER_GAP, and every rule below counts them
    inner2 = np.inf if _one_row(near_bins) else 0.0
    widest, second, middle = _widest_gap(found, used, inner2, keys, xs, ys)
    if widest < BORDER_GAP or second > INTERIOR_GAP:
        return
    if inner2 == 0.0:
        # rows farther apart across than along (a coarse tessellation's strips): the next row
        # out lies as far beyond p as the nearest row inside lies behind it
        co = math.cos(middle)
        si = math.sin(middle)
        depth = np.inf
        for a in range(used):
            behind = -(found[1, a] * co + found[2, a] * si)
            if found[3, a] <= found[4, a] and behind >= ROW_DEPTH * math.sqrt(found[3, a]):
                depth = min(depth, behind)
        if depth < np.inf:
            inner2 = (CLOSING_SPACINGS * depth) ** 2
            widest, second, middle = _widest_gap(found, used, inner2, keys, xs, ys)
            if widest < BORDER_GAP or second > INTERIOR_GAP:
                return
    co = math.cos(middle)
    si = math.sin(middle)
    for a in range(3):
        out[i, a] = co * frames[i, 0, a] + si * frames[i, 1, a]
    for f in range(folded):
        reach[i] = max(reach[i], far[0, f] * co + far[1, f] * si)


def _settled(points, normals, index, count, rows, frames, sheet_cos, flat_sin2, layers, closing2):
    """Per point rows[i], True when its neighbours index[i, :count[i]], all among its
    BORDER_CONFIRM nearest, already prove it no border there: their pseudo-angles leave no
    BORDER_RUN + 1 consecutive bins empty (nor then do those of all its BORDER_CONFIRM nearest:
    no gap reaches BORDER_GAP). The neighbours are taken as `_point_outwards` takes them, those
    within their closing distance only: whatever else `_point_outwards` counts adds to them."""
    settled = np.zeros(len(rows), np.bool_)
    over_rows(_settled_rows, len(rows), points, normals, index, count, rows, frames, sheet_cos, flat_sin2, layers,
              closing2, settled, grain=KERNEL_BLOCK)
    return settled


@numba.njit(cache=True, nogil=True)
def _settled_rows(first, stop, points, normals, index, count, rows, frames, sheet_cos, flat_sin2, layers, closing2,
                  settled):  # pragma: no cover - compiled
    """Rows first:stop of `_settled`."""
    for i in range(first, stop):
        p = rows[i]
        bins = np.uint64(0)
        for j in range(count[i]):
            q = index[i, j]
            facing, x, y, antisymmetric, height = _in_frame(points, normals, frames, i, p, q)
            if _far_side(facing, x, y, height, sheet_cos, flat_sin2):
                continue
            if q == p or (x == 0.0 and y == 0.0) or 0.5 * abs(antisymmetric) > layers[p] or \
                    x * x + y * y > max(closing2[p], closing2[q]):
                continue
            bins |= _key_bit(math.copysign(1.0 - x / (abs(x) + abs(y)), y))
        settled[i] = _no_wide_gap(bins, BORDER_RUN)


def _sheet_beyond(nbh: Neighbourhood, normals: np.ndarray, rows: np.ndarray, outwards: np.ndarray,
                  closing2: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Per border point p = rows[i], whether its own sheet goes on ahead of it (module
    docstring): among its BORDER_WIDE nearest, a neighbour q within p's closing distance,
    facing its way (n_p . n_q >= SHEET_COS), on its layer (|d . (n_p + n_q)| / 2, d = q - p,
    within SHEET_SPACINGS spacings) and within 45 degrees of its outward direction outwards[i]."""
    ahead = np.zeros(len(rows), bool)
    for start in range(0, len(rows), BEYOND_BLOCK):
        block = slice(start, start + BEYOND_BLOCK)
        p = rows[block]
        wider = nbh.nearest(p, min(BORDER_WIDE, len(nbh.points)))
        d = nbh.points[wider] - nbh.points[p][:, None, :]
        n_p, n_q = normals[p][:, None, :], normals[wider]
        dist2 = np.sum(d * d, axis=2)
        along = np.sum(d * outwards[block][:, None, :], axis=2)
        separation = 0.5 * np.abs(np.sum(d * (n_p + n_q), axis=2))
        same_sheet = (np.sum(n_p * n_q, axis=2) >= SHEET_COS) & (separation <= SHEET_SPACINGS * spacing[p, None])
        forward = (along > 0) & (along * along >= BEYOND_COS2 * dist2)
        ahead[block] = np.any(same_sheet & forward & (dist2 > 0) & (dist2 <= closing2[p, None]), axis=1)
    return ahead


def mesh_border_outwards(positions: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3): the outward unit tangent of each vertex on a boundary edge of the mesh (faces
    (F, 3) into positions (N, 3)), zero elsewhere (module docstring); `normals` (N, 3) unit,
    the vertices' tangent planes."""
    positions = np.asarray(positions, np.float64)
    outwards = np.zeros((len(positions), 3))
    starts, ends, _ = _boundary_edges(faces)
    if not len(starts):  # closed, as most meshes are: no weld needed
        return outwards
    # a seam's copies and a CAD export's rounded corners lie on such edges: weld those alone,
    # each group to its first vertex
    weld = np.arange(len(positions))
    loose = np.unique(np.concatenate([starts, ends]))
    _, first, group = np.unique(_welded(positions[loose], np.ptp(positions, axis=0)), return_index=True,
                                return_inverse=True)
    weld[loose] = loose[first][group.reshape(-1)]
    starts, ends, thirds = _boundary_edges(weld[faces])
    if not len(starts):
        return outwards
    a, b, c = positions[starts], positions[ends], positions[thirds]
    along = unit(b - a)
    away = a - c
    out = unit(away - np.sum(away * along, axis=1)[:, None] * along)
    summed = np.zeros_like(positions)
    np.add.at(summed, starts, out)
    np.add.at(summed, ends, out)
    summed[_crack_sides(positions, starts, ends)] = 0.0
    outwards = summed[weld]
    outwards -= np.sum(outwards * normals, axis=1)[:, None] * normals
    length = np.linalg.norm(outwards, axis=1)
    # a vertex where two boundary edges turn back on each other (a pinch) has no outward side
    kept = length > 1e-6
    outwards[kept] /= length[kept, None]
    outwards[~kept] = 0.0
    return outwards


def _boundary_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The edges (starts, ends) of the triangles `faces` that only one of them has, and each one's
    corner across from it (thirds); faces with a corner twice are left out."""
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    order, first, uses = edge_runs(faces)
    once = np.sort(order[first[uses == 1]])
    return tuple(np.roll(faces, -shift, axis=1).reshape(-1)[once] for shift in range(3))


def _crack_sides(positions: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """The vertices (indices into positions) of boundary edges (starts, ends) that lie within
    CRACK_SHARE of their boundary edges' mean length from a boundary edge not their own: the
    sides of a crack (module docstring). Edges are taken at CRACK_STEPS + 1 points each."""
    steps = np.linspace(0.0, 1.0, CRACK_STEPS + 1)
    along = positions[starts][:, None] * (1.0 - steps)[None, :, None] + positions[ends][:, None] * steps[None, :, None]
    owner = np.repeat(np.arange(len(starts)), len(steps))
    touching = np.concatenate([starts, ends])  # each edge's two vertices
    vertices, counts = np.unique(touching, return_counts=True)
    lengths = np.zeros(len(positions))
    np.add.at(lengths, touching, np.tile(np.linalg.norm(positions[ends] - positions[starts], axis=1), 2))
    nearest = min(CRACK_NEIGHBOURS, len(owner))
    distance, found = cKDTree(along.reshape(-1, 3)).query(positions[vertices], nearest)
    distance, found = distance.reshape(len(vertices), -1), found.reshape(len(vertices), -1)
    edges = owner[found]
    own = (starts[edges] == vertices[:, None]) | (ends[edges] == vertices[:, None])
    other = np.where(own, np.inf, distance).min(axis=1)
    return vertices[other < CRACK_SHARE * lengths[vertices] / counts]


def _welded(positions: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """(N,) each position's group: those within WELD_TOLERANCE of the diagonal of the box
    `extent` (3,) of each other, chained, are one vertex."""
    tolerance = WELD_TOLERANCE * float(np.linalg.norm(extent))
    pairs = cKDTree(positions).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(positions),) * 2)
    return connected_components(graph, directed=False)[1]


def border_outwards(nbh: Neighbourhood, normals: np.ndarray, index: np.ndarray, progress: bool | None,
                    layers: np.ndarray | None = None,
                    spacing: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3): the outward unit tangent of each point on the border of an open surface, zero
    elsewhere, and (N,) the fold's reach there (module docstring), in the neighbourhood's order.
    Points that look like borders among their nearest neighbours `index` are confirmed among
    their BORDER_CONFIRM nearest: in a sampling much denser on one side (a CAD mesh's vertices
    crowd at its curves), the nearest neighbours alone leave a gap towards the sparse side where
    the surface goes on. `layers`: each point's layer thickness (thickness.py), None for one
    layer everywhere; `spacing`: each point's sampling spacing (spacing.py), None for no
    closing distance."""
    n = len(nbh.points)
    layers = np.full(n, np.inf) if layers is None else np.asarray(layers, np.float64)
    closing2 = np.full(n, np.inf) if spacing is None else (CLOSING_SPACINGS * np.asarray(spacing, np.float64)) ** 2
    closing2[~np.isfinite(closing2)] = np.inf  # no spacing known (no distinct neighbour): no closing distance
    outwards, reach = map_chunks(lambda start, stop: _border_outwards(nbh.points, normals, index[start:stop],
                                                                      np.arange(start, stop),
                                                                      orthonormal_basis(normals[start:stop]),
                                                                      SHEET_COS, FLAT_SIN2, layers, closing2),
                                 n, progress, "borders")
    candidates = np.flatnonzero(any_per_row(outwards != 0.0))
    if len(candidates) and n > index.shape[1]:
        # most candidates are settled by the neighbours certainly among their BORDER_CONFIRM
        # nearest (those of the grid cells around them), without querying those nearest
        frames = orthonormal_basis(normals[candidates])
        sure, count = nbh.within(candidates, BORDER_CONFIRM)
        settled = _settled(nbh.points, normals, sure, count, candidates, frames, SHEET_COS, FLAT_SIN2, layers, closing2)
        outwards[candidates[settled]] = 0.0
        rest = candidates[~settled]
        wide = nbh.nearest(rest, BORDER_CONFIRM)
        # the wider neighbourhood confirms a border; its direction and reach stay the nearest
        # neighbours': farther samples of a curving outline (a shoulder turning into a neck) would
        # tilt the gap's middle, and every splat's clip line with it, into a sawtooth along the outline
        confirmed = _border_outwards(nbh.points, normals, wide, rest, frames[~settled], SHEET_COS, FLAT_SIN2,
                                     layers, closing2)[0].any(axis=1)
        outwards[rest[~confirmed]] = 0.0
        if spacing is not None:
            # a denser sampling's BORDER_CONFIRM nearest may all lie nearer than the closing
            # distance, on one side: the sheet may go on beyond them (module docstring)
            reached = np.sum((nbh.points[wide[:, -1]] - nbh.points[rest]) ** 2, axis=1)
            short = rest[confirmed & (reached < closing2[rest]) & np.isfinite(closing2[rest])]
            beyond = _sheet_beyond(nbh, normals, short, outwards[short], closing2, np.asarray(spacing, np.float64))
            outwards[short[beyond]] = 0.0
    reach[~any_per_row(outwards != 0.0)] = 0.0
    return outwards, reach
