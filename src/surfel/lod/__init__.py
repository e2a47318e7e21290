"""Level of detail: point-tree hierarchies and sequential point trees.

Dachsbacher, Vogelgsang & Stamminger 2003, "Sequential point trees" (survey section 2.2):
`build` makes the octree hierarchy with its errors, `traverse` the reference recursive
selection, `sequential` the GPU-friendly list with the CPU prefix and the per-point
[r_min, r_max] test (surfel/gl/lod.glsl is its shader twin), `format` the file.
Beyond memory: `outofcore` builds a partitioned hierarchy in a bounded memory budget (its
workers' kernels loaded by `worker_warm_up`),
`lazy` reads it as far as a view needs, `copc`/`copc_write` read and write COPC files, and
`source` is the protocol both lazy readers follow.
"""

from .build import LodTree, build_lod
from .format import FORMAT_VERSION, build_command, load_lod, save_lod
from .sequential import (
                         as_sequential,
                         frame_parameters,
                         is_sequential,
                         lod_scale,
                         lod_selected,
                         lod_subset,
                         near_distance,
                         prefix_count,
                         select_sequential,
                         sequential_order,
                         to_sequential_cloud,
)
from .source import LodSource, is_source, open_source
from .traverse import select_recursive

__all__ = ["LodTree", "build_lod", "FORMAT_VERSION", "build_command", "load_lod", "save_lod",
           "as_sequential", "frame_parameters", "is_sequential", "lod_scale", "lod_selected",
           "lod_subset", "near_distance", "prefix_count", "select_sequential", "sequential_order",
           "to_sequential_cloud", "select_recursive", "LodSource", "is_source", "open_source"]
