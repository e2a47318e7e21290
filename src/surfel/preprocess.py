"""Preprocessing the splatting papers assume: normals, splat radii, tangent frames, ellipses
and Phong splatting's normal fields, from raw points.

* Normals: PCA over the k nearest neighbours (the eigenvector of the smallest eigenvalue of
  the neighbourhood covariance), oriented towards a viewpoint when one is known, otherwise
  consistently by propagation along a minimum spanning tree of the neighbour graph with
  weights 1 - |n_i . n_j| (Hoppe et al. 1992), each connected component seeded at its point
  farthest from its centroid with the normal pointing away from the centroid.
  `ambiguous` counts points whose orientation is a guess: a flip decided across an edge with
  |n_i . n_parent| < 0.1, or a neighbourhood without a clear normal direction (the two
  smallest covariance eigenvalues within a factor 1.5 of each other: a line or a blob).
* Radii: RADIUS_FACTOR times the mean distance to the RADIUS_NEIGHBORS nearest neighbours.
  On a regular sampling with spacing a that mean is about 1.2 a, and a disk must reach the
  farthest corner of its Voronoi cell, a / sqrt(3) = 0.58 a: 0.75 gives 0.9 a, enough overlap
  for irregular scans without the silhouette spill of larger splats. Capped at
  RADIUS_CAP times the median so that a few stray points (water, sky) do not become blobs.
* Tangent frames: two unit tangents perpendicular to each normal (Duff et al. 2017),
  scaled by the radius: the `axes` of a circular splat.
* Ellipses (Phong splatting, Botsch, Spernat & Kobbelt 2004): the neighbourhood's principal
  directions in the tangent plane; the minor semi-axis keeps the circular radius and the
  major one grows with the spread ratio (at most ELLIPSE_MAX_RATIO), so coverage only grows.
* Normal fields (ibid., survey eq. 8): N_j(u, v) = n_j + u alpha_j û_j + v beta_j v̂_j with
  (u, v) the neighbour's local coordinates in units of the semi-axes; alpha_j and beta_j by
  least squares over the neighbours' normals: alpha = sum(u_i (n_i . û)) / sum(u_i²).
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from tqdm import tqdm

from .cloud import PointCloud

CHUNK = 1_000_000
PROGRESS_MIN_POINTS = 1_000_000
RADIUS_NEIGHBORS = 8
RADIUS_FACTOR = 0.75
RADIUS_CAP = 4.0
ELLIPSE_MAX_RATIO = 2.0
AMBIGUOUS_DOT = 0.1
DEGENERATE_RATIO = 1.5


def _progress(n: int, progress: bool | None, desc: str):
    show = n > PROGRESS_MIN_POINTS if progress is None else progress
    return tqdm(total=n, desc=desc, unit="pt", unit_scale=True, disable=not show, leave=False)


def neighbors(positions: np.ndarray, k: int, workers: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the k nearest neighbours of every point, itself excluded."""
    k = min(k, len(positions) - 1)
    if k < 1:
        return np.zeros((len(positions), 0)), np.zeros((len(positions), 0), np.int64)
    dist, idx = cKDTree(positions).query(positions, k=k + 1, workers=workers)
    return dist[:, 1:], idx[:, 1:]


def pca_normals(positions: np.ndarray, idx: np.ndarray, progress: bool | None = None):
    """Unit normals (N, 3) and a degenerate-neighbourhood mask from neighbour indices (N, k)."""
    n = len(positions)
    normals = np.empty((n, 3), np.float32)
    degenerate = np.zeros(n, bool)
    with _progress(n, progress, "normals") as bar:
        for start in range(0, n, CHUNK):
            stop = min(start + CHUNK, n)
            nb = positions[idx[start:stop]]  # (c, k, 3)
            nb = np.concatenate([positions[start:stop, None], nb], axis=1)
            nb -= nb.mean(axis=1, keepdims=True)
            cov = np.einsum("nki,nkj->nij", nb, nb)
            values, vectors = np.linalg.eigh(cov)
            normals[start:stop] = vectors[:, :, 0]
            degenerate[start:stop] = values[:, 1] <= DEGENERATE_RATIO * values[:, 0]
            bar.update(stop - start)
    return normals, degenerate


@numba.njit(cache=True)
def _propagate(order, parents, normals, flip_dot):
    """Walk the BFS order: each node takes the sign that agrees with its (already oriented)
    parent. Returns the number of near-perpendicular decisions."""
    ambiguous = 0
    for node in order:
        parent = parents[node]
        if parent < 0:
            continue
        d = normals[node, 0] * normals[parent, 0] + normals[node, 1] * normals[parent, 1] + normals[node, 2] * normals[parent, 2]
        if d < 0:
            normals[node, 0] = -normals[node, 0]
            normals[node, 1] = -normals[node, 1]
            normals[node, 2] = -normals[node, 2]
        if abs(d) < flip_dot:
            ambiguous += 1
    return ambiguous


def orient_by_propagation(positions: np.ndarray, normals: np.ndarray, idx: np.ndarray) -> int:
    """Orient `normals` in place consistently over the neighbour graph; returns ambiguous flips."""
    n, k = idx.shape
    rows = np.repeat(np.arange(n), k)
    cols = idx.ravel()
    dots = np.abs(np.einsum("ij,ij->i", normals[rows], normals[cols]))
    weights = 1.0 - dots + 1e-6  # > 0: sparse matrices drop explicit zeros
    graph = sparse.coo_matrix((weights, (rows, cols)), shape=(n, n)).tocsr()
    tree = csgraph.minimum_spanning_tree(graph)
    count, labels = csgraph.connected_components(tree, directed=False)
    # Seed of each component: its point farthest from the component centroid, normal outward.
    centroid = np.zeros((count, 3))
    np.add.at(centroid, labels, positions)
    centroid /= np.bincount(labels, minlength=count)[:, None]
    offset = positions - centroid[labels]
    reach = np.einsum("ij,ij->i", offset, offset)
    seeds = np.full(count, -1)
    order_by_reach = np.lexsort((reach, labels))
    seeds[labels[order_by_reach]] = order_by_reach  # the last write per label is the farthest point
    outward = np.einsum("ij,ij->i", normals[seeds], offset[seeds]) < 0
    normals[seeds[outward]] *= -1
    # One BFS over all components: a virtual root joined to every seed.
    root = n
    tree = tree.tocoo()
    edges_r = np.concatenate([tree.row, np.full(count, root)])
    edges_c = np.concatenate([tree.col, seeds])
    forest = sparse.coo_matrix((np.ones(len(edges_r)), (edges_r, edges_c)), shape=(n + 1, n + 1)).tocsr()
    order, parents = csgraph.breadth_first_order(forest, root, directed=False, return_predecessors=True)
    parents = parents[:n].astype(np.int64)
    parents[parents == root] = -1
    parents[parents < 0] = -1
    order = order[order != root].astype(np.int64)
    return int(_propagate(order, parents, normals, AMBIGUOUS_DOT))


def estimate_normals(positions: np.ndarray, k: int = 16, viewpoint=None, workers: int = -1,
                     progress: bool | None = None) -> tuple[np.ndarray, int]:
    """PCA normals over k neighbours, oriented; returns (normals (N, 3) float32, ambiguous)."""
    positions = np.asarray(positions, np.float64)
    local = positions - positions.mean(axis=0)
    _, idx = neighbors(local, k, workers)
    if idx.shape[1] < 2:
        return np.tile(np.float32([0, 0, 1]), (len(positions), 1)), len(positions)
    normals, degenerate = pca_normals(local, idx, progress)
    if viewpoint is not None:
        towards = np.asarray(viewpoint, np.float64) - positions
        flip = np.einsum("ij,ij->i", normals, towards) < 0
        normals[flip] *= -1
        ambiguous = int(degenerate.sum())
    else:
        ambiguous = orient_by_propagation(local, normals, idx) + int(degenerate.sum())
    return normals, ambiguous


def estimate_radii(positions: np.ndarray, k: int = RADIUS_NEIGHBORS, workers: int = -1) -> np.ndarray:
    """Splat radii (N,) float32 from the mean distance to the k nearest neighbours."""
    positions = np.asarray(positions, np.float64)
    dist, _ = neighbors(positions - positions.mean(axis=0), k, workers)
    if dist.shape[1] == 0:
        return np.ones(len(positions), np.float32)
    radii = RADIUS_FACTOR * dist.mean(axis=1)
    positive = radii > 0
    floor = radii[positive].min() if positive.any() else 1.0
    radii = np.maximum(radii, floor)  # duplicates still get a splat
    return np.minimum(radii, RADIUS_CAP * np.median(radii)).astype(np.float32)


def tangent_frames(normals: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(N, 2, 3) float32 tangent axes scaled by the radius (Duff et al. 2017, branch-free)."""
    n = np.asarray(normals, np.float64)
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    r = np.asarray(radii, np.float64)[:, None]
    return np.stack([t * r, s * r], axis=1).astype(np.float32)


def fit_ellipses(positions: np.ndarray, normals: np.ndarray, radii: np.ndarray, k: int = 12,
                 workers: int = -1) -> np.ndarray:
    """Elliptical splat axes (N, 2, 3) aligned with the neighbourhood's tangent spread."""
    positions = np.asarray(positions, np.float64)
    _, idx = neighbors(positions - positions.mean(axis=0), k, workers)
    frames = tangent_frames(normals, np.ones(len(positions))).astype(np.float64)
    axes = np.empty((len(positions), 2, 3), np.float32)
    for start in range(0, len(positions), CHUNK):
        stop = min(start + CHUNK, len(positions))
        offset = positions[idx[start:stop]] - positions[start:stop, None]
        uv = np.einsum("nkj,ntj->nkt", offset, frames[start:stop])  # (c, k, 2) tangent coordinates
        cov = np.einsum("nki,nkj->nij", uv, uv)
        values, vectors = np.linalg.eigh(cov)  # ascending: minor, major
        ratio = np.sqrt(np.maximum(values[:, 1], 1e-30) / np.maximum(values[:, 0], 1e-30))
        ratio = np.clip(ratio, 1.0, ELLIPSE_MAX_RATIO)
        major = np.einsum("nt,ntj->nj", vectors[:, :, 1], frames[start:stop])
        minor = np.einsum("nt,ntj->nj", vectors[:, :, 0], frames[start:stop])
        r = np.asarray(radii[start:stop], np.float64)[:, None]
        axes[start:stop, 0] = major * r * ratio[:, None]
        axes[start:stop, 1] = minor * r
    return axes


def fit_normal_field(positions: np.ndarray, normals: np.ndarray, axes: np.ndarray, k: int = 12,
                     workers: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Phong splatting's normal-field slopes (alpha, beta), each (N,) float32 (survey eq. 8)."""
    positions = np.asarray(positions, np.float64)
    _, idx = neighbors(positions - positions.mean(axis=0), k, workers)
    alpha = np.empty(len(positions), np.float32)
    beta = np.empty(len(positions), np.float32)
    for start in range(0, len(positions), CHUNK):
        stop = min(start + CHUNK, len(positions))
        ax = np.asarray(axes[start:stop], np.float64)  # (c, 2, 3)
        length2 = np.einsum("ntj,ntj->nt", ax, ax)
        offset = positions[idx[start:stop]] - positions[start:stop, None]
        local = np.einsum("nkj,ntj->nkt", offset, ax) / length2[:, None, :]  # (u, v) per neighbour
        nb_normals = np.asarray(normals, np.float64)[idx[start:stop]]
        nb_normals *= np.sign(np.einsum("nkj,nj->nk", nb_normals, normals[start:stop]))[..., None]
        unit_axes = ax / np.sqrt(length2)[..., None]
        tilt = np.einsum("nkj,ntj->nkt", nb_normals, unit_axes)  # (n_i . û, n_i . v̂)
        slope = (local * tilt).sum(axis=1) / np.maximum((local**2).sum(axis=1), 1e-12)
        alpha[start:stop], beta[start:stop] = slope[:, 0], slope[:, 1]
    return alpha, beta


def prepare(cloud: PointCloud, *, k_normals: int = 16, viewpoint=None, elliptical: bool = False,
            normal_field: bool = False, progress: bool | None = None) -> tuple[PointCloud, dict]:
    """Fill in what the cloud lacks; the report says what was estimated."""
    report: dict = {}
    changes: dict = {}
    normals = cloud.normals
    if normals is None:
        normals, ambiguous = estimate_normals(cloud.positions, k_normals, viewpoint, progress=progress)
        changes["normals"] = normals
        report["normals"] = f"estimated (PCA, k={k_normals}, " + ("towards viewpoint)" if viewpoint is not None else "propagated)")
        report["ambiguous_normals"] = ambiguous
    radii = cloud.radii
    if radii is None:
        radii = estimate_radii(cloud.positions)
        changes["radii"] = radii
        report["radii"] = f"estimated ({RADIUS_FACTOR} x mean distance to {RADIUS_NEIGHBORS} neighbours)"
    axes = cloud.axes
    if axes is None:
        axes = fit_ellipses(cloud.positions, normals, radii) if elliptical else tangent_frames(normals, radii)
        changes["axes"] = axes
        report["axes"] = "fitted ellipses" if elliptical else "circular tangent frames"
    if normal_field and "phong_alpha" not in cloud.extras:
        alpha, beta = fit_normal_field(cloud.positions, normals, axes)
        changes["extras"] = {**cloud.extras, "phong_alpha": alpha, "phong_beta": beta}
        report["normal_field"] = "fitted (least squares over 12 neighbours)"
    return (cloud.with_(**changes) if changes else cloud), report
