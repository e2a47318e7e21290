"""The compiled kernels of `cells.py`, whose docstring states what they compute: the tangent-plane
Voronoi cell of each point (its covering radius, `cell_radii`, or ellipse, `cell_ellipses`) and each
splat's clip lines at creases and borders (`cell_clip_lines`), one chunk of points per call.

The cells and the clip lines share the crease geometry (`_crease_half_plane`), hence one module:
numba's on-disk cache does not see a change to a function in another file, nor to a constant
(tests/test_preprocess_kernels.py), so the constants the kernels read are defined here.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..threads import over_rows

ELLIPSE_MAX_ASPECT = 4.0       # no needles: major / minor semi-axis at most this
CURVATURE_ANISOTROPY = 0.05    # radians the normals turn more one way than the other: an ellipse follows the curvature
CAP_SIDES = 8                  # a cell starts as this regular polygon through the farthest neighbour (open cells stop)
CLIP_LINES = 2                 # clip lines per splat: an edge, or an edge and a corner
INACTIVE_CLIP = (0.0, 0.0, 1.0)  # 0 u + 0 v <= 1: cuts nothing
PARALLEL_COS = math.cos(math.radians(30.0))  # clip lines closer in direction are one edge
CELL_BLOCK = 1024              # the fewest points per thread's piece of the cell kernels
RIM_MARGIN = 0.5               # a face's clip line at a curved rim: past the rim point by this share of its distance
BEYOND_MARGIN = 0.1            # q this share of its distance on p's side of a concave crease's line: it lies beyond p
LOPSIDED = 2.0                 # a cell reaching this many times farther the other way: a bisector on its short side
CHORD_SLACK = 0.25             # a mesh border's line cuts a splat it crosses within this (splat radii) of its vertex
MESH_BORDER = 2                # on_border's mark of a mesh's boundary vertex (1: a border the neighbours show)
SKIP_MARGIN = 1.0 + 1e-6       # a line this much farther than the farthest vertex (squared) misses the cell


# ---------------------------------------------------------------------------------------------
# the cell of one point: helpers of the kernels below, inlined into them (a call per point would
# cost as much as the work; inline="always" keeps these small functions as fast as one loop body)


@numba.njit(cache=True, inline="always")
def _crease_half_plane(points, p, q, normal_q, frame, on_plane_sin2):  # pragma: no cover - compiled
    """Where splat p meets the tangent plane of its neighbour q across a crease: the half-plane
    a x + b y <= c of p's plane points p + x e1 + y e2, (e1, e2) = frame (orthogonal, of any
    lengths: a cell's unit frame or a splat's semi-axes), that p keeps."""
    side = ga = gb = distance2 = 0.0
    for a in range(3):
        offset = points[p, a] - points[q, a]
        side += offset * normal_q[a]
        ga += frame[0, a] * normal_q[a]
        gb += frame[1, a] * normal_q[a]
        distance2 += offset * offset
    # a plane point lies at g(x, y) = side + x ga + y gb from q's plane; keep sign * g >= 0
    if side * side > on_plane_sin2 * distance2:
        sign = 1.0 if side > 0.0 else -1.0
        return -sign * ga, -sign * gb, sign * side
    # p on the crease line cannot tell its sides apart: the side away from q, from p on (q's
    # plane may pass p on that side, within ON_PLANE_SIN2, and would cut p's centre away)
    qx, qy = _frame_coordinates(points, frame, p, q)
    at_q = side + qx * ga + qy * gb  # g where q projects into p's plane: that side goes
    sign = -1.0 if at_q > 0.0 else 1.0
    return -sign * ga, -sign * gb, max(sign * side, 0.0)


@numba.njit(cache=True, inline="always")
def _frame_coordinates(points, frame, p, q):  # pragma: no cover - compiled
    """(x, y) of q projected into p's plane p + x e1 + y e2, (e1, e2) = frame orthogonal, of
    any lengths: its offsets along them over their lengths squared (0 along a degenerate axis)."""
    x = y = e1_length2 = e2_length2 = 0.0
    for a in range(3):
        offset = points[q, a] - points[p, a]
        x += offset * frame[0, a]
        y += offset * frame[1, a]
        e1_length2 += frame[0, a] * frame[0, a]
        e2_length2 += frame[1, a] * frame[1, a]
    return x / e1_length2 if e1_length2 > 0.0 else 0.0, y / e2_length2 if e2_length2 > 0.0 else 0.0


@numba.njit(cache=True, inline="always")
def _cell_bounds(points, normals, index, frames, i, p, features, sheet_cos, layers, lines, creases,
                 bounding):  # pragma: no cover - compiled
    """The sheet and crease rules: the half-planes a x + b y <= c of p's tangent frame
    (t, s) = frames[i] that bound its cell among its neighbours index[i], in the order they cut
    it; neighbours on another layer than p's (separation beyond layers[p], thickness.py) cut
    nothing. (Rows, not row views: a view per point costs as much as a tenth of the kernel.)

    Fills the scratch lines (k, 3), creases (k, 3) and bounding (k,) and returns (bisectors,
    count, reach): lines[:bisectors] are the bisectors of the bounding neighbours
    `bounding[:bisectors]` ((a, b) = their offset), lines[bisectors:count] the creases and the
    turns of steep neighbours; reach is the farthest neighbour's distance."""
    k = index.shape[1]
    bisectors = 0
    crease_count = 0
    reach2 = 0.0
    for j in range(k):
        q = index[i, j]
        d0 = points[q, 0] - points[p, 0]
        d1 = points[q, 1] - points[p, 1]
        d2 = points[q, 2] - points[p, 2]
        x = d0 * frames[i, 0, 0] + d1 * frames[i, 0, 1] + d2 * frames[i, 0, 2]
        y = d0 * frames[i, 1, 0] + d1 * frames[i, 1, 1] + d2 * frames[i, 1, 2]
        z = d0 * normals[p, 0] + d1 * normals[p, 1] + d2 * normals[p, 2]
        planar = x * x + y * y
        reach2 = max(reach2, planar + z * z)
        facing = 0.0
        for a in range(3):
            facing += normals[q, a] * normals[p, a]
        # q's separation from p's layer (thickness.py's |d_pq - d_qp| / 2), against its thickness
        separation = 0.5 * abs(z + d0 * normals[q, 0] + d1 * normals[q, 1] + d2 * normals[q, 2])
        if features.crease[q] or facing < sheet_cos or separation > layers[p]:
            continue
        crease = facing < features.sharp_cos and features.flat[q]
        # or the surface turning sharply away, which only oriented normals can tell (unoriented,
        # sheet_cos is -2): the cell ends at q's plane, or half-way to q
        turn = not crease and sheet_cos > -2.0 and z < 0 and z * z > planar
        if crease or turn:
            ca, cb, cc = _crease_half_plane(points, p, q, normals[q], frames[i], features.on_plane_sin2)
            if crease and z > 0.0 and x * ca + y * cb <= cc - BEYOND_MARGIN * math.sqrt(planar * (ca * ca + cb * cb)):
                continue  # a concave crease beyond p: none (cells.py)
            if ca * ca + cb * cb > 1e-12:  # not parallel planes (the far side of a sheet)
                creases[crease_count, 0] = ca
                creases[crease_count, 1] = cb
                creases[crease_count, 2] = max(cc, 0.5 * (x * ca + y * cb)) if turn else cc
                crease_count += 1
            continue
        if planar > 0 and z * z <= planar:  # skip duplicates and the far side of thin sheets
            lines[bisectors, 0] = x
            lines[bisectors, 1] = y
            lines[bisectors, 2] = 0.5 * planar  # nearer to p than to q: (x, y) . X <= |d|^2 / 2
            bounding[bisectors] = q
            bisectors += 1
    for c in range(crease_count):  # the creases cut after every bisector
        for a in range(3):
            lines[bisectors + c, a] = creases[c, a]
    return bisectors, bisectors + crease_count, math.sqrt(reach2)  # sqrt once: it is monotonic


@numba.njit(cache=True, inline="always")
def _clip(polygon, count, a, b, c, out):  # pragma: no cover - compiled
    """Clip the convex polygon[:count] to the half-plane a x + b y <= c into out (room for count + 2
    rows: one written past the last kept); returns its number of vertices. Each vertex and crossing
    is written, kept by counting it (no branch: which vertices a line cuts off is unpredictable)."""
    kept = 0
    first = a * polygon[0, 0] + b * polygon[0, 1] - c
    si = first
    for i in range(count):
        j = i + 1 if i + 1 < count else 0
        sj = a * polygon[j, 0] + b * polygon[j, 1] - c if j else first
        out[kept, 0] = polygon[i, 0]
        out[kept, 1] = polygon[i, 1]
        kept += si <= 0
        t = si / (si - sj) if si != sj else 0.0  # kept only where the signs differ
        out[kept, 0] = polygon[i, 0] + t * (polygon[j, 0] - polygon[i, 0])
        out[kept, 1] = polygon[i, 1] + t * (polygon[j, 1] - polygon[i, 1])
        kept += (si <= 0) != (sj <= 0)
        si = sj
    return kept


@numba.njit(cache=True, inline="always")
def _cell_polygon(lines, count, reach, polygon, spare):  # pragma: no cover - compiled
    """The cell: the regular CAP_SIDES-gon inscribed in the circle of radius `reach`, clipped to
    lines[:count] in order, in the scratch polygon and spare (CAP_SIDES + k + 1, 2: a clip adds at
    most one vertex). Returns (the one holding it, its number of vertices). A line no vertex lies
    beyond is skipped before the clip, which costs several times the test (most bisectors of the
    farther neighbours miss the cell); first, unvisited, one farther than the farthest vertex
    (c^2 >= r^2 (a^2 + b^2), SKIP_MARGIN for roundings)."""
    for c in range(CAP_SIDES):
        angle = 2.0 * math.pi * c / CAP_SIDES
        polygon[c, 0] = reach * math.cos(angle)
        polygon[c, 1] = reach * math.sin(angle)
    vertices = CAP_SIDES
    far2 = reach * reach  # the farthest vertex's squared distance
    for j in range(count):
        a, b, c = lines[j, 0], lines[j, 1], lines[j, 2]
        if c > 0.0 and c * c >= far2 * (a * a + b * b) * SKIP_MARGIN:
            continue
        beyond = -np.inf
        for v in range(vertices):
            beyond = max(beyond, a * polygon[v, 0] + b * polygon[v, 1] - c)
        if beyond <= 0.0:
            continue
        vertices = _clip(polygon, vertices, a, b, c, spare)
        polygon, spare = spare, polygon
        far2 = 0.0
        for v in range(vertices):
            far2 = max(far2, polygon[v, 0] * polygon[v, 0] + polygon[v, 1] * polygon[v, 1])
    return polygon, vertices


@numba.njit(cache=True, inline="always")
def _covering_radius(polygon, vertices):  # pragma: no cover - compiled
    """Distance from the centre to the polygon's farthest vertex."""
    far = 0.0
    for c in range(vertices):
        far = max(far, polygon[c, 0] * polygon[c, 0] + polygon[c, 1] * polygon[c, 1])
    return math.sqrt(far)


@numba.njit(cache=True, inline="always")
def _spread_direction(lines, bisectors):  # pragma: no cover - compiled
    """The angle in the tangent frame of the principal direction of the bounding neighbours'
    offsets lines[:bisectors, :2]."""
    mx = my = 0.0
    for j in range(bisectors):
        mx += lines[j, 0]
        my += lines[j, 1]
    mx /= max(bisectors, 1)
    my /= max(bisectors, 1)
    sxx = syy = sxy = 0.0
    for j in range(bisectors):
        sxx += (lines[j, 0] - mx) ** 2
        syy += (lines[j, 1] - my) ** 2
        sxy += (lines[j, 0] - mx) * (lines[j, 1] - my)
    return 0.5 * math.atan2(2.0 * sxy, sxx - syy)


@numba.njit(cache=True, inline="always")
def _curvature_direction(lines, bisectors, bounding, normals, frames, i, p):  # pragma: no cover - compiled
    """The angle in p's tangent frame (t, s) = frames[i] of the principal curvature direction of
    largest curvature, and the difference of the principal curvatures (per unit length): from
    the shape operator S, tilt = S offset, fitted by least squares to the bounding neighbours'
    normals (tilt: the tangential part of n_q / (n_q . n_p), as in normal_field.py) at their
    offsets lines[:bisectors, :2]."""
    dxx = dxy = dyy = 0.0
    txx = txy = tyx = tyy = 0.0
    for j in range(bisectors):
        q = bounding[j]
        along = tx = ty = 0.0
        for a in range(3):
            along += normals[q, a] * normals[p, a]
            tx += normals[q, a] * frames[i, 0, a]
            ty += normals[q, a] * frames[i, 1, a]
        if abs(along) < 0.5:  # across a crease, as normal_field.ACROSS_COS
            continue
        tx, ty = tx / along, ty / along
        x, y = lines[j, 0], lines[j, 1]
        dxx, dxy, dyy = dxx + x * x, dxy + x * y, dyy + y * y
        txx, txy = txx + tx * x, txy + tx * y
        tyx, tyy = tyx + ty * x, tyy + ty * y
    det = dxx * dyy - dxy * dxy
    if det <= 1e-30:
        return 0.0, 0.0
    s00 = (txx * dyy - txy * dxy) / det
    s01 = (txy * dxx - txx * dxy) / det
    s10 = (tyx * dyy - tyy * dxy) / det
    s11 = (tyy * dxx - tyx * dxy) / det
    shear = 0.5 * (s01 + s10)  # S is symmetric in theory: its symmetric part
    return 0.5 * math.atan2(2.0 * shear, s00 - s11), math.sqrt((s00 - s11) ** 2 + 4.0 * shear * shear)


@numba.njit(cache=True, inline="always")
def _ellipse_scale2(polygon, vertices, tau):  # pragma: no cover - compiled
    """Squared scale by which the ellipse with semi-axes (e^(tau/2), e^(-tau/2)) must grow to
    contain the polygon."""
    wx = math.exp(-tau)
    wy = math.exp(tau)
    scale2 = 0.0
    for c in range(vertices):
        scale2 = max(scale2, polygon[c, 0] * polygon[c, 0] * wx + polygon[c, 1] * polygon[c, 1] * wy)
    return scale2


@numba.njit(cache=True, inline="always")
def _covering_ellipse(polygon, vertices, co, si):  # pragma: no cover - compiled
    """Semi-axes (a, b) along (co, si) and its perpendicular of the smallest ellipse with aspect
    at most ELLIPSE_MAX_ASPECT that contains the polygon (rotated into those axes in place)."""
    for c in range(vertices):
        x0 = polygon[c, 0] * co + polygon[c, 1] * si
        polygon[c, 1] = -polygon[c, 0] * si + polygon[c, 1] * co
        polygon[c, 0] = x0
    lo = -math.log(ELLIPSE_MAX_ASPECT)
    hi = math.log(ELLIPSE_MAX_ASPECT)
    for _ in range(24):  # brackets the optimum to 1e-5 of the log-aspect range
        t1 = hi - 0.618033988749895 * (hi - lo)
        t2 = lo + 0.618033988749895 * (hi - lo)
        if _ellipse_scale2(polygon, vertices, t1) <= _ellipse_scale2(polygon, vertices, t2):
            hi = t2
        else:
            lo = t1
    tau = 0.5 * (lo + hi)
    scale = math.sqrt(_ellipse_scale2(polygon, vertices, tau))
    return math.exp(0.5 * tau) * scale, math.exp(-0.5 * tau) * scale


# ---------------------------------------------------------------------------------------------
# every point: the kernels of one chunk, points start + i


def cell_radii(points, normals, index, start, frames, features, sheet_cos, layers):
    """The covering radius of each point's cell (0 where all its neighbours coincide with it)."""
    radius = np.zeros(len(index))
    over_rows(_radii_rows, len(index), points, normals, index, start, frames, features, sheet_cos, layers, radius,
              grain=CELL_BLOCK)
    return radius


@numba.njit(cache=True, nogil=True)
def _radii_rows(first, stop, points, normals, index, start, frames, features, sheet_cos, layers,
                radius):  # pragma: no cover - compiled
    """Rows first:stop of `cell_radii`."""
    k = index.shape[1]
    # one set of scratch buffers per call: five allocations per point cost half the kernel
    lines, creases, bounding = np.empty((k, 3)), np.empty((k, 3)), np.empty(k, np.int64)
    polygon, spare = np.empty((CAP_SIDES + k + 1, 2)), np.empty((CAP_SIDES + k + 1, 2))
    for i in range(first, stop):
        _, count, reach = _cell_bounds(points, normals, index, frames, i, start + i, features, sheet_cos,
                                       layers, lines, creases, bounding)
        if reach == 0.0:
            continue
        cell, vertices = _cell_polygon(lines, count, reach, polygon, spare)
        radius[i] = _covering_radius(cell, vertices)


def cell_ellipses(points, normals, index, start, frames, features, sheet_cos, layers, reach_bound):
    """The covering radius of each point's cell, the semi-axes (m, 2) and direction
    (m, 2: cos, sin in the frame) of its covering ellipse (zero semi-axes for degenerate cells),
    fitted to the part of the cell within reach_bound (N,) of the point; its short side (m, 3, `_short_side`)."""
    m = len(index)
    radius = np.zeros(m)
    semi = np.zeros((m, 2))
    direction = np.zeros((m, 2))
    direction[:, 0] = 1.0
    short = np.zeros((m, 3))
    over_rows(_ellipse_rows, m, points, normals, index, start, frames, features, sheet_cos, layers, reach_bound,
              radius, semi, direction, short, grain=CELL_BLOCK)
    return radius, semi, direction, short


@numba.njit(cache=True, inline="always")
def _clip_to_disc(polygon, spare, vertices, reach):  # pragma: no cover - compiled
    """The polygon clipped to the regular CAP_SIDES-gon circumscribed about the circle of radius
    `reach` (none of the disc cut off); returns (the buffer holding it, its number of vertices)."""
    for c in range(CAP_SIDES):
        angle = 2.0 * math.pi * c / CAP_SIDES
        vertices = _clip(polygon, vertices, math.cos(angle), math.sin(angle), reach, spare)
        polygon, spare = spare, polygon
    return polygon, vertices


@numba.njit(cache=True, inline="always")
def _short_side(polygon, vertices, lines, bisectors):  # pragma: no cover - compiled
    """The cell polygon's short side: the bisector a x + b y <= c (of lines[:bisectors], (a, b)
    made unit) the other way from which the polygon reaches farthest in proportion to c, more
    than LOPSIDED c; c = 0 where none does (a bisector missing the cell has a larger c)."""
    best_a, best_b, best_c, best_ratio = 0.0, 0.0, 0.0, LOPSIDED
    for j in range(bisectors):
        length = math.sqrt(lines[j, 0] * lines[j, 0] + lines[j, 1] * lines[j, 1])
        a, b, c = lines[j, 0] / length, lines[j, 1] / length, lines[j, 2] / length
        opposite = 0.0
        for v in range(vertices):
            opposite = max(opposite, -(a * polygon[v, 0] + b * polygon[v, 1]))
        if opposite > best_ratio * c:
            best_a, best_b, best_c, best_ratio = a, b, c, opposite / c
    return best_a, best_b, best_c


@numba.njit(cache=True, nogil=True)
def _ellipse_rows(first, stop, points, normals, index, start, frames, features, sheet_cos, layers, reach_bound,
                  radius, semi, direction, short):  # pragma: no cover - compiled
    """Rows first:stop of `cell_ellipses`."""
    k = index.shape[1]
    lines, creases, bounding = np.empty((k, 3)), np.empty((k, 3)), np.empty(k, np.int64)
    # each clip adds at most one vertex: k lines, then the disc's CAP_SIDES
    rows = 2 * CAP_SIDES + k + 1
    polygon, spare, extra = np.empty((rows, 2)), np.empty((rows, 2)), np.empty((rows, 2))
    for i in range(first, stop):
        p = start + i
        bisectors, count, reach = _cell_bounds(points, normals, index, frames, i, p, features, sheet_cos,
                                               layers, lines, creases, bounding)
        if reach == 0.0:
            continue
        cell, vertices = _cell_polygon(lines, count, reach, polygon, spare)
        radius[i] = _covering_radius(cell, vertices)
        if radius[i] > reach_bound[p]:
            cell, vertices = _clip_to_disc(cell, extra, vertices, reach_bound[p])
        if vertices < 3:
            continue
        # Splats "aligned along the curvature" (survey 2.1.4), so that the normal field's two
        # slopes (eq. 8) describe the surface: the principal curvature directions, wherever the
        # normals turn more one way than the other across the cell.
        theta = _spread_direction(lines, bisectors)
        curvature_theta, anisotropy = _curvature_direction(lines, bisectors, bounding, normals, frames, i, p)
        if anisotropy * reach > CURVATURE_ANISOTROPY:
            theta = curvature_theta
        co = math.cos(theta)
        si = math.sin(theta)
        short[i, 0], short[i, 1], short[i, 2] = _short_side(cell, vertices, lines, bisectors)
        semi[i, 0], semi[i, 1] = _covering_ellipse(cell, vertices, co, si)
        direction[i, 0] = co
        direction[i, 1] = si


@numba.njit(cache=True, inline="always")
def _append_unit_line(candidates, count, a, b, c, length):  # pragma: no cover - compiled
    """Append a u + b v <= c, divided by length = |(a, b)|, as row `count` of candidates; the new count."""
    candidates[count, 0] = a / length
    candidates[count, 1] = b / length
    candidates[count, 2] = c / length
    return count + 1


@numba.njit(cache=True, inline="always")
def _in_plane(points, normals, p, q, flat_sin2):  # pragma: no cover - compiled
    """Whether neighbour q lies in p's tangent plane: ((q - p) . n_p)^2 <= flat_sin2 |q - p|^2."""
    height = distance2 = 0.0
    for a in range(3):
        offset = points[q, a] - points[p, a]
        height += offset * normals[p, a]
        distance2 += offset * offset
    return height * height <= flat_sin2 * distance2


@numba.njit(cache=True, inline="always")
def _crease_candidates(points, normals, index, axes, i, p, features, layers, candidates):  # pragma: no cover - compiled
    """The crease half-planes of splat p that cut it, among its neighbours index[i], in its axes
    (u, v) = axes[i], as unit (a, b, c) rows of candidates, a rim's moved out by RIM_MARGIN of
    the rim point's distance, a steep neighbour's turn no nearer than half-way to it (cells.py);
    returns their number."""
    count = 0
    for j in range(index.shape[1]):
        q = index[i, j]
        if features.crease[q]:
            continue
        facing = height = distance2 = 0.0
        across = 0.0  # (q - p) . n_q
        for a in range(3):
            offset = points[q, a] - points[p, a]
            facing += normals[q, a] * normals[p, a]
            height += offset * normals[p, a]
            across += offset * normals[q, a]
            distance2 += offset * offset
        # the surface turning sharply away below p (_cell_bounds' turn, on p's layer), where p
        # lies below q's plane too: a convex edge or a thin part's rim, not another part of the
        # surface below p (a tail under a rump)
        turn = (not (facing < features.sharp_cos and features.flat[q]) and facing >= features.sheet_cos
                and height < 0.0 and 2.0 * height * height > distance2 and across > 0.0
                and 0.5 * abs(height + across) <= layers[p])
        if turn:
            la, lb, lc = _crease_half_plane(points, p, q, normals[q], axes[i], features.on_plane_sin2)
            length = math.sqrt(la * la + lb * lb)
            qu, qv = _frame_coordinates(points, axes[i], p, q)
            lc = max(lc, 0.5 * (qu * la + qv * lb))
            if length >= 1e-6 and lc < length:
                count = _append_unit_line(candidates, count, la, lb, lc, length)
            continue
        if facing >= features.sharp_cos:
            continue
        # a curved neighbour in p's face's plane lies on the rim of that face: a bolt hole's, a
        # rounded outer edge's, where no second face makes crease points
        rim = not features.flat[q]
        if rim and not (features.flat[p] and _in_plane(points, normals, p, q, features.flat_sin2)):
            continue
        if facing < features.sheet_cos and _in_plane(points, normals, p, q, features.flat_sin2):
            continue  # in p's face: the same surface seen from behind
        la, lb, lc = _crease_half_plane(points, p, q, normals[q], axes[i], features.on_plane_sin2)
        length = math.sqrt(la * la + lb * lb)
        qu, qv = _frame_coordinates(points, axes[i], p, q)
        if not rim and height > 0.0 and la * qu + lb * qv <= lc - BEYOND_MARGIN * math.hypot(qu, qv) * length:
            continue  # a concave crease beyond p: none (cells.py)
        if rim:
            lc += RIM_MARGIN * math.hypot(qu, qv) * length
        if length < 1e-6 or lc >= length:  # parallel planes, or the line misses the splat
            continue
        count = _append_unit_line(candidates, count, la, lb, lc, length)
    return count


@numba.njit(cache=True, inline="always")
def _goes_on_past(points, normals, index, i, p, q, outwards, on_border, reach, sharp_cos):  # pragma: no cover
    """Whether p's side goes on past the border line of q, a neighbour facing away: a neighbour
    facing p's way (within SHARP_ANGLE), not on a border itself, lies beyond it (cells.py)."""
    for j in range(index.shape[1]):
        r = index[i, j]
        beyond, facing = -reach[q], 0.0
        for a in range(3):
            beyond += (points[r, a] - points[q, a]) * outwards[q, a]
            facing += normals[r, a] * normals[p, a]
        if beyond > 0.0 and facing >= sharp_cos and not on_border[r]:
            return True
    return False


@numba.njit(cache=True, inline="always")
def _border_candidates(points, normals, index, axes, i, p, features, outwards, on_border, reach, margin,
                       candidates, count):  # pragma: no cover - compiled
    """Append the border half-planes that cut splat p as unit (a, b, c) rows of candidates in its
    axes (u, v) = axes[i]: for each neighbour q on a border (its own included; not one facing away
    where p's side goes on past its line, `_goes_on_past`), the side of the line across w_q that
    holds the surface, (p + u u_axis + v v_axis - q) . w_q <= reach[q], moved out by `margin` in
    (u, v); returns the new count."""
    uu = axes[i, 0, 0] ** 2 + axes[i, 0, 1] ** 2 + axes[i, 0, 2] ** 2  # the axes' squared lengths (mesh borders)
    vv = axes[i, 1, 0] ** 2 + axes[i, 1, 1] ** 2 + axes[i, 1, 2] ** 2
    for j in range(index.shape[1]):
        q = index[i, j]
        if not on_border[q]:  # no outward direction, no line: most neighbours (a seventh of the pass)
            continue
        facing = normals[q, 0] * normals[p, 0] + normals[q, 1] * normals[p, 1] + normals[q, 2] * normals[p, 2]
        if facing < features.sheet_cos and _goes_on_past(points, normals, index, i, p, q, outwards, on_border, reach,
                                                         features.sharp_cos):
            continue
        wa = wb = qu = qv = 0.0
        inside = reach[q]
        for a in range(3):
            d = points[q, a] - points[p, a]
            wa += axes[i, 0, a] * outwards[q, a]
            wb += axes[i, 1, a] * outwards[q, a]
            inside += d * outwards[q, a]
            qu, qv = qu + d * axes[i, 0, a], qv + d * axes[i, 1, a]
        length = math.sqrt(wa * wa + wb * wb)
        moved = inside + margin * length
        # no border, a border seen edge-on, p beyond it (a concave border), or a line missing the splat
        if length < 1e-6 or inside < 0.0 or moved >= length:
            continue
        # a mesh's border ends with its edges: q farther along its line than its half chord across the splat
        if on_border[q] == MESH_BORDER and abs(qv * wa / vv - qu * wb / uu) > (
                math.sqrt(1.0 - (moved / length) ** 2) + CHORD_SLACK) * length:
            continue
        count = _append_unit_line(candidates, count, wa, wb, moved, length)
    return count


@numba.njit(cache=True, inline="always")
def _nearest_creases(candidates, count, lines, i):  # pragma: no cover - compiled
    """Fill lines[i] (CLIP_LINES, 3) with the most restrictive candidates (smallest c), each
    more than acos(PARALLEL_COS) in direction from those chosen before."""
    used = 0
    while used < CLIP_LINES:
        best = -1
        for c in range(count):
            parallel = False
            for other in range(used):
                if candidates[c, 0] * lines[i, other, 0] + candidates[c, 1] * lines[i, other, 1] > PARALLEL_COS:
                    parallel = True
            if not parallel and (best < 0 or candidates[c, 2] < candidates[best, 2]):
                best = c
        if best < 0:
            return
        for a in range(3):
            lines[i, used, a] = candidates[best, a]
        used += 1


@numba.njit(cache=True, nogil=True)
def _cutting_neighbours(gathered, k, nx, ny, nz, sharp_cos):  # pragma: no cover - compiled
    """How many of p's k neighbours (offsets gathered[0:3], normals gathered[3:6], border marks
    gathered[6]; p's normal n) may make one of its clip lines: a crease's or a rim's (normals
    more than SHARP_ANGLE apart), a turn's (a neighbour more than 45 degrees below p's plane,
    with p below its plane), a border's (`_crease_candidates`, `_border_candidates`). Branch-free
    over contiguous rows (SIMD): the points none can cut (most) skip those loops' branches (a
    1.4M-point build partition, one core: `cells.clip_lines` 0.59 -> 0.17-0.26 s)."""
    count = 0
    for j in range(k):
        dx, dy, dz = gathered[0, j], gathered[1, j], gathered[2, j]
        qx, qy, qz = gathered[3, j], gathered[4, j], gathered[5, j]
        facing = qx * nx + qy * ny + qz * nz
        height = dx * nx + dy * ny + dz * nz
        across = dx * qx + dy * qy + dz * qz
        distance2 = dx * dx + dy * dy + dz * dz
        turn = (height < 0.0) & (2.0 * height * height > distance2) & (across > 0.0)
        count += (facing < sharp_cos) | turn | (gathered[6, j] != 0.0)
    return count


def cell_clip_lines(points, normals, index, start, axes, features, layers, outwards, on_border, reach, margin):
    """CLIP_LINES clip lines (a, b, c) per splat, in its local coordinates (u, v) (1 on the rim):
    the crease and turn half-planes that end its cell (neighbours of another of the `layers`
    aside) and the border lines of its neighbours (`outwards`, nonzero where `on_border`).
    A dropped splat keeps nothing (u <= -2, -u <= -2)."""
    lines = np.empty((len(index), CLIP_LINES, 3), np.float32)
    over_rows(_clip_rows, len(index), points, normals, index, start, axes, features, layers, outwards, on_border,
              reach, margin, lines, grain=CELL_BLOCK)
    return lines


@numba.njit(cache=True, nogil=True)
def _clip_rows(first, stop, points, normals, index, start, axes, features, layers, outwards, on_border, reach, margin,
               lines):  # pragma: no cover - compiled
    """Rows first:stop of `cell_clip_lines`."""
    k = index.shape[1]
    candidates = np.empty((2 * k, 3))  # one per call: an allocation per point costs as much
    gathered = np.empty((7, k))  # a point's neighbours' offsets, normals and border marks, in rows
    for i in range(first, stop):
        p = start + i
        dropped = features.crease[p]
        for line in range(CLIP_LINES):
            lines[i, line, 0] = 1.0 - 2.0 * line if dropped else INACTIVE_CLIP[0]
            lines[i, line, 1] = 0.0 if dropped else INACTIVE_CLIP[1]
            lines[i, line, 2] = -2.0 if dropped else INACTIVE_CLIP[2]
        if not dropped:
            for j in range(k):
                q = index[i, j]
                for a in range(3):
                    gathered[a, j] = points[q, a] - points[p, a]
                    gathered[3 + a, j] = normals[q, a]
                gathered[6, j] = 1.0 if on_border[q] else 0.0
            if _cutting_neighbours(gathered, k, normals[p, 0], normals[p, 1], normals[p, 2], features.sharp_cos) == 0:
                continue  # no neighbour can make a clip line (most points)
            count = _crease_candidates(points, normals, index, axes, i, p, features, layers, candidates)
            count = _border_candidates(points, normals, index, axes, i, p, features, outwards, on_border, reach,
                                       margin, candidates, count)
            _nearest_creases(candidates, count, lines, i)
