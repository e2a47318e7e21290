"""Layer thickness: how far along its normal a splat's own surface reaches before another
surface lies behind or in front of it, so that the visibility threshold z_t of the blended
splat methods stays inside the layer where two surfaces lie closer than a splat radius (cloth
on a body, a sheet on a wall, the two scans of a thin plate), and so that the other layer's
samples do not cut the splat's Voronoi cell (`cells.py`) into holes.

Botsch & Kobbelt (2003) and Botsch et al. (2005) blend every fragment within z_t of the
nearest depth, z_t a fixed fraction of the splat radius. Where another surface lies within that
distance, its splats blend in too: the surface behind bleeds through the one in front. Here z_t
is capped per splat by the thickness tau_p of its own layer (the renderers turn it into eye depth
along the ray, gl/common.glsl layer_offset and its CPU twins):

    z_t,p = min(depth_offset r_p, tau_p / max(|n_p . view|, MIN_LAYER_COS))

Two points p, q of one smooth surface see each other below (or above) their tangent planes by
about the same amount, d_pq = (q - p) . n_p ~ d_qp = (p - q) . n_q ~ -kappa s^2 / 2, while two
points of parallel layers a distance h apart see each other on opposite sides, d_pq = -d_qp = -h.
So the separation of q from p's layer is the antisymmetric part, less, where the normals lie
more than 15 degrees apart (CREASE_COS), what a crease between their planes explains (q at
tangential distance t_pq from p on a plane tilted by the angle between the normals:
|d_pq - d_qp| is at most t_pq |n_p - n_q|):

    h_pq = max(0, |d_pq - d_qp| - c_pq t_pq |n_p - n_q|) / 2,   d_pq - d_qp = (q - p) . (n_p + n_q),

c_pq = 1 at such a crease, else 0; curvature and creases leave it near zero, noise spreads it
over a continuous range. (The cells and the borders, which only need to know which neighbours
lie beyond tau_p, compare |d_pq - d_qp| / 2 with it.)

Over p's k nearest neighbours (about two sample spacings: the splats that can overlap p's)
whose normals lie within 60 degrees of p's (a surface facing the other way is the back-face
weight's business), sorted by h, p's own layer is the run of separations up to the first gap:
the first h_(i+1) that exceeds GAP_FACTOR times the layer's extent e so far plus GAP_FLOOR s_p,
s_p the distance to p's FLOOR_NEIGHBOUR-th neighbour (a local sample spacing). The extent is
the largest, over the run, of |d_pq - d_qp| / 2 (the layer's noise, and what creases add) and
of the curvature offset (|d_pq| + |d_qp|) / 2 brought to the distance s_p (times
min(1, s_p^2 / t_pq^2): a curve's offset grows with the square of the distance), so that the
layer's curvature at the splat's scale widens it too. With at least MIN_LAYER neighbours in
the run and MIN_OTHER beyond the gap (a lone far sample is the tail of the noise),

    tau_p = (e + h_(i+1)) / 2,

half way between the own layer and the next; without a gap tau_p is infinite (INFINITE_LENGTH:
no cap), which is what a single surface gets, noisy or curved, and what misaligned scans of one
surface get while the misalignment stays within their noise (they blend, as they should).
Screen-facing splats (no tangent plane) get no cap. A level-of-detail hierarchy keeps no
thickness: its inner nodes are new disks spanning the layers.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..attributes import INFINITE_LENGTH
from ..cloud import PointCloud
from ..threads import over_rows
from .chunked import map_chunks

PARALLEL_COS = 0.5   # neighbours whose normals are within 60 degrees count as parallel layers
CREASE_COS = float(np.cos(np.radians(15.0)))  # normals further apart may meet at a crease
GAP_FACTOR = 2.0     # a gap wider than twice the own layer's extent ...
GAP_FLOOR = 0.1      # ... plus this fraction of the local spacing separates two layers
FLOOR_NEIGHBOUR = 4  # the neighbour whose distance is that spacing
MIN_LAYER = 2        # neighbours that must share the point's layer before a gap counts ...
MIN_OTHER = 5        # ... and lie beyond it (a third of them: fewer are the tail of its noise)
THICKNESS_BLOCK = 1024  # the fewest points per thread's piece


def layer_thickness(points: np.ndarray, normals: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(N,) float64 tau_p (module docstring; INFINITE_LENGTH for none) of `points` (N, 3) with
    unit `normals` (N, 3), given each point's neighbours `index` (N, k), nearest first, itself
    first."""
    normals = np.ascontiguousarray(normals, np.float64)
    thickness = map_chunks(lambda start, stop: _layer_thickness(points, normals, index[start:stop], start),
                           len(points))
    return np.minimum(thickness, INFINITE_LENGTH)


def splat_thickness(cloud: PointCloud, start: int = 0, stop: int | None = None) -> np.ndarray:
    """(n,) float32 tau of points start:stop as the renderers take it: 0 where there is no cap
    (no thickness estimated, or no other layer near)."""
    stop = len(cloud) if stop is None else stop
    thickness = cloud.attributes.get("thickness")
    if thickness is None:
        return np.zeros(stop - start, np.float32)
    values = thickness[start:stop]
    return np.where(values < INFINITE_LENGTH, values, 0.0).astype(np.float32)


@numba.njit(cache=True, inline="always")
def _sort_by_rank(keys, values, n, sorted_keys, sorted_values):  # pragma: no cover - compiled
    """keys[:n] ascending into sorted_keys, values[:n] along, equal keys in their order: each
    goes to its rank, the number of keys below it and of equal ones before it. The counts
    compile to SIMD compares, where sorting by insertion mispredicted a branch per key."""
    for a in range(n):
        key = keys[a]
        rank = 0
        for b in range(n):
            rank += (keys[b] < key) | ((keys[b] == key) & (b < a))
        sorted_keys[rank] = key
        sorted_values[rank] = values[a]


def _layer_thickness(points, normals, index, start):
    """tau_p of each point p = start + i."""
    m = len(index)
    out = np.empty(m)
    over_rows(_layer_thickness_rows, m, points, normals, index, start, out, grain=THICKNESS_BLOCK)
    return out


@numba.njit(cache=True, nogil=True)
def _layer_thickness_rows(first, stop, points, normals, index, start, out):  # pragma: no cover - compiled
    """Rows first:stop of `_layer_thickness`."""
    k = index.shape[1]
    # buffers per call (an allocation per point costs as much as its work): the neighbours'
    # separations and extents as they come, then sorted by separation
    found_h, found_e, separation, extent = np.empty(k), np.empty(k), np.empty(k), np.empty(k)
    for i in range(first, stop):
        p = start + i
        f = index[i, min(FLOOR_NEIGHBOUR, k - 1)]
        spacing2 = (points[f, 0] - points[p, 0]) ** 2 + (points[f, 1] - points[p, 1]) ** 2 \
            + (points[f, 2] - points[p, 2]) ** 2
        floor = GAP_FLOOR * math.sqrt(spacing2)
        count = 0
        widest = 0.0
        for j in range(1, k):
            q = index[i, j]
            cos = normals[p, 0] * normals[q, 0] + normals[p, 1] * normals[q, 1] + normals[p, 2] * normals[q, 2]
            if cos < PARALLEL_COS:
                continue
            dx, dy, dz = points[q, 0] - points[p, 0], points[q, 1] - points[p, 1], points[q, 2] - points[p, 2]
            d_pq = dx * normals[p, 0] + dy * normals[p, 1] + dz * normals[p, 2]
            d_qp = -(dx * normals[q, 0] + dy * normals[q, 1] + dz * normals[q, 2])
            tangential2 = max(dx * dx + dy * dy + dz * dz - d_pq * d_pq, 0.0)
            antisymmetric = 0.5 * abs(d_pq - d_qp)
            crease = math.sqrt(tangential2 * max(2.0 - 2.0 * cos, 0.0)) if cos < CREASE_COS else 0.0
            h = max(antisymmetric - 0.5 * crease, 0.0)
            bend = 0.5 * (abs(d_pq) + abs(d_qp)) * min(1.0, spacing2 / max(tangential2, 1e-300))
            found_h[count], found_e[count] = h, max(antisymmetric, bend)
            count += 1
            widest = max(widest, h)
        out[i] = np.inf
        if widest <= floor:
            continue  # no separation reaches past the floor of a gap: one layer, no sort needed
        _sort_by_rank(found_h, found_e, count, separation, extent)
        layer = 0.0
        for j in range(count):
            if j >= MIN_LAYER and count - j >= MIN_OTHER and separation[j] > GAP_FACTOR * layer + floor:
                out[i] = 0.5 * (layer + separation[j])
                break
            layer = max(layer, extent[j])
