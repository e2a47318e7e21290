"""What surface splatting assumes of its points: normals, splat sizes, tangent frames, ellipses
and Phong splatting's normal fields, estimated from raw positions.

Normals (`estimate_normals`)
    PCA over the k nearest neighbours: the eigenvector of the smallest eigenvalue of the
    neighbourhood covariance. Orientation: towards a viewpoint when the sensor position is
    known; otherwise consistently by propagation (Hoppe, DeRose, Duchamp, McDonald & Stuetzle
    1992, "Surface reconstruction from unorganized points"): a minimum spanning tree of the
    kNN graph (ORIENT_NEIGHBOURS per point; Hoppe's Riemannian graph adds the Euclidean MST
    to connect everything, here each connected component is oriented on its own) with edge
    weights 1 - |n_i . n_j| (so flips propagate across nearly parallel normals first), walked
    breadth-first, every node taking the sign that agrees with its
    parent. Each connected component then faces outward as a whole: it is flipped when the
    flux sum_i n_i . (p_i - centroid) is negative, which by the divergence theorem (the flux
    of p - c through a closed surface is 3 x its volume) is the outward choice for closed
    scans, and does not hinge on one seed point's normal.

    `ambiguous` counts the points whose orientation is a guess:
      * degenerate neighbourhoods without a tangent plane: the two smallest covariance
        eigenvalues within a factor 1/DEGENERATE_RATIO of each other (a line, a blob, the
        crossing of two surfaces), or a neighbourhood that is a line or a single point;
      * sign decisions taken against a nearly perpendicular reference, |cos| < AMBIGUOUS_COS:
        the tree parent's normal, or the direction to the viewpoint;
      * every point of a component without an outside: |flux| < AMBIGUOUS_COS x
        sum_i |n_i . (p_i - c)| (a flat patch, a single point), whose sign is arbitrary.

Radii (`estimate_radii`): each splat covers its own Voronoi cell.
    The union of disks covers a surface exactly when every sample's disk contains the part of
    the surface nearer to it than to any other sample: its Voronoi cell. So the radius is the
    distance from the point to the farthest vertex of its cell, computed in its tangent plane
    among its k nearest neighbours (the half-planes nearer to it than to each neighbour,
    clipped to the disk of the k-th neighbour's distance), times RADIUS_MARGIN for curvature
    and normal noise. Unlike a fixed multiple of a neighbour distance, this adapts to the
    anisotropic spacing of LiDAR scan lines (a cell is long across the lines, short along
    them) and to jittered sampling, without inflating the splats of regular regions.
    Neighbours more than 45 degrees off the tangent plane (the far side of a thin sheet) do
    not cut the cell. A point whose radius exceeds ISOLATED_FACTOR x the median radius of its
    neighbours (an outlier) is capped there so it does not become a blob.

Tangent frames (`tangent_frames`): the branch-free orthonormal basis of Duff, Burgess,
    Christensen, Hery, Kensler, Liani & Villemin 2017, "Building an orthonormal basis,
    revisited", scaled by the radius; (u, v, n) is right-handed.

Ellipses (`fit_ellipses`, for Phong splatting, Botsch, Spernat & Kobbelt 2004):
    axis directions are the principal curvature directions ("aligned along the curvature",
    fitted to the neighbours' normals) where the normals turn more one way than the other
    (by CURVATURE_ANISOTROPY across the cell), else the principal directions of the
    neighbours projected into the tangent plane; the semi-axes are those of the
    smallest-area ellipse with these directions that contains the point's Voronoi cell
    (aspect at most ELLIPSE_MAX_ASPECT), times RADIUS_MARGIN and the same outlier cap: the
    covering rule of the radii, never with more area than the disk (the disk is one of the
    candidates). u is the major axis.

Normal fields (`fit_normal_field`, Botsch et al. 2004; survey eq. 8):
    N_j(u, v) = n_j + u alpha_j û_j + v beta_j v̂_j, where û_j, v̂_j are the UNIT axis
    directions and (u, v) = (u_j . (q - c_j) / |u_j|^2, v_j . (q - c_j) / |v_j|^2) are local
    coordinates that reach 1 on the ellipse's rim, so alpha and beta are dimensionless (the
    tangent of the normal's tilt at the rim). Fitted by least squares over the neighbours'
    normals, each slope a 1-D problem with a closed form.

Sharp features (`prepare(sharp_features=True)`, the default when radii are estimated):
    circular or elliptical splats are smooth; at the crease of a piecewise smooth shape (a CAD
    part, a building) every splat near the edge sticks out past it, and the silhouette grows a
    scalloped rim. Following the clipped splats of Zwicker, Pauly, Knoll & Gross 2002
    ("Pointshop 3D") and Pauly, Keiser, Kobbelt & Gross 2003 ("Shape modeling with
    point-sampled geometry"), each splat carries up to CLIP_LINES clip lines a u + b v <= c in
    its local coordinates (u, v) (1 on the rim), attributes["clip_lines"] (N, CLIP_LINES, 3):
      * flat points: those whose neighbours with normals within SHARP_ANGLE lie within
        FLAT_SIN2 of their tangent plane (faces; not coarsely sampled curved surfaces, whose
        neighbours' planes would facet them);
      * two flat neighbours p, q with normals more than SHARP_ANGLE apart lie across a crease:
        the crease is the line where their tangent planes meet. p's Voronoi cell ends there
        instead of at the bisector (so its radius reaches the edge and no further), and its
        clip lines are the nearest such lines (in two directions). p keeps its centre's side
        of q's plane, or, if its centre lies in that plane, the side away from q;
      * crease points, which lie in the planes of two flat neighbours more than SHARP_ANGLE
        apart (on the edge itself, their normals averaged over both faces), stick out of one
        face or the other whatever their orientation: they are dropped (clip lines that keep
        nothing) and ignored by every cell, so the faces' cells reach the crease without them.
    Every splat method evaluates the lines per fragment (the GPU methods in the splat's plane,
    EWA as pixel half-planes through its Jacobian). Smooth surfaces get no lines.

Memory stays bounded: the neighbour lists (N x k indices) and the propagation graph are the
only O(N k) arrays; all per-neighbour work runs in numba kernels (parallel over points) or in
chunks of CHUNK points. Every function takes and returns arrays in the input's order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from tqdm import tqdm

from .cloud import PointCloud

CHUNK = 1 << 18                # points per step of the chunked passes (bounds temporary memory)
PROGRESS_MIN_POINTS = 1_000_000  # automatic progress bars above this many points
AMBIGUOUS_COS = 0.1            # |cos| below which a sign decision is a guess
DEGENERATE_RATIO = 0.5         # lambda_0 > this x lambda_1: no dominant normal direction
ORIENT_NEIGHBOURS = 8          # edges per point of the propagation graph: half the MST time of 15,
                               # the same orientations on the bunny
RADIUS_NEIGHBOURS = 16         # neighbours bounding a Voronoi cell: enough to reach the next scan
                               # line when lines are up to ~8 x farther apart than points on a line
RADIUS_MARGIN = 1.2            # covering radius x this: curvature, normal noise, and overlap for
                               # the Gaussian blending (coverage 99.98% at 1.0, 99.998% at 1.2)
ISOLATED_FACTOR = 2.0          # a radius at most this x the median of its neighbours' radii
ELLIPSE_MAX_ASPECT = 4.0       # no needles: major / minor semi-axis at most this
CURVATURE_ANISOTROPY = 0.05    # radians by which the normals turn more one way than the other
                               # across a cell, above which an ellipse follows the curvature
FIELD_NEIGHBOURS = 16          # neighbours whose normals fit a splat's normal field
SHARP_ANGLE = 45.0             # degrees between neighbouring normals that make a sharp feature:
                               # a 90 degree crease tilts its averaged vertex normals 45 degrees
SHEET_COS = -0.5               # neighbours' normals more than 120 degrees apart: two sides of a sheet
CLIP_LINES = 2                 # clip lines per splat: an edge, or an edge and a corner
INACTIVE_CLIP = (0.0, 0.0, 1.0)  # 0 u + 0 v <= 1: cuts nothing
ON_PLANE_SIN2 = math.sin(math.radians(3.0)) ** 2  # a neighbour's plane through the point
FLAT_SIN2 = math.sin(math.radians(10.0)) ** 2     # a face: its neighbours this close to its plane
PARALLEL_COS = math.cos(math.radians(30.0))  # clip lines closer in direction are one edge
_CAP_SIDES = 8                 # a cell starts as a regular octagon inscribed in the circle through
                               # the k-th neighbour: open cells (borders) stop there


# ---------------------------------------------------------------------------------------------
# neighbourhoods


@dataclass(frozen=True)
class _Neighbourhood:
    """The points and their k nearest neighbours (nearest first, the point itself first), in
    the k-d tree's leaf order: neighbours then lie close in memory, which makes the queries
    and every gather below several times faster than in the input's order. Positions are
    relative to their centroid, so georeferenced coordinates keep their precision."""

    points: np.ndarray  # (N, 3) float64, sorted
    index: np.ndarray   # (N, k) int32 or int64 into the sorted points
    order: np.ndarray   # (N,) input index of each sorted point

    def first(self, k: int) -> np.ndarray:
        return self.index[:, :min(k, self.index.shape[1])]

    def sort(self, values: np.ndarray) -> np.ndarray:
        return np.asarray(values)[self.order]

    def unsort(self, values: np.ndarray) -> np.ndarray:
        out = np.empty_like(values)
        out[self.order] = values
        return out


def _bar(total: int, progress: bool | None, desc: str) -> tqdm:
    show = total > PROGRESS_MIN_POINTS if progress is None else bool(progress)
    return tqdm(total=total, desc=f"surfel: {desc}", unit="pt", unit_scale=True, disable=not show, leave=False)


def _chunks(n: int):
    for start in range(0, n, CHUNK):
        yield start, min(start + CHUNK, n)


def _points(positions: np.ndarray) -> np.ndarray:
    pts = np.asarray(positions, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"positions must have shape (N, 3) with N > 0, got {pts.shape}")
    return pts


def _neighbourhood(positions: np.ndarray, k: int, workers: int, progress: bool | None) -> _Neighbourhood:
    if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1:
        raise TypeError(f"k must be a positive integer, got {type(k).__name__} {k!r:.40}")
    pts = _points(positions)
    pts = pts - pts.mean(axis=0)
    n = len(pts)
    k = max(1, min(k, n))
    tree = cKDTree(pts)
    order = tree.indices
    rank = np.empty(n, np.int32 if n < 2**31 else np.int64)
    rank[order] = np.arange(n)
    points = pts[order]
    index = np.empty((n, k), rank.dtype)
    with _bar(n, progress, "neighbours") as bar:
        for start, stop in _chunks(n):
            _, idx = tree.query(points[start:stop], k=k, workers=workers)
            index[start:stop] = rank[idx.reshape(stop - start, k)]
            bar.update(stop - start)
    return _Neighbourhood(points, index, order)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


# ---------------------------------------------------------------------------------------------
# normals


@numba.njit(parallel=True, cache=True)
def _covariances(points, index, start):  # pragma: no cover - compiled
    """Covariance (m, 3, 3) of each neighbourhood, from offsets to the point itself so the
    one-pass formula subtracts small numbers (no gathered (m, k, 3) array)."""
    m, k = index.shape
    cov = np.empty((m, 3, 3))
    for i in numba.prange(m):
        p = start + i
        s = np.zeros(3)
        ss = np.zeros((3, 3))
        for j in range(k):
            q = index[i, j]
            for a in range(3):
                da = points[q, a] - points[p, a]
                s[a] += da
                for b in range(a + 1):
                    ss[a, b] += da * (points[q, b] - points[p, b])
        for a in range(3):
            for b in range(a + 1):
                c = ss[a, b] / k - s[a] * s[b] / (k * k)
                cov[i, a, b] = c
                cov[i, b, a] = c
    return cov


def _pca_normals(nbh: _Neighbourhood, k: int, progress: bool | None) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented unit normals (N, 3) float64 and the degenerate-neighbourhood mask."""
    n = len(nbh.points)
    index = nbh.first(k)
    normals = np.empty((n, 3))
    degenerate = np.empty(n, bool)
    with _bar(n, progress, "normals") as bar:
        for start, stop in _chunks(n):
            values, vectors = np.linalg.eigh(_covariances(nbh.points, index[start:stop], start))
            normals[start:stop] = vectors[:, :, 0]  # eigenvalues ascending: the normal direction first
            # No tangent plane: the two smallest spreads alike (line with noise, blob, crossing
            # surfaces), or the neighbourhood is a line or a point (both nearly zero).
            degenerate[start:stop] = ((values[:, 0] > DEGENERATE_RATIO * values[:, 1])
                                      | (values[:, 1] <= 1e-12 * values[:, 2]))
            bar.update(stop - start)
    return normals, degenerate


def _orient_towards(normals: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Flip normals (in place) to face `towards` ((3,) or (N, 3)); returns the ambiguous mask."""
    towards = np.broadcast_to(towards, normals.shape)
    dot = np.einsum("ij,ij->i", normals, towards)
    normals[dot < 0] *= -1
    return np.abs(dot) < AMBIGUOUS_COS * np.linalg.norm(towards, axis=1)


@numba.njit(cache=True)
def _cumulative_sign(order, parent, relative):  # pragma: no cover - compiled
    """Product of the relative signs along the path to the root: BFS order puts every parent
    before its children, so one pass suffices."""
    sign = relative.copy()
    for node in order:
        p = parent[node]
        if p >= 0:
            sign[node] *= sign[p]
    return sign


def _orient_by_propagation(nbh: _Neighbourhood, normals: np.ndarray) -> np.ndarray:
    """Orient normals (in place) consistently over the kNN graph (Hoppe et al. 1992); returns
    the mask of points whose sign decision was ambiguous."""
    pts = nbh.points
    n = len(pts)
    cols = np.ascontiguousarray(nbh.first(ORIENT_NEIGHBOURS + 1)[:, 1:])
    kg = cols.shape[1]
    ambiguous = np.zeros(n, bool)
    if kg == 0:
        ambiguous[:] = True
        return ambiguous
    weights = np.empty((n, kg))
    for start, stop in _chunks(n):
        dots = np.einsum("ij,ikj->ik", normals[start:stop], normals[cols[start:stop]])
        # + epsilon: a weight of 0 would be no edge in a sparse graph
        weights[start:stop] = 1.0 - np.abs(dots) + 1e-6
    # Rows are sorted already: build the CSR directly instead of sorting N k COO entries.
    graph = sparse.csr_matrix((weights.ravel(), cols.ravel(), np.arange(0, n * kg + 1, kg)), shape=(n, n))
    tree = csgraph.minimum_spanning_tree(graph).tocoo()
    count, labels = csgraph.connected_components(tree, directed=False)
    seeds = np.unique(labels, return_index=True)[1]  # any point will do: the flux decides below
    # One breadth-first walk over all components: a virtual root (node n) joined to every seed.
    root = n
    rows = np.concatenate([tree.row, np.full(count, root, tree.row.dtype)])
    cols_t = np.concatenate([tree.col, seeds.astype(tree.col.dtype)])
    forest = sparse.csr_matrix((np.ones(len(rows)), (rows, cols_t)), shape=(n + 1, n + 1))
    order, parent = csgraph.breadth_first_order(forest, root, directed=False, return_predecessors=True)
    parent = parent[:n].astype(np.int64)
    parent[parent == root] = -1
    order = order[order != root]
    has_parent = parent >= 0
    dots = np.ones(n)
    for start, stop in _chunks(n):
        p = np.where(has_parent[start:stop], parent[start:stop], np.arange(start, stop))
        dots[start:stop] = np.einsum("ij,ij->i", normals[start:stop], normals[p])
    relative = np.where(dots < 0, -1, 1).astype(np.int8)
    ambiguous |= has_parent & (np.abs(dots) < AMBIGUOUS_COS)
    sign = _cumulative_sign(order, parent, relative)
    # Each component as a whole faces outward: positive flux of (p - centroid).
    size = np.bincount(labels, minlength=count)
    centroid = np.stack([np.bincount(labels, pts[:, a], count) for a in range(3)], axis=1) / size[:, None]
    radial = np.einsum("ij,ij->i", normals, pts - centroid[labels])
    flux = np.bincount(labels, sign * radial, count)
    total = np.bincount(labels, np.abs(radial), count)
    spread = np.bincount(labels, np.linalg.norm(pts - centroid[labels], axis=1), count)
    sign = np.where(flux[labels] < 0, -sign, sign)
    # No outside (a flat patch, a single point): the whole component's orientation is a guess.
    ambiguous |= (np.abs(flux) <= np.maximum(AMBIGUOUS_COS * total, 1e-9 * spread))[labels]
    normals *= sign[:, None]
    return ambiguous


def _normals(nbh: _Neighbourhood, k: int, towards: np.ndarray | None,
             progress: bool | None) -> tuple[np.ndarray, np.ndarray]:
    normals, ambiguous = _pca_normals(nbh, k, progress)
    if towards is not None:
        ambiguous |= _orient_towards(normals, towards)
    else:
        ambiguous |= _orient_by_propagation(nbh, normals)
    return normals, ambiguous


def estimate_normals(positions: np.ndarray, k: int = 16, viewpoint: np.ndarray | None = None,
                     workers: int = -1, progress: bool | None = None) -> tuple[np.ndarray, int]:
    """PCA normals over the k nearest neighbours, oriented: (normals (N, 3) float32, ambiguous).

    viewpoint: sensor position (3,) or per-point sensor positions (N, 3) to face; None orients
    consistently by minimum-spanning-tree propagation, each component facing outward.
    ambiguous: the number of points whose orientation is a guess (see the module docstring).
    progress: None shows a progress bar above PROGRESS_MIN_POINTS points; True/False force it.
    """
    pts = _points(positions)
    nbh = _neighbourhood(pts, k, workers, progress)
    towards = None if viewpoint is None else nbh.sort(np.asarray(viewpoint, np.float64) - pts)
    normals, ambiguous = _normals(nbh, k, towards, progress)
    return nbh.unsort(normals.astype(np.float32)), int(ambiguous.sum())


# ---------------------------------------------------------------------------------------------
# tangent frames


def _orthonormal_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents t, s with (t, s, n) right-handed, float64 (Duff et al. 2017, listing 3)."""
    n = np.asarray(normals, np.float64)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sign = np.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    s = np.stack([b, sign + y * y * a, -y], axis=1)
    return t, s


def tangent_frames(normals: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Circular splat axes (N, 2, 3) float32: orthonormal tangents of the (unit) normals, scaled
    by the radii; (u, v, n) is right-handed."""
    t, s = _orthonormal_basis(_unit(np.asarray(normals, np.float64)))
    r = np.asarray(radii, np.float64)[:, None]
    return np.stack([t * r, s * r], axis=1).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# radii and ellipses: tangent-plane Voronoi cells


@numba.njit(cache=True)
def _clip(px, py, count, a, b, c, qx, qy):  # pragma: no cover - compiled
    """Clip the convex polygon (px, py)[:count] to the half-plane a x + b y <= c into (qx, qy)."""
    out = 0
    for i in range(count):
        j = i + 1 if i + 1 < count else 0
        si = a * px[i] + b * py[i] - c
        sj = a * px[j] + b * py[j] - c
        if si <= 0:
            qx[out] = px[i]
            qy[out] = py[i]
            out += 1
        if (si <= 0) != (sj <= 0):
            t = si / (si - sj)
            qx[out] = px[i] + t * (px[j] - px[i])
            qy[out] = py[i] + t * (py[j] - py[i])
            out += 1
    return out


@numba.njit(cache=True)
def _ellipse_scale2(px, py, count, tau):  # pragma: no cover - compiled
    """Squared scale by which the ellipse with semi-axes (e^(tau/2), e^(-tau/2)) must grow to
    contain the polygon (px, py)[:count]."""
    wx = math.exp(-tau)
    wy = math.exp(tau)
    scale2 = 0.0
    for c in range(count):
        scale2 = max(scale2, px[c] * px[c] * wx + py[c] * py[c] * wy)
    return scale2


@numba.njit(cache=True)
def _crease_half_plane(points, p, q, normal_q, e1, e2):  # pragma: no cover - compiled
    """Where splat p meets the tangent plane of its neighbour q across a sharp feature: the
    half-plane a x + b y <= c of p's plane points p + x e1 + y e2 that p keeps. Its boundary
    is the crease, the line where the two planes meet. p keeps its centre's side of q's plane;
    a centre within ON_PLANE_SIN2 of that plane (on the crease line, whose sides it cannot
    tell apart) keeps the side away from q, the side of its own face."""
    side = 0.0
    ga = 0.0
    gb = 0.0
    distance2 = 0.0
    for a in range(3):
        offset = points[p, a] - points[q, a]
        side += offset * normal_q[a]
        ga += e1[a] * normal_q[a]
        gb += e2[a] * normal_q[a]
        distance2 += offset * offset
    # a plane point lies at g(x, y) = side + x ga + y gb from q's plane; keep sign * g >= 0
    if side * side > ON_PLANE_SIN2 * distance2:
        sign = 1.0 if side > 0.0 else -1.0
    else:
        qx = 0.0
        qy = 0.0
        for a in range(3):
            qx += (points[q, a] - points[p, a]) * e1[a]
            qy += (points[q, a] - points[p, a]) * e2[a]
        at_q = side + qx * ga + qy * gb  # g where q projects into p's plane: that side goes
        sign = -1.0 if at_q > 0.0 else 1.0
    return -sign * ga, -sign * gb, sign * side


@numba.njit(parallel=True, cache=True)
def _flat_points(points, index, start, normals, sharp_cos):  # pragma: no cover - compiled
    """Whether each point start + i is flat: its neighbours with normals within
    acos(sharp_cos) of its own lie in its tangent plane (within FLAT_SIN2). Such points are
    the faces of a piecewise smooth shape; a coarsely sampled curved surface is not flat, and
    the tangent planes of its neighbours would facet it."""
    m, k = index.shape
    flat = np.ones(m, np.bool_)
    for i in numba.prange(m):
        p = start + i
        for j in range(k):
            q = index[i, j]
            height = 0.0
            facing = 0.0
            distance2 = 0.0
            for a in range(3):
                offset = points[q, a] - points[p, a]
                height += offset * normals[p, a]
                facing += normals[q, a] * normals[p, a]
                distance2 += offset * offset
            if facing >= sharp_cos and height * height > FLAT_SIN2 * distance2:
                flat[i] = False
                break
    return flat


@numba.njit(parallel=True, cache=True)
def _crease_points(points, index, start, normals, sharp_cos, flat):  # pragma: no cover - compiled
    """Whether each point start + i lies on a crease itself: in the tangent planes (within
    ON_PLANE_SIN2) of two flat neighbours whose normals are more than acos(sharp_cos) apart,
    i.e. on two faces at once, its normal typically averaged over both. Every part of its
    splat sticks out of one face or the other: it is dropped, and the faces' cells reach the
    crease without it."""
    m, k = index.shape
    crease = np.zeros(m, np.bool_)
    for i in numba.prange(m):
        p = start + i
        planes = np.empty(k, np.int64)  # flat neighbours in whose tangent plane the point lies
        count = 0
        for j in range(k):
            q = index[i, j]
            if q == p or not flat[q]:
                continue
            side = 0.0
            distance2 = 0.0
            for a in range(3):
                offset = points[p, a] - points[q, a]
                side += offset * normals[q, a]
                distance2 += offset * offset
            if side * side > ON_PLANE_SIN2 * distance2:
                continue
            for other in range(count):
                across = 0.0
                for a in range(3):
                    across += normals[q, a] * normals[planes[other], a]
                if across < sharp_cos:
                    crease[i] = True
            if crease[i]:
                break
            planes[count] = q
            count += 1
    return crease


@numba.njit(cache=True)
def _principal_direction(xs, ys, neighbours, count, all_normals, normal, t, s):  # pragma: no cover - compiled
    """The angle in the tangent frame (t, s) of the principal curvature direction of largest
    curvature, and the difference of the principal curvatures (per unit length): from the
    shape operator S, tilt = S offset, fitted by least squares to the neighbours' normals
    (tilt: the tangential part of n_q / (n_q . n), as in _slopes) at their offsets (xs, ys)."""
    dxx = dxy = dyy = 0.0
    txx = txy = tyx = tyy = 0.0
    for j in range(count):
        q = neighbours[j]
        along = tx = ty = 0.0
        for a in range(3):
            along += all_normals[q, a] * normal[a]
            tx += all_normals[q, a] * t[a]
            ty += all_normals[q, a] * s[a]
        if abs(along) < 0.5:
            continue
        tx /= along
        ty /= along
        dxx += xs[j] * xs[j]
        dxy += xs[j] * ys[j]
        dyy += ys[j] * ys[j]
        txx += tx * xs[j]
        txy += tx * ys[j]
        tyx += ty * xs[j]
        tyy += ty * ys[j]
    det = dxx * dyy - dxy * dxy
    if det <= 1e-30:
        return 0.0, 0.0
    s00 = (txx * dyy - txy * dxy) / det
    s01 = (txy * dxx - txx * dxy) / det
    s10 = (tyx * dyy - tyy * dxy) / det
    s11 = (tyy * dxx - tyx * dxy) / det
    shear = 0.5 * (s01 + s10)  # S is symmetric in theory: its symmetric part
    return 0.5 * math.atan2(2.0 * shear, s00 - s11), math.sqrt((s00 - s11) ** 2 + 4.0 * shear * shear)


@numba.njit(parallel=True, cache=True)
def _tangent_cells(points, index, start, normals, t, s, ellipse, max_aspect, all_normals, sharp_cos,
                   flat, dropped, sheet_cos):  # pragma: no cover - compiled
    """For each point start + i: the farthest vertex distance of its Voronoi cell among its
    neighbours in the tangent frame (t, s) (the covering radius), and if `ellipse` the
    semi-axes and direction (cos, sin in the frame) of the cell-covering ellipse aligned with
    the principal curvature directions (`_principal_direction`), or where the curvature has
    none, with the neighbours' principal directions. A neighbour whose normal (all_normals)
    has a dot product below sharp_cos with the point's lies across a sharp feature when both
    are flat (`_flat_points`): the cell ends where the two tangent planes meet
    (`_crease_half_plane`, where the clip lines cut the splat) rather than at the bisector.
    Dropped points (crease points) do not bound any cell, nor do neighbours whose normals
    face away (dot below sheet_cos): the other side of a thin sheet, a surface of its own
    that would otherwise cut this side's cells into holes."""
    m, k = index.shape
    radius = np.zeros(m)
    semi = np.zeros((m, 2))
    direction = np.zeros((m, 2))
    direction[:, 0] = 1.0
    size = _CAP_SIDES + k + 1
    for i in numba.prange(m):
        p = start + i
        xs = np.empty(k)
        ys = np.empty(k)
        used_index = np.empty(k, np.int64)
        crease = np.empty((k, 3))
        creases = 0
        used = 0
        reach = 0.0
        for j in range(k):
            q = index[i, j]
            d0 = points[q, 0] - points[p, 0]
            d1 = points[q, 1] - points[p, 1]
            d2 = points[q, 2] - points[p, 2]
            x = d0 * t[i, 0] + d1 * t[i, 1] + d2 * t[i, 2]
            y = d0 * s[i, 0] + d1 * s[i, 1] + d2 * s[i, 2]
            z = d0 * normals[i, 0] + d1 * normals[i, 1] + d2 * normals[i, 2]
            planar = x * x + y * y
            reach = max(reach, math.sqrt(planar + z * z))
            facing = 0.0
            for a in range(3):
                facing += all_normals[q, a] * normals[i, a]
            if dropped[q] or facing < sheet_cos:
                continue
            if facing < sharp_cos and flat[p] and flat[q]:
                ca, cb, cc = _crease_half_plane(points, p, q, all_normals[q], t[i], s[i])
                if ca * ca + cb * cb > 1e-12:  # not parallel planes (the far side of a sheet)
                    crease[creases, 0] = ca
                    crease[creases, 1] = cb
                    crease[creases, 2] = cc
                    creases += 1
                continue
            if planar > 0 and z * z <= planar:  # skip duplicates and the far side of thin sheets
                xs[used] = x
                ys[used] = y
                used_index[used] = q
                used += 1
        if reach == 0.0:
            continue
        px = np.empty(size)
        py = np.empty(size)
        qx = np.empty(size)
        qy = np.empty(size)
        for c in range(_CAP_SIDES):
            angle = 2.0 * math.pi * c / _CAP_SIDES
            px[c] = reach * math.cos(angle)
            py[c] = reach * math.sin(angle)
        count = _CAP_SIDES
        for j in range(used):  # nearer to the point than to neighbour j: x.d <= |d|^2 / 2
            count = _clip(px, py, count, xs[j], ys[j], 0.5 * (xs[j] * xs[j] + ys[j] * ys[j]), qx, qy)
            px, qx = qx, px
            py, qy = qy, py
        for j in range(creases):
            count = _clip(px, py, count, crease[j, 0], crease[j, 1], crease[j, 2], qx, qy)
            px, qx = qx, px
            py, qy = qy, py
        far = 0.0
        for c in range(count):
            far = max(far, px[c] * px[c] + py[c] * py[c])
        radius[i] = math.sqrt(far)
        if not ellipse or count < 3:
            continue
        # principal directions of the projected neighbours
        mx = 0.0
        my = 0.0
        for j in range(used):
            mx += xs[j]
            my += ys[j]
        mx /= max(used, 1)
        my /= max(used, 1)
        sxx = 0.0
        syy = 0.0
        sxy = 0.0
        for j in range(used):
            sxx += (xs[j] - mx) ** 2
            syy += (ys[j] - my) ** 2
            sxy += (xs[j] - mx) * (ys[j] - my)
        theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
        # Splats "aligned along the curvature" (survey 2.1.4), so that the normal field's two
        # slopes (eq. 8) describe the surface: the principal curvature directions, wherever the
        # normals turn more one way than the other across the cell.
        curvature_theta, anisotropy = _principal_direction(xs, ys, used_index, used, all_normals,
                                                           normals[i], t[i], s[i])
        if anisotropy * reach > CURVATURE_ANISOTROPY:
            theta = curvature_theta
        co = math.cos(theta)
        si = math.sin(theta)
        # Rotate the cell into those directions; the smallest ellipse x^2/a^2 + y^2/b^2 <= 1
        # with a b = 1 containing it: with a = e^(tau/2), b = e^(-tau/2) the needed scale^2 is
        # a maximum of functions convex in tau, so golden-section search finds the optimum.
        for c in range(count):
            x0 = px[c] * co + py[c] * si
            py[c] = -px[c] * si + py[c] * co
            px[c] = x0
        lo = -math.log(max_aspect)
        hi = math.log(max_aspect)
        for _ in range(24):  # brackets the optimum to 1e-5 of the log-aspect range
            t1 = hi - 0.618033988749895 * (hi - lo)
            t2 = lo + 0.618033988749895 * (hi - lo)
            if _ellipse_scale2(px, py, count, t1) <= _ellipse_scale2(px, py, count, t2):
                hi = t2
            else:
                lo = t1
        tau = 0.5 * (lo + hi)
        scale = math.sqrt(_ellipse_scale2(px, py, count, tau))
        a = math.exp(0.5 * tau)
        b = math.exp(-0.5 * tau)
        semi[i, 0] = a * scale
        semi[i, 1] = b * scale
        direction[i, 0] = co
        direction[i, 1] = si
    return radius, semi, direction


def _cells(nbh: _Neighbourhood, normals: np.ndarray, k: int, ellipse: bool,
           progress: bool | None, desc: str,
           features: tuple[np.ndarray, np.ndarray] | None = None,
           oriented: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Radii (N,) float64 and, if `ellipse`, axes (N, 2, 3) float64, both including the margin
    and the outlier cap; given the (flat, crease) masks of `_sharp_features`, cells end at
    sharp features and ignore the crease points. With `oriented` normals, neighbours facing
    the other way (the far side of a thin sheet) do not bound cells."""
    n = len(nbh.points)
    index = nbh.first(k)
    normals = _unit(np.asarray(normals, np.float64))
    sharp_cos = math.cos(math.radians(SHARP_ANGLE))
    flat, dropped = features if features is not None else (np.zeros(n, bool), np.zeros(n, bool))
    raw = np.empty(n)
    axes = np.empty((n, 2, 3)) if ellipse else None
    with _bar(n, progress, desc) as bar:
        for start, stop in _chunks(n):
            t, s = _orthonormal_basis(normals[start:stop])
            radius, semi, direction = _tangent_cells(nbh.points, index[start:stop], start, normals[start:stop],
                                                     t, s, ellipse, ELLIPSE_MAX_ASPECT, normals, sharp_cos, flat,
                                                     dropped,
                                                     SHEET_COS if oriented else -2.0)
            raw[start:stop] = radius
            if ellipse:
                co, si = direction[:, 0:1], direction[:, 1:2]
                major = semi[:, 0] >= semi[:, 1]
                e1 = co * t + si * s
                e2 = -si * t + co * s
                # u is the major axis; (e2, -e1) keeps (u, v, n) right-handed
                u = np.where(major[:, None], e1 * semi[:, 0:1], e2 * semi[:, 1:2])
                v = np.where(major[:, None], e2 * semi[:, 1:2], -e1 * semi[:, 0:1])
                axes[start:stop] = np.stack([u, v], axis=1)
            bar.update(stop - start)
    # Points all of whose neighbours coincide with them have no cell: borrow a typical size.
    positive = raw > 0
    raw[~positive] = np.median(raw[positive]) if positive.any() else 1.0
    if ellipse:
        circle = ~positive | (np.linalg.norm(axes, axis=2).min(axis=1) <= 0)
        t, s = _orthonormal_basis(normals[circle])
        axes[circle] = np.stack([t, s], axis=1) * raw[circle][:, None, None]
    scale = np.full(n, RADIUS_MARGIN)
    if index.shape[1] > 1:
        for start, stop in _chunks(n):
            typical = np.median(raw[index[start:stop, 1:]], axis=1)
            scale[start:stop] *= np.minimum(1.0, ISOLATED_FACTOR * typical / raw[start:stop])
    if ellipse:
        axes *= scale[:, None, None]
    return raw * scale, axes


def estimate_radii(positions: np.ndarray, k: int = RADIUS_NEIGHBOURS, normals: np.ndarray | None = None,
                   workers: int = -1, progress: bool | None = None) -> np.ndarray:
    """Splat radii (N,) float32 that cover the surface without holes: each point's covering
    radius of its tangent-plane Voronoi cell among its k nearest neighbours, times
    RADIUS_MARGIN, outliers capped (see the module docstring). Normals only define the tangent
    planes; without them unoriented PCA normals over the same neighbours are used."""
    nbh = _neighbourhood(positions, k, workers, progress)
    oriented = normals is not None
    normals = _pca_normals(nbh, k, progress)[0] if normals is None else nbh.sort(normals)
    radii, _ = _cells(nbh, normals, k, False, progress, "radii", oriented=oriented)
    return nbh.unsort(radii.astype(np.float32))


def fit_ellipses(positions: np.ndarray, normals: np.ndarray, k: int = RADIUS_NEIGHBOURS, workers: int = -1,
                 progress: bool | None = None) -> np.ndarray:
    """Elliptical splat axes (N, 2, 3) float32 (u major, (u, v, n) right-handed): principal
    directions of the neighbours in the tangent plane, semi-axes covering the point's
    Voronoi cell like the radius rule (see the module docstring)."""
    nbh = _neighbourhood(positions, k, workers, progress)
    _, axes = _cells(nbh, nbh.sort(normals), k, True, progress, "ellipses")
    return nbh.unsort(axes.astype(np.float32))


# ---------------------------------------------------------------------------------------------
# sharp features


@numba.njit(parallel=True, cache=True)
def _clip_lines(points, index, start, normals, axes, sharp_cos, flat, dropped):  # pragma: no cover - compiled
    """CLIP_LINES clip lines (a, b, c) per splat start + i, in its local coordinates (u, v)
    (1 on the rim): the splat keeps a u + b v <= c, (a, b) a unit vector. They are crease
    half-planes that end its cell (`_tangent_cells`): the one nearest the centre, then the
    nearest in another direction. A dropped splat keeps nothing."""
    m, k = index.shape
    lines = np.empty((m, CLIP_LINES, 3), np.float32)
    for i in numba.prange(m):
        p = start + i
        for line in range(CLIP_LINES):
            if dropped[p]:  # u <= -2, then -u <= -2
                lines[i, line, 0] = 1.0 - 2.0 * line
                lines[i, line, 1] = 0.0
                lines[i, line, 2] = -2.0
            else:
                lines[i, line, 0] = INACTIVE_CLIP[0]
                lines[i, line, 1] = INACTIVE_CLIP[1]
                lines[i, line, 2] = INACTIVE_CLIP[2]
        if dropped[p]:
            continue
        candidates = np.empty((k, 3))
        count = 0
        for j in range(k):
            q = index[i, j]
            facing = 0.0
            for a in range(3):
                facing += normals[q, a] * normals[p, a]
            if facing >= sharp_cos or dropped[q] or not (flat[p] and flat[q]):
                continue
            la, lb, lc = _crease_half_plane(points, p, q, normals[q], axes[i, 0], axes[i, 1])
            length = math.sqrt(la * la + lb * lb)
            if length < 1e-6 or lc >= length:  # parallel planes, or the line misses the splat
                continue
            candidates[count, 0] = la / length
            candidates[count, 1] = lb / length
            candidates[count, 2] = lc / length
            count += 1
        used = 0
        while used < CLIP_LINES:
            best = -1
            for c in range(count):  # the most restrictive line not parallel to a chosen one
                parallel = False
                for other in range(used):
                    if candidates[c, 0] * lines[i, other, 0] + candidates[c, 1] * lines[i, other, 1] > PARALLEL_COS:
                        parallel = True
                if not parallel and (best < 0 or candidates[c, 2] < candidates[best, 2]):
                    best = c
            if best < 0:
                break
            for a in range(3):
                lines[i, used, a] = candidates[best, a]
            used += 1
    return lines


def clipped_away(cloud: PointCloud) -> np.ndarray:
    """(N,) bool: the splats whose clip lines keep nothing of them (crease points)."""
    lines = cloud.attributes.get("clip_lines")
    if lines is None:
        return np.zeros(len(cloud), bool)
    return (lines[:, :, 2] < -1).any(axis=1)


def _sharp_features(nbh: _Neighbourhood, normals: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The (flat, crease) masks (N,) bool of `_flat_points` and `_crease_points`."""
    n = len(nbh.points)
    index = nbh.first(k)
    normals = _unit(np.asarray(normals, np.float64))
    sharp_cos = math.cos(math.radians(SHARP_ANGLE))
    flat = np.empty(n, bool)
    crease = np.empty(n, bool)
    for start, stop in _chunks(n):
        flat[start:stop] = _flat_points(nbh.points, index[start:stop], start, normals, sharp_cos)
    for start, stop in _chunks(n):
        crease[start:stop] = _crease_points(nbh.points, index[start:stop], start, normals, sharp_cos, flat)
    return flat, crease


def _sharp_clip_lines(nbh: _Neighbourhood, normals: np.ndarray, axes: np.ndarray,
                      features: tuple[np.ndarray, np.ndarray], k: int, progress: bool | None) -> np.ndarray:
    """Clip lines (N, CLIP_LINES, 3) float32 of `_clip_lines`."""
    n = len(nbh.points)
    index = nbh.first(k)
    normals = _unit(np.asarray(normals, np.float64))
    sharp_cos = math.cos(math.radians(SHARP_ANGLE))
    lines = np.empty((n, CLIP_LINES, 3), np.float32)
    with _bar(n, progress, "sharp features") as bar:
        for start, stop in _chunks(n):
            lines[start:stop] = _clip_lines(nbh.points, index[start:stop], start, normals,
                                            np.asarray(axes[start:stop], np.float64), sharp_cos, *features)
            bar.update(stop - start)
    return lines


# ---------------------------------------------------------------------------------------------
# Phong splatting's normal field


@numba.njit(parallel=True, cache=True)
def _slopes(points, index, start, normals, axes):  # pragma: no cover - compiled
    """Least-squares slopes (alpha, beta) of each splat start + i over its neighbours."""
    m, k = index.shape
    slopes = np.zeros((m, 2))
    for i in numba.prange(m):
        p = start + i
        num = np.zeros(2)
        den = np.zeros(2)
        for j in range(k):
            q = index[i, j]
            if q == p:
                continue
            along = 0.0
            for a in range(3):
                along += normals[q, a] * normals[p, a]
            # The model's normal has component 1 along n_j: compare n_i / (n_i . n_j), whose
            # tangential part is exactly (u alpha, v beta). Neighbours more than 60 degrees
            # off (across a crease) would only bend the fit; their sign does not matter.
            if abs(along) < 0.5:
                continue
            for t in range(2):
                length2 = 0.0
                offset = 0.0
                tilt = 0.0
                for a in range(3):
                    axis = axes[i, t, a]
                    length2 += axis * axis
                    offset += (points[q, a] - points[p, a]) * axis
                    tilt += normals[q, a] * axis
                if length2 == 0.0:
                    continue
                coordinate = offset / length2                      # 1 on the ellipse's rim
                tilt /= math.sqrt(length2) * along
                num[t] += coordinate * tilt
                den[t] += coordinate * coordinate
        for t in range(2):
            if den[t] > 1e-12:
                slopes[i, t] = num[t] / den[t]
    return slopes


def _normal_field(nbh: _Neighbourhood, normals: np.ndarray, axes: np.ndarray, k: int,
                  progress: bool | None) -> tuple[np.ndarray, np.ndarray]:
    n = len(nbh.points)
    index = nbh.first(k)
    normals = _unit(np.asarray(normals, np.float64))
    slopes = np.empty((n, 2), np.float32)
    with _bar(n, progress, "normal field") as bar:
        for start, stop in _chunks(n):
            axes_chunk = np.asarray(axes[start:stop], np.float64)
            slopes[start:stop] = _slopes(nbh.points, index[start:stop], start, normals, axes_chunk)
            bar.update(stop - start)
    return slopes[:, 0].copy(), slopes[:, 1].copy()


def fit_normal_field(positions: np.ndarray, normals: np.ndarray, axes: np.ndarray, k: int = FIELD_NEIGHBOURS,
                     workers: int = -1, progress: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Phong splatting's linear normal field (alpha, beta), each (N,) float32:
    N_j(u, v) = n_j + u alpha_j û_j + v beta_j v̂_j with unit axis directions û_j, v̂_j and
    (u, v) in semi-axis units, least squares over the k - 1 nearest neighbours' normals."""
    nbh = _neighbourhood(positions, k, workers, progress)
    alpha, beta = _normal_field(nbh, nbh.sort(normals), nbh.sort(axes), k, progress)
    return nbh.unsort(alpha), nbh.unsort(beta)


# ---------------------------------------------------------------------------------------------
# clouds


def prepare(cloud: PointCloud, *, k_normals: int = 16, viewpoint: np.ndarray | None = None,
            elliptical: bool = False, normal_field: bool = False, sharp_features: bool = True,
            progress: bool | None = None) -> tuple[PointCloud, dict]:
    """Fill in what `cloud` lacks for splatting; returns (cloud, report).

    normals: estimated if None: towards `viewpoint` if given; geospatial clouds (aerial scans,
    seen from above) face +Z; otherwise propagated and outward. A cloud with axes but no
    normals gets u x v, the orientation its splats already have.
    radii: estimated if None (covering radii of the tangent-plane Voronoi cells).
    axes: if None, fitted ellipses when `elliptical`, else circular frames of the radii.
    normal_field: also fit attributes["phong_alpha"], attributes["phong_beta"] if missing.
    sharp_features: when radii and axes are estimated, cells end at creases and
    attributes["clip_lines"] (N, CLIP_LINES, 3) cut the splats there ("Sharp features" in the
    module docstring).
    Given attributes are kept as they are. The report names every estimated attribute and
    how, plus "ambiguous_normals" when normals were estimated.
    """
    report: dict = {}
    need_field = normal_field and not {"phong_alpha", "phong_beta"} <= set(cloud.attributes)
    if cloud.normals is not None and cloud.radii is not None and cloud.axes is not None and not need_field:
        return cloud, report
    k = max(k_normals, RADIUS_NEIGHBOURS, FIELD_NEIGHBOURS if need_field else 1)
    nbh = _neighbourhood(cloud.positions, k, -1, progress)
    given = {name: None if getattr(cloud, name) is None else nbh.sort(getattr(cloud, name))
             for name in ("normals", "radii", "axes")}
    estimated: dict = {}
    normals = given["normals"]
    if normals is None and given["axes"] is not None:
        axes64 = given["axes"].astype(np.float64)
        normals = estimated["normals"] = _unit(np.cross(axes64[:, 0], axes64[:, 1]))
        report["normals"] = "from the splat axes (u x v)"
    elif normals is None:
        if viewpoint is not None:
            towards = nbh.sort(np.asarray(viewpoint, np.float64) - cloud.positions)
            how = "facing the viewpoint"
        elif cloud.geospatial:
            towards, how = np.array([0.0, 0.0, 1.0]), "facing up (+Z)"
        else:
            towards, how = None, "oriented by MST propagation, outward"
        normals, ambiguous = _normals(nbh, k_normals, towards, progress)
        estimated["normals"] = normals
        report["normals"] = f"estimated (PCA, k={k_normals}, {how})"
        report["ambiguous_normals"] = int(ambiguous.sum())
    radii = given["radii"]
    features = None
    if sharp_features and radii is None and given["axes"] is None:
        features = _sharp_features(nbh, normals, RADIUS_NEIGHBOURS)
    if radii is None:
        radii = estimated["radii"] = _cells(nbh, normals, RADIUS_NEIGHBOURS, False, progress, "radii", features)[0]
        report["radii"] = (f"estimated (Voronoi covering radius, k={RADIUS_NEIGHBOURS}, "
                           f"x{RADIUS_MARGIN}, mean {float(np.mean(radii)):.4g})")
    axes = given["axes"]
    if axes is None and elliptical:
        _, axes = _cells(nbh, normals, RADIUS_NEIGHBOURS, True, progress, "ellipses", features)
        report["axes"] = f"fitted ellipses (k={RADIUS_NEIGHBOURS})"
    elif axes is None:
        axes = tangent_frames(normals, radii)
        report["axes"] = "circular (tangent frames of the radii)"
    if given["axes"] is None:
        estimated["axes"] = axes
    changes = {name: nbh.unsort(np.asarray(value, np.float32)) for name, value in estimated.items()}
    attributes = dict(cloud.attributes)
    if features is not None:
        lines = _sharp_clip_lines(nbh, normals, axes, features, RADIUS_NEIGHBOURS, progress)
        attributes["clip_lines"] = nbh.unsort(lines)
        report["sharp_features"] = (f"{float(np.mean(lines[:, 0, 2] < 1)):.1%} of splats end at creases "
                                    f"(normals > {SHARP_ANGLE:g} degrees apart), "
                                    f"{int(features[1].sum())} crease points dropped")
    if need_field:
        alpha, beta = _normal_field(nbh, normals, axes, FIELD_NEIGHBOURS, progress)
        attributes.update(phong_alpha=nbh.unsort(alpha), phong_beta=nbh.unsort(beta))
        report["normal_field"] = f"fitted (least squares, k={FIELD_NEIGHBOURS})"
    if attributes.keys() != cloud.attributes.keys():
        changes["attributes"] = attributes
    return cloud.with_(**changes), report
