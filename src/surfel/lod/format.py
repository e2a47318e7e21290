"""The LOD file: a sequential point tree stored as an uncompressed NumPy .npz (format 1).

A LOD file is an ordinary surfel point-cloud NPZ (`surfel.io.npz`), so `surfel.io.load`
reads it as a cloud whose attributes carry the LOD data; by convention it is named *.lod.npz.
Every array has one row per tree node, in sequential order (r_max decreasing at 8-bit
mantissa resolution, see sequential.py):

    positions    (M, 3) float64   node centre (leaves: the input point)
    normals      (M, 3) float32   unit normal (inner nodes: area-weighted average)
    colors       (M, 3) float32   RGB in [0, 1] (absent if the input had none)
    radii        (M,)   float32   disk radius (inner nodes: encloses all children's disks)
    axes         (M, 2, 3) float32 tangent axes scaled to the ellipse semi-axes
                                  (inner nodes: circular)
    lod_emin     (M,)   float32   e_g of the node: r_min = lod_emin * k
    lod_emax     (M,)   float32   e_g of the parent: r_max = lod_emax * k (the root stores
                                  the largest float32 for infinity); r_max_bucket(lod_emax)
                                  is non-increasing
    lod_dparent  (M,)   float32   distance from the node's centre to its parent's (0: root)
    lod_dsuffix  (M,)   float32   max of lod_dparent over this row and all later ones
    clip_lines   (M, 2, 3) float32 leaves' clip lines at sharp features (absent if the input
                                  had none; inner nodes cut nothing)
    NAME         (M, ...) any     each scanner attribute of the input in its own dtype
                                  (inner nodes: aggregated, build.py)
    surfel_schema ()    str       the attributes' schema as JSON (surfel.attributes): their
                                  dtypes, shapes and kinds
    surfel_lod_version ()  int64  FORMAT_VERSION
    geospatial   ()     bool      the input's up axis is +Z (LAS/LAZ)

with k = fy / eps per frame (`sequential.py` gives the selection rule). Errors are in the
units of the positions. Scalars are ignored by the generic NPZ reader; nothing is pickled,
and files are written to a temporary name first and renamed, so a reader never sees half
a file.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ..files import write_atomically, write_json
from ..io.npz import cloud_arrays, read_npz
from .build import LodTree, build_lod, morton_order
from .sequential import is_sequential, r_max_bucket, to_sequential_cloud

FORMAT_VERSION = 1


def save_lod(lod: LodTree | PointCloud, path: str | os.PathLike) -> None:
    """Write a tree (sequentialised first) or a sequential cloud as a LOD file."""
    seq = to_sequential_cloud(lod) if isinstance(lod, LodTree) else lod
    if not is_sequential(seq):
        raise ValueError("save_lod needs a LodTree or a cloud from to_sequential_cloud")
    arrays = {**cloud_arrays(seq), "surfel_lod_version": np.int64(FORMAT_VERSION)}
    write_atomically(path, lambda file: np.savez(file, **arrays))


def load_lod(path: str | os.PathLike) -> PointCloud:
    """Read a LOD file as a sequential cloud (InputError if it is not one)."""
    path = str(path)
    cloud = read_npz(path)
    with np.load(path, allow_pickle=False) as archive:
        if "surfel_lod_version" not in archive.files:
            raise InputError(path, "not a surfel LOD file (no surfel_lod_version)")
        version = int(archive["surfel_lod_version"])
    if version != FORMAT_VERSION:
        raise InputError(path, f"LOD format version {version} is not supported (need {FORMAT_VERSION})")
    if not is_sequential(cloud) or cloud.normals is None or cloud.axes is None:
        raise InputError(path, "LOD file lacks normals, axes or lod_* arrays")
    if np.any(np.diff(r_max_bucket(cloud.attributes["lod_emax"]).astype(np.int32)) > 0):
        raise InputError(path, "LOD file is not sorted by lod_emax")
    return cloud


def build_command(in_path: str | os.PathLike, out_path: str | os.PathLike,
                  stats_path: str | os.PathLike | None = None, *, progress: bool | None = None) -> dict:
    """`surfel lod build IN -o OUT [--stats FILE.json]`: load, complete, build, save.

    Stats: points, nodes, ms (building the hierarchy and sequentialising it; not file I/O,
    attribute estimation, or jit_ms: loading the compiled numba kernels, once per process),
    points_per_s (points / ms).
    """
    from ..io import load
    from ..preprocess import complete

    cloud = load(in_path)
    # in Morton order, the completion and the tree gather from nearby rows (the tree's order
    # does not depend on the input's); the input's order is not kept alive beside it
    cloud = cloud.take(morton_order(cloud.positions))
    cloud, estimated = complete(cloud)
    points = len(cloud)
    start = time.perf_counter()
    warm_up()
    jit_ms = (time.perf_counter() - start) * 1000
    start = time.perf_counter()
    tree = build_lod(cloud, progress=progress)
    del cloud  # the input is not needed while the tree is sequentialised: lower peak memory
    seq = to_sequential_cloud(tree)
    ms = (time.perf_counter() - start) * 1000
    nodes = len(tree)
    del tree
    save_lod(seq, out_path)
    stats = {"points": points, "nodes": nodes, "ms": round(ms, 3),
             "points_per_s": round(points / max(ms / 1000, 1e-9)), "jit_ms": round(jit_ms, 3)}
    if estimated:
        stats["estimated"] = estimated
    if stats_path is not None:
        write_json(stats_path, stats)
    return stats


def warm_up() -> LodTree:
    """Load (or compile) the numba kernels and start their thread pool on a tiny tree; the tree."""
    positions = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    tiny = PointCloud(positions, normals=np.tile([0.0, 0, 1], (3, 1)), colors=np.full((3, 3), 0.5),
                      axes=np.tile([[[0.5, 0, 0], [0, 0.5, 0]]], (3, 1, 1)))
    tree = build_lod(tiny, progress=False)
    to_sequential_cloud(tree)
    return tree
