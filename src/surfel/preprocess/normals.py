"""Normals: PCA over the k nearest neighbours, oriented towards a viewpoint or by propagation.

Direction: the eigenvector of the smallest eigenvalue of the neighbourhood covariance
C = 1/k sum_j (q_j - p)(q_j - p)^T - s s^T / k^2, s = sum_j (q_j - p) (the one-pass formula on
offsets to the point itself, so that it subtracts small numbers).

Orientation: towards a viewpoint when the sensor position is known; otherwise consistently by
propagation (Hoppe, DeRose, Duchamp, McDonald & Stuetzle 1992, "Surface reconstruction from
unorganized points"): a minimum spanning tree of the kNN graph (ORIENT_NEIGHBOURS per point;
Hoppe's Riemannian graph adds the Euclidean MST to connect everything, here each connected
component is oriented on its own) with edge weights 1 - |n_i . n_j| (so flips propagate
across nearly parallel normals first), walked breadth-first, every node taking the sign that
agrees with its parent. Each connected component then faces outward as a whole: it is flipped
when the flux sum_i n_i . (p_i - centroid) is negative, which by the divergence theorem (the
flux of p - c through a closed surface is 3 x its volume) is the outward choice for closed
scans, and does not hinge on one seed point's normal.

`ambiguous` counts the points whose orientation is a guess:
  * degenerate neighbourhoods without a tangent plane: the two smallest covariance
    eigenvalues within a factor 1/DEGENERATE_RATIO of each other (a line, a blob, the
    crossing of two surfaces), or a neighbourhood that is a line or a single point;
  * sign decisions taken against a nearly perpendicular reference, |cos| < AMBIGUOUS_COS:
    the tree parent's normal, or the direction to the viewpoint;
  * every point of a component without an outside: |flux| < AMBIGUOUS_COS x
    sum_i |n_i . (p_i - c)| (a flat patch, a single point), whose sign is arbitrary.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from .chunked import map_chunks
from .neighbourhood import Neighbourhood, as_points

NORMAL_NEIGHBOURS = 16   # neighbours of the PCA
AMBIGUOUS_COS = 0.1      # |cos| below which a sign decision is a guess
DEGENERATE_RATIO = 0.5   # lambda_0 > this x lambda_1: no dominant normal direction
ORIENT_NEIGHBOURS = 8    # edges per point of the propagation graph: half the MST time of 15,
                         # the same orientations on the bunny


@numba.njit(parallel=True, cache=True)
def _covariances(points, index, start):  # pragma: no cover - compiled
    """Covariance (m, 3, 3) of the neighbourhood of each point start + i (no gathered
    (m, k, 3) array)."""
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


def pca_normals(nbh: Neighbourhood, k: int, progress: bool | None) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented unit normals (N, 3) float64 and the degenerate-neighbourhood mask."""
    index = nbh.first(k)

    def pca(start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        values, vectors = np.linalg.eigh(_covariances(nbh.points, index[start:stop], start))
        # No tangent plane: the two smallest spreads alike (line with noise, blob, crossing
        # surfaces), or the neighbourhood is a line or a point (both nearly zero).
        degenerate = (values[:, 0] > DEGENERATE_RATIO * values[:, 1]) | (values[:, 1] <= 1e-12 * values[:, 2])
        return vectors[:, :, 0], degenerate  # eigenvalues ascending: the normal direction first

    return map_chunks(pca, len(nbh.points), progress, "normals")


def orient_towards(normals: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Flip normals (in place) to face `towards` ((3,) or (N, 3)); returns the ambiguous mask."""
    towards = np.broadcast_to(towards, normals.shape)
    dot = np.einsum("ij,ij->i", normals, towards)
    normals[dot < 0] *= -1
    return np.abs(dot) < AMBIGUOUS_COS * np.linalg.norm(towards, axis=1)


def _spanning_forest(nbh: Neighbourhood, normals: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """The minimum spanning forest of the propagation graph: (components, the component of
    each point, breadth-first order, each point's parent or -1 at a component's seed)."""
    n = len(nbh.points)
    cols = np.ascontiguousarray(nbh.first(ORIENT_NEIGHBOURS + 1)[:, 1:])
    kg = cols.shape[1]
    # + epsilon: a weight of 0 would be no edge in a sparse graph
    weights = map_chunks(lambda start, stop: 1.0 - np.abs(np.einsum("ij,ikj->ik", normals[start:stop],
                                                                    normals[cols[start:stop]])) + 1e-6, n)
    # Rows are sorted already: build the CSR directly instead of sorting N k COO entries.
    graph = sparse.csr_matrix((weights.ravel(), cols.ravel(), np.arange(0, n * kg + 1, kg)), shape=(n, n))
    tree = csgraph.minimum_spanning_tree(graph).tocoo()
    count, labels = csgraph.connected_components(tree, directed=False)
    seeds = np.unique(labels, return_index=True)[1]  # any point will do: the flux decides the sign
    # One breadth-first walk over all components: a virtual root (node n) joined to every seed.
    root = n
    rows = np.concatenate([tree.row, np.full(count, root, tree.row.dtype)])
    cols_t = np.concatenate([tree.col, seeds.astype(tree.col.dtype)])
    forest = sparse.csr_matrix((np.ones(len(rows)), (rows, cols_t)), shape=(n + 1, n + 1))
    order, parent = csgraph.breadth_first_order(forest, root, directed=False, return_predecessors=True)
    parent = parent[:n].astype(np.int64)
    parent[parent == root] = -1
    return count, labels, order[order != root], parent


def orient_by_propagation(nbh: Neighbourhood, normals: np.ndarray) -> np.ndarray:
    """Orient normals (in place) consistently over the kNN graph (Hoppe et al. 1992), each
    component outward; returns the mask of points whose sign decision was ambiguous."""
    pts = nbh.points
    n = len(pts)
    if nbh.first(ORIENT_NEIGHBOURS + 1).shape[1] == 1:  # single points: no graph
        return np.ones(n, bool)
    count, labels, order, parent = _spanning_forest(nbh, normals)
    has_parent = parent >= 0

    def parent_dots(start: int, stop: int) -> np.ndarray:
        p = np.where(has_parent[start:stop], parent[start:stop], np.arange(start, stop))
        return np.einsum("ij,ij->i", normals[start:stop], normals[p])

    dots = map_chunks(parent_dots, n)
    relative = np.where(dots < 0, -1, 1).astype(np.int8)
    ambiguous = has_parent & (np.abs(dots) < AMBIGUOUS_COS)
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


def oriented_normals(nbh: Neighbourhood, k: int, towards: np.ndarray | None,
                     progress: bool | None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 3) float64 facing `towards` ((3,) or (N, 3), in the sorted order), or
    propagated and outward if None; and the ambiguous mask."""
    normals, ambiguous = pca_normals(nbh, k, progress)
    if towards is not None:
        ambiguous |= orient_towards(normals, towards)
    else:
        ambiguous |= orient_by_propagation(nbh, normals)
    return normals, ambiguous


def estimate_normals(positions: np.ndarray, k: int = NORMAL_NEIGHBOURS, viewpoint: np.ndarray | None = None,
                     workers: int = -1, progress: bool | None = None) -> tuple[np.ndarray, int]:
    """PCA normals over the k nearest neighbours, oriented: (normals (N, 3) float32, ambiguous).

    viewpoint: sensor position (3,) or per-point sensor positions (N, 3) to face; None orients
    consistently by minimum-spanning-tree propagation, each component facing outward.
    ambiguous: the number of points whose orientation is a guess (see the module docstring).
    progress: None shows a progress bar above chunked.PROGRESS_MIN_POINTS points; True/False
    force it.
    """
    pts = as_points(positions)
    nbh = Neighbourhood.build(pts, k, workers, progress)
    towards = None if viewpoint is None else nbh.sort(np.asarray(viewpoint, np.float64) - pts)
    normals, ambiguous = oriented_normals(nbh, k, towards, progress)
    return nbh.unsort(normals.astype(np.float32)), int(ambiguous.sum())
