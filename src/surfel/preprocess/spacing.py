"""The sampling bound: no splat reaches farther than the sampling around it warrants.

A covering radius (cells.py) is what a surface needs to be hole-free, but it trusts the cell:
at the edge of a sparse region (the few returns over water, a wire, a bird, the fringe of a
scan) the cell is open or huge, and its disk invents surface far past the data. So every
estimated semi-axis is capped at

    BOUND_FACTOR x s,    s = min(s_local, s_ref)

  s_local  the local spacing: the median distance to the point's LOCAL_NEIGHBOURS nearest
           distinct neighbours (coincident returns, common in quantised LAS files, do not
           count);
  s_ref    the reference spacing of the acquisition, where it has one:
           * given by the caller: a COPC file's octree spacing at each point's level (lod/copc.py);
           * a known sensor position (terrestrial scans: E57 poses, --sensor): the spacing of
             a scan grows with the range r from its sensor, s_ref = alpha r, with alpha the
             scan's angular step, the median of s_local / r over the scan;
           * otherwise a geospatial cloud (an airborne tile, sampled evenly by design): the
             median horizontal nearest-neighbour distance over the tile (of REFERENCE_SAMPLE
             points spread over it), the point spacing of the survey, s_h; on the points
             with a tangent plane (the surfaces, structure.py) at least

                 ONE_LAYER_RATIO x median{s_local over those points}

             On one surface the median nearest-neighbour distance is 0.57 (samples at random)
             to 1 (a grid) times the median s_local, so an s_h below that says that surfaces
             overlap seen from above: the returns of one pulse stacked through a canopy, the
             layers and steep sides of an object in a terrestrial scan or a photogrammetric
             cloud stored as LAS. There s_h understates each surface's own spacing (4.7 times
             on a bunny sampled at random), and its bound cut the splats of well-sampled
             surfaces until the far side showed through, as dark specks under eye-dome
             lighting. The floor is a single layer's ratio, not the least one: a bound of
             2.5 x 0.57 s_local still cuts the largest cells of samples at random. On one
             layer it lets a splat reach at most 2.5 x 0.7 / 0.57 = 3.1 s_h, inside the
             4 s_h past which a pixel is far from every return (lidar_readability.py in
             benchmarks/). Points without a tangent plane (vegetation, wires) keep s_h, and
             so do the surfaces of a tile whose s_h is above the floor, or where most points
             have no tangent plane: there the few that do are patches scattered through
             vegetation, sparse among its returns, and a floor from their spacing would make
             them blobs;
           * none for other clouds (points sampled from a surface, whose sampling may vary
             legitimately): the local spacing alone bounds them.

On a regular surface (ground, roofs, facades) the covering radius is 0.6 to 1.2 spacings,
inside the bound: it stays hole-free. Where the sampling warrants no surface, splats stay dots
of at most BOUND_FACTOR spacings. The screen-facing splats of structure.py take their radius
from the same s.

Points without any distinct neighbour (a single point, or only coincident ones) take s_ref,
else the median spacing of the others, else LONE_POINT_FRACTION of the cloud's framing
radius: a lone point is a dot, not a disk that fills the view.

The kernel reads the neighbour lists of neighbourhood.py chunk by chunk (chunked.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial import cKDTree

from .chunked import map_chunks
from .neighbourhood import Neighbourhood

BOUND_FACTOR = 2.5          # semi-axes at most this x the spacing: past the 1.2 covering radius
                            # of scan-line sampling up to about 4 times as sparse across the lines
LOCAL_NEIGHBOURS = 4        # distinct neighbours whose median distance is the local spacing
REFERENCE_SAMPLE = 20_000   # points whose horizontal nearest neighbour gives the tile's spacing
REFERENCE_NEIGHBOURS = 8    # neighbours searched for the nearest distinct one (duplicates)
ONE_LAYER_RATIO = 0.7       # nearest-neighbour distance / s_local on one surface: 0.57 at random,
                            # about 0.6 along airborne scan lines, 0.85 on a jittered grid
SURFACE_MAJORITY = 0.5      # share of points with a tangent plane above which their spacing is
                            # the surfaces' own, not that of patches scattered through vegetation
LONE_POINT_FRACTION = 0.2   # spacing of a cloud without two distinct points / its framing radius


@numba.njit(parallel=True, cache=True)
def _local_spacing(points, index, start, count):  # pragma: no cover - compiled
    """Median distance from each point start + i to its `count` nearest distinct neighbours
    (neighbours come nearest first); NaN where it has none."""
    m, k = index.shape
    out = np.full(m, np.nan)
    for i in numba.prange(m):
        p = start + i
        distances = np.empty(count)
        found = 0
        for j in range(k):
            q = index[i, j]
            d2 = 0.0
            for a in range(3):
                offset = points[q, a] - points[p, a]
                d2 += offset * offset
            if d2 > 0.0:
                distances[found] = math.sqrt(d2)
                found += 1
                if found == count:
                    break
        if found > 0:  # ascending: the median is the middle one or two
            out[i] = 0.5 * (distances[(found - 1) // 2] + distances[found // 2])
    return out


def local_spacing(nbh: Neighbourhood, progress: bool | None = None) -> np.ndarray:
    """s_local (N,) float64 in the neighbourhood's order; NaN for points without a distinct
    neighbour."""
    index = nbh.index
    return map_chunks(lambda start, stop: _local_spacing(nbh.points, index[start:stop], start, LOCAL_NEIGHBOURS),
                      len(nbh.points), progress, "spacing")


def horizontal_spacing(points: np.ndarray) -> float | None:
    """The median horizontal distance to the nearest distinct neighbour, over REFERENCE_SAMPLE
    points spread evenly over `points` (N, 3); None if no point has one."""
    xy = np.ascontiguousarray(points[:, :2])
    tree = cKDTree(xy, balanced_tree=False, compact_nodes=False)
    sample = np.unique(np.linspace(0, len(xy) - 1, min(len(xy), REFERENCE_SAMPLE)).astype(np.int64))
    distances, _ = tree.query(xy[sample], k=min(REFERENCE_NEIGHBOURS, len(xy)), workers=-1)
    distances = distances.reshape(len(sample), -1)
    positive = distances > 0
    has = positive.any(axis=1)
    if not has.any():
        return None
    nearest = distances[has, positive[has].argmax(axis=1)]
    return float(np.median(nearest))


def sampling_spacing(nbh: Neighbourhood, *, geospatial: bool, ranges: np.ndarray | None,
                     framing_radius: float, reference: np.ndarray | None = None,
                     surface: np.ndarray | None = None, progress: bool | None = None) -> tuple[np.ndarray, dict]:
    """s = min(s_local, s_ref) (N,) float64 in the neighbourhood's order (module docstring),
    and its report: the reference model and its value.

    ranges: each point's distance to its sensor (sorted order), or None when no sensor is known.
    reference: s_ref (N,) (sorted order) when the caller knows it (a COPC node's spacing).
    surface: (N,) bool (sorted order), the points with a tangent plane; None: all of them.
    """
    local = local_spacing(nbh, progress)
    report: dict = {"local": f"median distance to {LOCAL_NEIGHBOURS} nearest distinct neighbours"}
    if reference is not None:
        report["reference"] = "given (the spacing of each point's level of detail)"
    elif ranges is not None:
        usable = np.isfinite(local) & (ranges > 0)
        if usable.any():
            step = float(np.median(local[usable] / ranges[usable]))
            reference = step * ranges
            report["reference"] = f"{step:.4g} x range from the sensor (the scan's angular step)"
            report["angular_step"] = step
    elif geospatial:
        horizontal = horizontal_spacing(nbh.points)
        if horizontal is not None:
            reference = np.full(len(local), horizontal)
            report["reference"] = "median horizontal nearest-neighbour distance of the tile"
            report["reference_spacing"] = horizontal
            surface = np.ones(len(local), np.bool_) if surface is None else surface
            surfaces = local[surface & np.isfinite(local)]
            one_layer = ONE_LAYER_RATIO * float(np.median(surfaces)) if len(surfaces) else 0.0
            if one_layer > horizontal and surface.mean() >= SURFACE_MAJORITY:
                reference[surface] = one_layer
                report["surface_reference_spacing"] = one_layer
                report["reference"] += f", on surfaces at least {ONE_LAYER_RATIO:g} x their median local spacing"
    spacing = local if reference is None else np.fmin(local, reference)
    missing = ~np.isfinite(spacing)
    if missing.any():
        known = spacing[~missing]
        spacing[missing] = np.median(known) if len(known) else LONE_POINT_FRACTION * framing_radius
    return spacing, report


@numba.njit(parallel=True, cache=True)
def _bound_semi_axes(axes, radii, bound):  # pragma: no cover - compiled
    """`bound_semi_axes` in one pass, with numpy's arithmetic (each length the square root of
    the sum of the squares, in order): the same values to the bit, without its temporaries."""
    n = len(axes)
    out = np.empty((n, 2, 3))
    out_radii = np.empty(n)
    capped = np.empty(n, np.bool_)
    for i in numba.prange(n):
        b = bound[i]
        cut = radii[i] > b
        for j in range(2):
            x, y, z = np.float64(axes[i, j, 0]), np.float64(axes[i, j, 1]), np.float64(axes[i, j, 2])
            scale = min(1.0, b / max(math.sqrt(x * x + y * y + z * z), 1e-300))
            cut = cut or scale < 1.0
            out[i, j, 0] = x * scale
            out[i, j, 1] = y * scale
            out[i, j, 2] = z * scale
        out_radii[i] = min(np.float64(radii[i]), b)
        capped[i] = cut
    return out, out_radii, capped


def bound_semi_axes(axes: np.ndarray, radii: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """Axes (N, 2, 3) and radii (N,) with every semi-axis at most BOUND_FACTOR x spacing (N,),
    float64, and the (N,) mask of the splats that were capped."""
    bound = BOUND_FACTOR * np.asarray(spacing, np.float64)
    return _bound_semi_axes(np.ascontiguousarray(axes), np.ascontiguousarray(radii), bound)
