"""Sequential point trees (Dachsbacher, Vogelgsang & Stamminger 2003; survey section 2.2.2).

The recursive traversal (`traverse.select_recursive`) refines a node while its projected
geometric error e_g f / r exceeds the threshold eps pixels (f = camera.fy, r = distance
from the eye to the node). With k = f / eps the node is refined iff r < e_g k, so a node
is drawn iff

    r_min = e_g(node) k  <=  r  <  r_max = e_g(parent) k                            (1)

(leaves: e_g = 0, r_min = 0; the root: parent error inf, r_max = inf, stored as the largest
float32). Because e_g is
monotone along every root-to-leaf path, for one common r exactly one node of each path
passes (1). `e_g(node)` and `e_g(parent)` are view independent and stored per point as the
extras `lod_emin` and `lod_emax`; k is chosen per frame.

Sequentialisation: all nodes are listed by r_max decreasing (by lod_emax; see "Order and
prefix" below). For a view the CPU draws only a prefix of the list and the vertex shader
applies the test per point with the point's own distance r, culling the rest (`lod.glsl`).

Per-point distances: in the GPU test a node and its parent see different r (the paper's
simplification), so a leaf's path could have its parent rejected (r_parent >= r_max) and
the child rejected too (r_child >= r_max), opening a hole. We therefore test the upper
bound against the parent's smallest possible distance, r - |c - c_parent|:

    e_g(node) k  <=  r     and     r - d_parent  <  e_g(parent) k                    (2)

Whenever the recursive traversal refines the parent (r_parent < e_g(parent) k), (2)'s
upper test passes for the child too (r_parent >= r - d_parent by the triangle
inequality), so on every path the first
non-refined node is drawn: no holes, at the price of a thin band of overlapping parents and
children (a superset of the recursive selection). `lod_dparent` stores d_parent.

Order and prefix: the list is sorted by r_max decreasing at the resolution of 8 mantissa
bits (e_g(parent) rounded up: `r_max_bucket`), and by node index within a bucket, which
keeps siblings and neighbours together in memory (sorting on the exact value scatters
them). A node can pass (2) only if r_near - d_parent < e_g(parent) k, where r_near is the
smallest eye distance to the model's bounding sphere (the paper's conservative choice).
With `lod_dsuffix[j]` = max of lod_dparent over positions >= j and ceil(e) the rounded-up
lod_emax, every later node i > j has lod_emax[i] <= ceil(lod_emax[j]), so
f(j) = ceil(lod_emax[j]) k + lod_dsuffix[j] is non-increasing and bounds them all: the
prefix ends at the first j with f(j) <= r_near, found by binary search.

Orthographic cameras have no distance: the projected error is e_g p (p = pixels per world
unit), and a node is drawn iff e_g(node) p <= eps < e_g(parent) p, which is (1) with r = 1,
k = p / eps and d_parent = 0.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..cloud import PointCloud, scatter_rows, take_rows
from .build import ROOT_PARENT_ERROR, LodTree, build_lod

EXTRAS = ("lod_emin", "lod_emax", "lod_dparent", "lod_dsuffix")


BUCKET_SHIFT = 15  # float32 bits below the 8 mantissa bits the list is sorted on


def r_max_bucket(error: np.ndarray) -> np.ndarray:
    """Non-negative float32 errors rounded up to 8 mantissa bits, as uint16 sort keys."""
    bits = np.asarray(error, np.float32).view(np.uint32).astype(np.uint64)
    return ((bits + (1 << BUCKET_SHIFT) - 1) >> BUCKET_SHIFT).astype(np.uint16)


def _bucket_ceiling(error: float) -> float:
    """The value of r_max_bucket(error): error rounded up to 8 mantissa bits (inf past FLT_MAX)."""
    key = int(r_max_bucket(np.float32(error)))
    return float(np.uint32(key << BUCKET_SHIFT).view(np.float32))


def sequential_order(tree: LodTree) -> np.ndarray:
    """Node indices sorted by r_max (parent error) bucket decreasing, the root first.

    Siblings share their r_max, so ordering the inner nodes and listing each one's children
    in that order sorts all nodes while sorting only the inner ones; the stable radix sort
    on 16-bit keys keeps node indices ascending within a bucket.
    """
    keys = ~r_max_bucket(tree.e_g[tree.n_leaves:])  # descending
    inner = tree.n_leaves + np.argsort(keys, kind="stable")
    return np.concatenate(([tree.root], tree.children_of(inner)))


def to_sequential_cloud(tree: LodTree) -> PointCloud:
    """All nodes of `tree` as one cloud in sequential order, with its attributes and the LOD
    extras."""
    order = sequential_order(tree)
    destination = np.empty(len(order), np.int64)
    destination[order] = np.arange(len(order))

    def permuted(values: np.ndarray | None, dtype=None) -> np.ndarray | None:
        return None if values is None else scatter_rows(np.asarray(values, dtype), destination)

    e_g = np.asarray(tree.e_g, np.float32)  # each node's own error, and its parent's
    parent = permuted(tree.parent)
    emax = np.where(parent >= 0, take_rows(e_g, np.maximum(parent, 0)), np.float32(ROOT_PARENT_ERROR))
    dparent = permuted(tree.d_parent, np.float32)
    dsuffix = np.maximum.accumulate(dparent[::-1])[::-1]
    attributes = {name: permuted(values) for name, values in tree.attributes.items()}
    attributes.update(lod_emin=permuted(e_g), lod_emax=emax, lod_dparent=dparent,
                      lod_dsuffix=dsuffix)
    if tree.clip_lines is not None:
        attributes["clip_lines"] = permuted(tree.clip_lines, np.float32)
    if tree.screen_facing is not None:
        attributes["screen_facing"] = permuted(tree.screen_facing, np.float32)
    return PointCloud(permuted(tree.positions, np.float64), normals=permuted(tree.normals, np.float32),
                      colors=permuted(tree.colors, np.float32), radii=permuted(tree.radii, np.float32),
                      axes=permuted(tree.axes, np.float32), attributes=attributes, kinds=tree.kinds,
                      geospatial=tree.geospatial)


def is_sequential(cloud: PointCloud) -> bool:
    return all(name in cloud.attributes for name in EXTRAS)


def lod_scale(camera: Camera, epsilon: float) -> float:
    """k of (1): fy / eps for perspective cameras, pixels-per-unit / eps for orthographic.

    Uses the output image's focal length: eps is in output pixels whatever the supersampling.
    """
    if not epsilon > 0:
        raise ValueError(f"LOD error threshold must be positive, got {epsilon}")
    return camera.pixel_scale() / epsilon


def near_distance(cloud: PointCloud, camera: Camera) -> float:
    """Smallest eye distance to the cloud's bounding sphere (0 inside it); 1 when orthographic."""
    if camera.ortho_height is not None:
        return 1.0
    return max(float(np.linalg.norm(camera.eye - cloud.center)) - cloud.bounding_radius, 0.0)


def prefix_count(seq: PointCloud, r_near: float, k: float, *, orthographic: bool = False) -> int:
    """Length of the list prefix that may pass (2) for any r >= r_near (binary search)."""
    return prefix_length(seq.attributes["lod_emax"], seq.attributes["lod_dsuffix"], r_near, k,
                         orthographic=orthographic)


def prefix_length(emax, dsuffix, r_near: float, k: float, *, orthographic: bool = False) -> int:
    """`prefix_count` over the lod_emax and lod_dsuffix arrays themselves (memory-mapped ones
    too: the search touches log n of their rows)."""
    lo, hi = 0, len(emax)
    while lo < hi:  # first j with f(j) <= r_near; f is non-increasing
        mid = (lo + hi) // 2
        bound = _bucket_ceiling(emax[mid]) * k + (0.0 if orthographic else float(dsuffix[mid]))
        if bound <= r_near:
            hi = mid
        else:
            lo = mid + 1
    return lo


def frame_parameters(seq: PointCloud, camera: Camera, epsilon: float) -> tuple[int, float]:
    """What a GPU renderer needs per frame: (prefix length to draw, k for the u_lod_k uniform)."""
    k = lod_scale(camera, epsilon)
    ortho = camera.ortho_height is not None
    return prefix_count(seq, near_distance(seq, camera), k, orthographic=ortho), k


def view_distances(positions: np.ndarray, camera: Camera) -> np.ndarray:
    """Euclidean eye distances r of positions (float64)."""
    return np.linalg.norm(positions - camera.eye, axis=1)


def lod_selected(view_distance, emin, emax, dparent, k: float) -> np.ndarray:
    """Test (2) elementwise: the numpy twin of lod_selected() in lod.glsl."""
    return (emin * k <= view_distance) & (view_distance - dparent < emax * k)


def select_sequential(seq: PointCloud, camera: Camera, epsilon: float) -> np.ndarray:
    """Boolean mask over `seq`: what the CPU prefix plus the vertex-shader test (2) draw."""
    count, k = frame_parameters(seq, camera, epsilon)
    ortho = camera.ortho_height is not None
    mask = np.zeros(len(seq), bool)
    emin = seq.attributes["lod_emin"][:count].astype(np.float64)
    emax = seq.attributes["lod_emax"][:count].astype(np.float64)
    if ortho:  # r = 1, no parent distance (see the module docstring)
        mask[:count] = lod_selected(1.0, emin, emax, 0.0, k)
    else:
        r = view_distances(seq.positions[:count], camera)
        mask[:count] = lod_selected(r, emin, emax, seq.attributes["lod_dparent"][:count].astype(np.float64), k)
    return mask


def as_sequential(cloud: PointCloud, *, progress: bool | None = None) -> PointCloud:
    """`cloud` itself if it is a sequential point tree (a loaded LOD file), else its tree
    built and sequentialised (once per cloud by `rendering.Renderer`): how renderers apply
    --lod-error to any input."""
    if is_sequential(cloud):
        return cloud
    return to_sequential_cloud(build_lod(cloud, progress=progress))


def lod_subset(seq: PointCloud, camera: Camera, epsilon: float) -> PointCloud:
    """The selected nodes only, as a plain cloud with every attribute but the LOD extras: LOD
    for backends without vertex shaders (the Renderer keeps the last one per cloud, so
    repeated renders of one view reuse it)."""
    mask = select_sequential(seq, camera, epsilon)
    subset = PointCloud(seq.positions[mask], normals=seq.normals[mask],
                        colors=None if seq.colors is None else seq.colors[mask],
                        radii=seq.radii[mask], axes=seq.axes[mask], geospatial=seq.geospatial,
                        source=seq.source, kinds=seq.schema.kinds,
                        attributes={name: values[mask] for name, values in seq.attributes.items()
                                    if name not in EXTRAS})
    return subset
