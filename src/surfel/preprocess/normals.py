"""Normals: PCA over the k nearest neighbours, oriented towards a viewpoint or by propagation.

Direction: the eigenvector of the smallest eigenvalue of the neighbourhood covariance
C = 1/k sum_j (q_j - p)(q_j - p)^T - s s^T / k^2, s = sum_j (q_j - p) (the one-pass formula on
offsets to the point itself, so that it subtracts small numbers), diagonalised by cyclic Jacobi
rotations (Press et al., Numerical Recipes, 3rd ed., section 11.1) in the kernel that sums it.

Scale (noisy clouds): the angle error of a PCA normal over a neighbourhood of radius r that
holds k points has a curvature term that grows with r and a noise term that shrinks with it
(Mitra & Nguyen 2003, "Estimating surface normals in noisy point cloud data", Proc. 19th
Symposium on Computational Geometry, 322-328, whose optimal r grows as (sigma / kappa)^(1/3)):

    E_j = a kappa r_j + 2 sigma / (r_j sqrt(k_j)),   a = CURVATURE_WEIGHT,

the second term the tilt of a plane fitted to k points of tangent spread lambda_t = r^2 / 4
with range noise sigma. sigma and kappa are estimated per point from its PCA at each candidate
scale k_j of SCALES: a quadratic patch of curvature kappa with noise sigma, sampled uniformly
over a disk of radius r_j (r_j^2 = 2 (lambda1 + lambda2)), has

    lambda0(k_j) = sigma^2 + kappa^2 r_j^4 / 48,

fitted by least squares over the scales (sigma^2, kappa^2 >= 0). Each point takes the normal,
eigenvalues and degeneracy of its scale of least E_j. A cloud is noisy when the median
scattering lambda0 / lambda2 at k = NORMAL_NEIGHBOURS exceeds NOISE_SCATTERING (vertices of a
smooth mesh: about 0.004; a range scan with 0.1% noise: 0.025); only then are the wider
neighbourhoods searched. And it is noisy only if that scattering falls as the neighbourhood
widens: noise keeps lambda0 at sigma^2 while lambda2 grows as r^2, but curvature grows lambda0 as
r^4 (the model above), so a coarse sampling of a smooth surface, which scatters a plane fit as
much as noise does, scatters more at the widest scale than at the first. The median scattering
at k = 48 over that at k = 16: 0.50-0.81 on raw scans of seven meshes (`surfel scan`'s
defaults), 1.3-47 on the vertices of 15 meshes, among them figures decimated to 2,000-3,300
vertices that scatter up to 0.18 at 16. Their normals taken at each point's scale were worse
than at 16 (the decimated ogre's 21 degrees from the mesh's, 34% of them flipped, against 19
degrees and 27%): rendered from their points alone, six such figures, 18 views each at 512 x
512, gained 0.1 to 1.7 dB with `deferred` (5 renders over 0.1% holes instead of 9) and -0.04 to
+2.4 dB with `mls` (40 instead of 46). A clean cloud's PCA normals are refined by quadrics
instead (`jets.py`), which follow the curvature that tilts the plane.

Orientation: towards a viewpoint when the sensor position is known; otherwise consistently by
propagation (Hoppe, DeRose, Duchamp, McDonald & Stuetzle 1992, "Surface reconstruction from
unorganized points"): a minimum spanning tree of the symmetric kNN graph (ORIENT_NEIGHBOURS per
point; Hoppe's Riemannian graph adds the Euclidean MST to connect everything, here each
connected component is oriented on its own) with edge weights 1 - |n_i . n_j| (so flips
propagate across nearly parallel normals first), grown by Prim's algorithm (an indexed binary
heap, in numba), every point taking the sign that agrees with its tree parent. Each connected
component then faces outward as a whole: it is flipped when the flux
sum_i n_i . (p_i - centroid) is negative, which by the divergence theorem (the flux of p - c
through a closed surface is 3 x its volume) is the outward choice for closed scans, and does
not hinge on one seed point's normal. A geospatial cloud (an aerial tile, seen from above)
has an up direction instead: each component faces up as a whole, sum_i n_i . up >= 0, unless
it rises as much as it falls (|sum| < AMBIGUOUS_COS sum |n_i . up|: walls, a closed object),
when the flux decides. Facing +Z point by point would flip half of every steep surface at
random (walls, crowns, an object's sides), and neighbours facing apart read as the two sides
of a sheet or a crease to every estimation after.

Given normals keep their orientation where a sensor or an up direction says which side was
seen, or given splat axes fix it (u x v). Elsewhere (`orient_given`, on every cloud that
`complete.complete` passes on or prepares):
  * signs picked point by point, as a PCA that was never oriented leaves them, are oriented as
    estimated normals are, by propagation: more than RANDOM_SIGNS_SHARE of the pairs of
    neighbours (ORIENT_NEIGHBOURS each) whose normals lie within 60 degrees of one line face
    apart (`signs_at_random`). Only pairs on one surface count: the neighbour within
    asin(IN_PLANE_SIN) of the point's tangent plane (a thin part's far side, 0.4 spacings
    below, faces away), and not a copy in its place facing away (a two-sided mesh repeats each
    vertex for its back faces). That share is 0.5 at random; on the vertices of 18 models of
    common-3d-test-models and 10 decimations of them it is 0 to 0.021, 0.12 for the ogre
    decimated to 3,096 vertices, whose loincloth lies over its body closer than its sampling.
    Spot with its vertices' signs at random, three views at 512 x 512: `deferred` 25.4 to
    27.9 dB, `phong` 25.8 to 28.3 dB, `mls` 36.0 to 37.3 dB, now as with its own normals
    (36.3 to 39.2 dB); the bunny's 30.5 to 43.3 dB over the three methods, now 37.0 to
    45.1 dB, as with its own.
  * a closed mesh's vertex normals that face inward as a whole are turned: flux <
    -AMBIGUOUS_COS x sum_i |n_i . (p_i - c)| (`faces_inward`). A mesh wound the other way round (the Cyberware
    horse: flux -0.72 of the total; the 22 other meshes there with an inside: +0.19 to +1.0)
    gives its vertices inward normals, and the cells read every convex edge as concave
    (`cells.py`): splats at the horse's hooves stood out as wings across the view. The horse's
    48,485 vertices and its decimations to 6,000 / 4,000 / 2,500, 18 views at 512 x 512:
    `deferred` 36.5 / 27.1 / 25.5 / 24.3 -> 38.6 / 31.1 / 29.5 / 27.6 dB, `phong` 39.6 /
    27.3 / 25.6 / 24.5 -> 40.5 / 31.4 / 29.7 / 27.7 dB. The coarsest now shows holes at its
    hooves' soles (10 views over 0.1% with `deferred`) that the wings covered: a sole is one
    polygon of five vertices, none inside it, whose normals lean 45 to 70 degrees into the
    walls. A point cloud's normals keep their sides: the flux of a scan made inside a room or
    a corridor, its normals facing the scanner, is as negative as an inside-out object's. So
    do an open mesh's (`io.mesh.opening` at least CLOSED_OPENING; at most 0.02 on the figures
    and CAD parts here, whose holes are small): a room without its ceiling, faces facing in,
    seen from inside at 256 x 256, lost 4.4 and 5.8 dB in two of three views turned. A closed
    room is turned all the same, as an object wound inside out would be.
Propagation is not the default for given normals: on 9 of those 26 meshes with an inside it
flips more than a tenth of the vertices against the mesh's orientation (the cow 16%, the ogre
32%), where consistent given normals are right.

`ambiguous` counts the points whose orientation is a guess:
  * degenerate neighbourhoods without a tangent plane: the two smallest covariance
    eigenvalues within a factor 1/DEGENERATE_RATIO of each other (a line, a blob, the
    crossing of two surfaces), or a neighbourhood that is a line or a single point;
  * sign decisions taken against a nearly perpendicular reference, |cos| < AMBIGUOUS_COS:
    the tree parent's normal, or the direction to the viewpoint;
  * every point of a component without an outside: |flux| < AMBIGUOUS_COS x
    sum_i |n_i . (p_i - c)| (a flat patch, a single point), and, given an up direction,
    without one either, whose sign is arbitrary.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..threads import over_rows
from .chunked import map_chunks
from .jets import jet_normals
from .neighbourhood import Neighbourhood, as_points

NORMAL_NEIGHBOURS = 16   # neighbours of the PCA
AMBIGUOUS_COS = 0.1      # |cos| below which a sign decision is a guess
DEGENERATE_RATIO = 0.5   # lambda_0 > this x lambda_1: no dominant normal direction
ORIENT_NEIGHBOURS = 8    # edges per point of the propagation graph: half the MST time of 15,
                         # the same orientations on the bunny
JACOBI_SWEEPS = 16       # cyclic Jacobi sweeps at most (a 3 x 3 converges in about 4 to 6)
SCALES = (16, 24, 32, 48)  # candidate neighbourhood sizes of the scale selection
CURVATURE_WEIGHT = 0.15  # a of E_j: the least mean error over the scans of benchmarks/scan_fidelity.py
NOISE_SCATTERING = 0.01  # median lambda0 / lambda2 above which a cloud's normals select their scale
RANDOM_SIGNS_SHARE = 0.35  # of neighbours' near-parallel normals facing apart: given signs at random
CLOSED_OPENING = 0.1       # io.mesh.opening below which a mesh is closed: seen from outside
IN_PLANE_SIN = 0.25        # a neighbour within asin(this) of a point's tangent plane lies on its surface


def _pca(points, index, start):
    """Eigenvalues (m, 3), ascending, of the neighbourhood covariance of each point start + i,
    and the unit eigenvector (m, 3) of the smallest: the covariance from offsets to the point
    itself, diagonalised by cyclic Jacobi rotations (no gathered (m, k, 3) array, no LAPACK
    call per point)."""
    m = len(index)
    values = np.empty((m, 3))
    vectors = np.empty((m, 3))
    over_rows(_pca_rows, m, points, index, start, values, vectors)
    return values, vectors


@numba.njit(cache=True, nogil=True)
def _pca_rows(first, stop, points, index, start, values, vectors):  # pragma: no cover - compiled
    """Rows first:stop of `_pca`."""
    k = index.shape[1]
    for i in range(first, stop):
        p = start + i
        s = np.zeros(3)
        a = np.zeros((3, 3))
        for j in range(k):
            q = index[i, j]
            for r in range(3):
                dr = points[q, r] - points[p, r]
                s[r] += dr
                for c in range(r + 1):
                    a[r, c] += dr * (points[q, c] - points[p, c])
        for r in range(3):
            for c in range(r + 1):
                a[r, c] = a[r, c] / k - s[r] * s[c] / (k * k)
                a[c, r] = a[r, c]
        v = np.eye(3)
        for _ in range(JACOBI_SWEEPS):
            off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
            if off <= 1e-32 * (a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]):
                break
            for pair in range(3):
                r, c = (0, 1) if pair == 0 else (0, 2) if pair == 1 else (1, 2)
                if a[r, c] == 0.0:
                    continue
                # the rotation in the (r, c) plane that zeroes a[r, c] (Numerical Recipes 11.1)
                theta = (a[c, c] - a[r, r]) / (2.0 * a[r, c])
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                cos = 1.0 / math.sqrt(t * t + 1.0)
                sin = t * cos
                for x in range(3):
                    ar, ac = a[x, r], a[x, c]
                    a[x, r], a[x, c] = cos * ar - sin * ac, sin * ar + cos * ac
                for x in range(3):
                    ar, ac = a[r, x], a[c, x]
                    a[r, x], a[c, x] = cos * ar - sin * ac, sin * ar + cos * ac
                for x in range(3):
                    vr, vc = v[x, r], v[x, c]
                    v[x, r], v[x, c] = cos * vr - sin * vc, sin * vr + cos * vc
        low = 0  # the diagonal, sorted
        if a[1, 1] < a[low, low]:
            low = 1
        if a[2, 2] < a[low, low]:
            low = 2
        high = 2 if low != 2 else 1
        middle = 3 - low - high
        if a[middle, middle] > a[high, high]:
            high, middle = middle, high
        values[i, 0], values[i, 1], values[i, 2] = a[low, low], a[middle, middle], a[high, high]
        for x in range(3):
            vectors[i, x] = v[x, low]


def pca_normals(nbh: Neighbourhood, k: int, progress: bool | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unoriented unit normals (N, 3) float64, the degenerate-neighbourhood mask, and the
    covariance eigenvalues (N, 3) float64, ascending (what `structure.py` reads the shape of a
    neighbourhood from)."""
    index = nbh.first(k)

    def pca(start: int, stop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        values, vectors = _pca(nbh.points, index[start:stop], start)
        # No tangent plane: the two smallest spreads alike (line with noise, blob, crossing
        # surfaces), or the neighbourhood is a line or a point (both nearly zero).
        degenerate = (values[:, 0] > DEGENERATE_RATIO * values[:, 1]) | (values[:, 1] <= 1e-12 * values[:, 2])
        return vectors, degenerate, values

    return map_chunks(pca, len(nbh.points), progress, "normals")


def scattering(eigenvalues: np.ndarray) -> float:
    """The median scattering lambda0 / lambda2 of these eigenvalues (N, 3)."""
    return float(np.median(eigenvalues[:, 0] / np.maximum(eigenvalues[:, 2], 1e-300)))


def is_noisy(eigenvalues: np.ndarray) -> bool:
    """Whether these eigenvalues (N, 3) scatter as much as a noisy cloud's (the first test of the
    module docstring; `scale_selected_normals` makes the second)."""
    return scattering(eigenvalues) > NOISE_SCATTERING


def scale_selected_normals(nbh: Neighbourhood, progress: bool | None, scales: tuple[int, ...] = SCALES
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """pca_normals at each point's scale of least expected error (module docstring): unoriented
    normals (N, 3), the degenerate mask, the eigenvalues (N, 3) of the chosen scales; None when
    the scattering does not fall from the first scale to the widest (curvature, not noise)."""
    wide = nbh.widened(max(scales), progress=progress)
    fits = [pca_normals(wide, k, progress) for k in scales]
    values = np.stack([f[2] for f in fits])                   # (S, N, 3)
    if scattering(values[-1]) >= scattering(values[0]):
        return None
    r2 = 2.0 * (values[:, :, 1] + values[:, :, 2])            # r_j^2
    quartic = r2 * r2 / 48.0
    # least squares of lambda0 = sigma^2 + kappa^2 r^4 / 48 over the scales, per point
    a11, a12, a22 = len(scales), quartic.sum(0), (quartic * quartic).sum(0)
    b1, b2 = values[:, :, 0].sum(0), (quartic * values[:, :, 0]).sum(0)
    det = np.maximum(a11 * a22 - a12 * a12, 1e-300)
    noise2 = np.maximum((a22 * b1 - a12 * b2) / det, 0.0)
    curvature2 = np.maximum((a11 * b2 - a12 * b1) / det, 0.0)
    radius = np.sqrt(r2)
    counts = np.array([min(k, len(nbh.points)) for k in scales], np.float64)[:, None]
    error = CURVATURE_WEIGHT * np.sqrt(curvature2) * radius + 2.0 * np.sqrt(noise2) / (
        np.maximum(radius, 1e-300) * np.sqrt(counts))
    best = np.argmin(error, axis=0)
    rows = np.arange(len(best))
    return (np.stack([f[0] for f in fits])[best, rows], np.stack([f[1] for f in fits])[best, rows],
            values[best, rows])


def orient_towards(normals: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Flip normals (in place) to face `towards` ((3,) or (N, 3)); returns the ambiguous mask."""
    towards = np.broadcast_to(towards, normals.shape)
    dot = np.einsum("ij,ij->i", normals, towards)
    normals[dot < 0] *= -1
    return np.abs(dot) < AMBIGUOUS_COS * np.linalg.norm(towards, axis=1)


def faces_inward(points: np.ndarray, normals: np.ndarray) -> bool:
    """Whether unit `normals` (N, 3) face inward as a whole: their flux about the centroid is
    negative beyond a guess (module docstring: given normals). By the divergence theorem the
    flux of p - c through a closed surface is 3 x its volume whatever c; a flat patch has none."""
    radial = np.einsum("ij,ij->i", normals, points - points.mean(axis=0))
    return bool(radial.sum() < -AMBIGUOUS_COS * np.abs(radial).sum())


@numba.njit(cache=True, inline="always")
def _row_dot(rows, i, j):  # pragma: no cover - compiled
    return rows[i, 0] * rows[j, 0] + rows[i, 1] * rows[j, 1] + rows[i, 2] * rows[j, 2]


@numba.njit(cache=True, inline="always")
def _same_position(points, i, q):  # pragma: no cover - compiled
    return points[i, 0] == points[q, 0] and points[i, 1] == points[q, 1] and points[i, 2] == points[q, 2]


@numba.njit(cache=True, nogil=True)
def _facing_apart(points, index, normals, in_plane2):  # pragma: no cover - compiled
    """Among the pairs (i, index[i, j]) of distinct positions whose normals lie within 60
    degrees of one line, how many face apart, and how many there are. A point with a copy in
    its place facing away is one side of a two-sided sheet (a mesh that repeats each vertex
    for its back faces), where neighbours facing apart say nothing of the signs: left out."""
    n, k = index.shape
    two_sided = np.zeros(n, np.bool_)
    for i in range(n):
        for j in range(k):
            q = index[i, j]
            if _same_position(points, i, q) and _row_dot(normals, i, q) < -0.5:
                two_sided[i] = True
    apart = parallel = 0
    for i in range(n):
        if two_sided[i]:
            continue
        for j in range(k):
            q = index[i, j]
            if two_sided[q] or _same_position(points, i, q):
                continue
            dx, dy, dz = points[q, 0] - points[i, 0], points[q, 1] - points[i, 1], points[q, 2] - points[i, 2]
            height = normals[i, 0] * dx + normals[i, 1] * dy + normals[i, 2] * dz
            if height * height > in_plane2 * (dx * dx + dy * dy + dz * dz):
                continue  # off the tangent plane: maybe another layer, a thin part's far side
            dot = _row_dot(normals, i, q)
            if abs(dot) > 0.5:
                parallel += 1
                apart += dot < 0.0
    return apart, parallel


def signs_at_random(nbh: Neighbourhood, normals: np.ndarray) -> bool:
    """Whether the signs of unit `normals` (in the sorted order) disagree between neighbours as
    signs picked at random do (module docstring: given normals)."""
    nearest = nbh.first(ORIENT_NEIGHBOURS + 1)
    if nearest.shape[1] == 1:
        return False
    apart, parallel = _facing_apart(nbh.points, np.ascontiguousarray(nearest[:, 1:]), np.ascontiguousarray(normals),
                                    IN_PLANE_SIN ** 2)
    return apart > RANDOM_SIGNS_SHARE * parallel


def orient_given(nbh: Neighbourhood, normals: np.ndarray, closed_mesh: bool) -> tuple[np.ndarray, str | None]:
    """Given `normals` (in the sorted order) where nothing says which side was seen (module
    docstring): (normals, None) as given; or, with what was done, propagated where their signs
    were picked at random, or turned where they are a closed mesh's (`closed_mesh`: its faces'
    winding says which side is outside, and it has no inside to be seen from) and face
    inward as a whole."""
    unit = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    if signs_at_random(nbh, unit):
        orient_by_propagation(nbh, unit)
        return unit, "with signs that disagree between neighbours: oriented by MST propagation, outward"
    if closed_mesh and faces_inward(nbh.points, unit):
        return -normals, "a closed mesh's, facing inward as a whole: turned to face outward"
    return normals, None


@numba.njit(cache=True, inline="always")
def _sift_up(heap, place, key, at):  # pragma: no cover - compiled
    """Move heap[at] up the binary min-heap (by key) until its parent's key is not larger."""
    node = heap[at]
    while at > 0:
        up = (at - 1) // 2
        if key[heap[up]] <= key[node]:
            break
        heap[at] = heap[up]
        place[heap[at]] = at
        at = up
    heap[at] = node
    place[node] = at


@numba.njit(cache=True, inline="always")
def _sift_down(heap, place, key, size, at):  # pragma: no cover - compiled
    """Move heap[at] down the binary min-heap (by key) until no child's key is smaller."""
    node = heap[at]
    while True:
        child = 2 * at + 1
        if child >= size:
            break
        if child + 1 < size and key[heap[child + 1]] < key[heap[child]]:
            child += 1
        if key[heap[child]] >= key[node]:
            break
        heap[at] = heap[child]
        place[heap[at]] = at
        at = child
    heap[at] = node
    place[node] = at


@numba.njit(cache=True)
def _propagate(index, normals):  # pragma: no cover - compiled
    """Prim's minimum spanning forest of the symmetric kNN graph of `index` (N, k), edge weight
    1 - |n_i . n_j|, grown from the lowest unvisited point of each component, with an indexed
    binary heap (O(N) memory). Each point takes the sign agreeing with its tree parent's.
    Returns (sign (N,) int8, parent (N,) or -1 at a seed, component (N,), the number of
    components, the dot product with the parent (1 at a seed))."""
    n, k = index.shape
    # the reverse lists: j lists i when i lists j, so that the graph is symmetric
    starts = np.zeros(n + 1, np.int64)
    for i in range(n):
        for j in range(k):
            starts[index[i, j] + 1] += 1
    for i in range(n):
        starts[i + 1] += starts[i]
    cursor = starts[:-1].copy()
    listed_by = np.empty(n * k, np.int32)  # point indices, < 2^31 (neighbourhood.py)
    for i in range(n):
        for j in range(k):
            q = index[i, j]
            listed_by[cursor[q]] = i
            cursor[q] += 1
    sign = np.zeros(n, np.int8)
    parent = np.full(n, -1, np.int64)
    component = np.full(n, -1, np.int64)
    dots = np.ones(n)
    key = np.full(n, np.inf)
    towards = np.full(n, -1, np.int64)  # the visited point of the lightest edge to each point
    heap = np.empty(n, np.int64)
    place = np.full(n, -1, np.int64)  # position in the heap, -1 outside it
    done = np.zeros(n, np.bool_)
    components = 0
    for seed in range(n):
        if done[seed]:
            continue
        size = 1
        heap[0] = seed
        place[seed] = 0
        key[seed] = 0.0
        while size > 0:
            u = heap[0]
            place[u] = -1
            size -= 1
            if size > 0:
                heap[0] = heap[size]
                place[heap[0]] = 0
                _sift_down(heap, place, key, size, 0)
            done[u] = True
            component[u] = components
            via = towards[u]
            if via < 0:
                sign[u] = 1
            else:
                d = _row_dot(normals, u, via)
                parent[u] = via
                dots[u] = d
                sign[u] = sign[via] if d >= 0.0 else -sign[via]
            for side in range(2):
                count = k if side == 0 else starts[u + 1] - starts[u]
                for j in range(count):
                    v = index[u, j] if side == 0 else listed_by[starts[u] + j]
                    if done[v] or v == u:
                        continue
                    # + epsilon as in Hoppe's graph: parallel normals still make an edge
                    w = 1.0 - abs(_row_dot(normals, u, v)) + 1e-6
                    if w < key[v]:
                        key[v] = w
                        towards[v] = u
                        if place[v] < 0:
                            heap[size] = v
                            place[v] = size
                            size += 1
                        _sift_up(heap, place, key, place[v])
        components += 1
    return sign, parent, component, components, dots


def orient_by_propagation(nbh: Neighbourhood, normals: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Orient normals (in place) consistently over the kNN graph (Hoppe et al. 1992), each
    component outward, or facing `up` where it says which way is up; returns the mask of points
    whose sign decision was ambiguous."""
    pts = nbh.points
    n = len(pts)
    nearest = nbh.first(ORIENT_NEIGHBOURS + 1)
    if nearest.shape[1] == 1:  # single points: no graph
        return np.ones(n, bool)
    cols = np.ascontiguousarray(nearest[:, 1:])
    sign, parent, labels, count, dots = _propagate(cols, np.ascontiguousarray(normals, np.float64))
    sign = sign.astype(np.float64)
    ambiguous = (parent >= 0) & (np.abs(dots) < AMBIGUOUS_COS)
    # Each component as a whole faces outward: positive flux of (p - centroid).
    size = np.bincount(labels, minlength=count)
    centroid = np.stack([np.bincount(labels, pts[:, a], count) for a in range(3)], axis=1) / size[:, None]
    radial = np.einsum("ij,ij->i", normals, pts - centroid[labels])
    flux = np.bincount(labels, sign * radial, count)
    total = np.bincount(labels, np.abs(radial), count)
    spread = np.bincount(labels, np.linalg.norm(pts - centroid[labels], axis=1), count)
    no_outside = np.abs(flux) <= np.maximum(AMBIGUOUS_COS * total, 1e-9 * spread)
    if up is not None:
        rising = normals @ np.asarray(up, np.float64)
        vote = np.bincount(labels, sign * rising, count)
        level = np.abs(vote) <= AMBIGUOUS_COS * np.bincount(labels, np.abs(rising), count)
        flux = np.where(level, flux, vote)
        no_outside &= level
    sign = np.where(flux[labels] < 0, -sign, sign)
    # No outside (a flat patch, a single point): the whole component's orientation is a guess.
    ambiguous |= no_outside[labels]
    normals *= sign[:, None]
    return ambiguous


def oriented_normals(nbh: Neighbourhood, k: int, towards: np.ndarray | None,
                     progress: bool | None, adaptive: bool = False, up: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Unit normals (N, 3) float64 facing `towards` ((3,) or (N, 3), in the sorted order), or
    propagated if None, each component outward, or facing `up` (3,) where it rises or falls
    (module docstring); the ambiguous mask; the covariance eigenvalues (N, 3); whether the
    cloud is noisy. adaptive: a noisy cloud's normals take each point's scale (module
    docstring), a clean one's are refined by quadrics (`jets.py`); else PCA over k."""
    normals, ambiguous, eigenvalues = pca_normals(nbh, k, progress)
    chosen = scale_selected_normals(nbh, progress) if adaptive and is_noisy(eigenvalues) else None
    noisy = chosen is not None
    if noisy:
        normals, ambiguous, eigenvalues = chosen
    elif adaptive:
        normals = jet_normals(nbh.points, nbh.first(k), normals, ambiguous)
    if towards is not None:
        ambiguous |= orient_towards(normals, towards)
    else:
        ambiguous |= orient_by_propagation(nbh, normals, up)
    return normals, ambiguous, eigenvalues, noisy


def estimate_normals(positions: np.ndarray, k: int = NORMAL_NEIGHBOURS, viewpoint: np.ndarray | None = None,
                     workers: int = -1, progress: bool | None = None,
                     adaptive: bool = False) -> tuple[np.ndarray, int]:
    """PCA normals over the k nearest neighbours, oriented: (normals (N, 3) float32, ambiguous).

    viewpoint: sensor position (3,) or per-point sensor positions (N, 3) to face; None orients
    consistently by minimum-spanning-tree propagation, each component facing outward.
    ambiguous: the number of points whose orientation is a guess (see the module docstring).
    adaptive: if the cloud is noisy, each point's neighbourhood size is chosen from SCALES
    (Mitra & Nguyen's error bound, see the module docstring) instead of k; if it is clean, the
    normals of quadrics fitted over the k neighbours refine the PCA's (`jets.py`).
    progress: None shows a progress bar above chunked.PROGRESS_MIN_POINTS points; True/False
    force it.
    """
    pts = as_points(positions)
    nbh = Neighbourhood.build(pts, k, workers, progress)
    towards = None if viewpoint is None else nbh.sort(np.asarray(viewpoint, np.float64) - pts)
    normals, ambiguous, _, _ = oriented_normals(nbh, k, towards, progress, adaptive)
    return nbh.unsort(normals.astype(np.float32)), int(ambiguous.sum())
