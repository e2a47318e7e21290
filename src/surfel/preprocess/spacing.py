"""The sampling bound: no splat reaches farther than the sampling around it warrants.

A covering radius (cells.py) is what a surface needs to be hole-free, but it trusts the cell:
at the edge of a sparse region (the few returns over water, a wire, a bird, the fringe of a
scan) the cell is open or huge, and its disk invents surface far past the data. So every
estimated semi-axis is capped at

    BOUND_FACTOR x s,    s = min(s_local, s_ref)

  s_local  the local spacing: the median distance to the point's LOCAL_NEIGHBOURS nearest
           distinct neighbours (coincident returns, common in quantised LAS files, do not
           count), lifted where the sampling is anisotropic (below);
  s_ref    the reference spacing of the acquisition, where it has one:
           * given by the caller: a COPC file's octree spacing at each point's level (lod/copc.py);
           * a known sensor position (terrestrial scans: E57 poses, --sensor, `surfel scan`):
             the spacing of a scan grows with the range r from its sensor and with the tilt of
             the surface from its rays,

                 s_ref = alpha r / max(cos theta, INCIDENCE_FLOOR)

             with alpha the scan's angular step, the median of s_local / r over the scan, and
             theta the angle between the point's normal and its sensor's ray (0 for points
             without a tangent plane, structure.py). A surface tilted by theta takes the rays of
             one angular step 1 / cos theta farther apart along its tilt, and a scanner loses
             more and more returns as theta nears grazing, at random, so that the samples left
             there lie sparser every way: past 2.5 alpha r apart, where the bound cut their
             cells into scattered dots. (`python benchmarks/scan_fidelity.py MESH... --oblique`:
             scans of 9 models, 18 views each, 16 of them oblique: renders with more than 0.1%
             holes 11 -> 6 for `deferred` and 12 -> 6 for `phong`, the worst 1.85% -> 0.36%
             (a casting's pocket, seen by the scan only at grazing angles; what is left there
             was never sampled) and 0.60% -> 0.08% (a rocker arm's underside), those renders
             +2 to +3 dB; median PSNR 32.93 -> 32.97 dB and 33.78 -> 33.77 dB. The cost is on
             figures: at the fork of homer's legs and at cheburashka's fingers, which every
             view sees at grazing angles, a few splats with noisy normals now reach past the
             surface, -1.3 to -1.7 dB in four views of homer, -0.2 dB on average over
             cheburashka's. Growing only along the tilt, or only where the neighbourhood is
             planar, kept most of those holes; only off the borders, half of them. A floor of
             cos 60 degrees kept the cost and left 9 renders over 0.1% holes; cos 80 degrees
             gave the same as cos 75. The ground around a scanner on a tripod, seen from
             above out to 6.7 times the tripod's height, where the rays meet it at 8.5
             degrees (tests/test_lidar.py): rings of dots, 87% of it covered, became one
             surface, 99.4%.)
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

Anisotropic sampling: a CAD tessellation's long thin triangles sample a surface in rows far
apart, dense along each row (a car body's sill, 9 to 20 times denser along its rows than
across). There the 4 nearest all lie on the row, s_local is the spacing along it, and the bound
cut every splat short of the next row: a dotted line of holes between two rows (beetle-alt, seen
obliquely: 0.14% of the picture). So, for the splats the bound cut (outside geospatial tiles,
whose survey spacing bounds them), each point's nearest neighbour in each quadrant of its
tangent plane is found among its k nearest, or among its WIDE_NEIGHBOURS nearest where those
fill only two quadrants (one row). Where three quadrants at least hold one (a surface, not a
wire or a lone row), the farthest of them lies ANISOTROPY times the nearest or more, and its
normal turns by less than acos(FLAT_ACROSS_COS) from the point's, s_local is lifted to
ROW_REACH / BOUND_FACTOR times that distance: the splat may reach ROW_REACH of the way to the
next row, past the middle to the corners of the cell between two rows (at ANISOTROPY to one,
0.505 of the way). ANISOTROPY is 7, not 8, for a thin part's rings: the cow's tail's lie 7.3
times farther apart than the vertices of a ring, and once the ellipses stopped at the bound
(cells.py) the tail opened between its rings unless lifted (front view, `deferred` / `phong`:
holes 0.086 / 0.088% before, 0.108 / 0.113% with the ellipses clipped, 0.096 / 0.088% lifted
too). Across a tight curve (a teapot's rolled rim) the lift would stand splats off
the surface. `surfel compare MODEL --method deferred --size 512x512 --shading lambert`, front
and --azimuth 60 --elevation 20: beetle-alt 33.01 / 31.88 dB with 0.136% holes became 33.01 /
33.41 dB with none; the teapot lost 0.6 dB in both views (its lowest rows reach over the curve
into its base); ten other models, the shared ones and their range scans are unchanged. Beyond
about 19 to one the cells of cells.py, ending at the farthest of their k nearest, stop short of
the middle between two rows; a lifted splat whose cell stopped short of its bound grows to it
(`reach_next_row`). Beyond WIDE_NEIGHBOURS / 2 to one (32) the next row lies past the wider
search too, and the rows stay apart.

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

from ..threads import over_rows
from .chunked import map_chunks
from .neighbourhood import Neighbourhood

BOUND_FACTOR = 2.5          # semi-axes at most this x the spacing: past the 1.2 covering radius
                            # of scan-line sampling up to about 4 times as sparse across the lines
LOCAL_NEIGHBOURS = 4        # distinct neighbours whose median distance is the local spacing
REFERENCE_SAMPLE = 20_000   # points whose horizontal nearest neighbour gives the tile's spacing
REFERENCE_NEIGHBOURS = 8    # neighbours searched for the nearest distinct one (duplicates)
INCIDENCE_FLOOR = math.cos(math.radians(75.0))  # a scan's spacing grows up to 1 / cos 75 = 3.9 times at grazing
ONE_LAYER_RATIO = 0.7       # nearest-neighbour distance / s_local on one surface: 0.57 at random,
                            # about 0.6 along airborne scan lines, 0.85 on a jittered grid
SURFACE_MAJORITY = 0.5      # share of points with a tangent plane above which their spacing is
                            # the surfaces' own, not that of patches scattered through vegetation
LONE_POINT_FRACTION = 0.2   # spacing of a cloud without two distinct points / its framing radius
ANISOTROPY = 7.0            # farthest / nearest of the quadrants' nearest neighbours: sampled
                            # anisotropically (rows far apart, dense within a row)
FLAT_ACROSS_COS = 0.985     # ... and flat across the rows: the next row's normal within 10 degrees
ROW_REACH = 0.55            # there a splat may reach this share of the way to the next row
WIDE_NEIGHBOURS = 64        # neighbours searched where the k nearest lie along one row


def _local_spacing(points, index, start, count):
    """Median distance from each point start + i to its `count` nearest distinct neighbours
    (neighbours come nearest first); NaN where it has none."""
    m = len(index)
    out = np.full(m, np.nan)
    over_rows(_local_spacing_rows, m, points, index, start, count, out)
    return out


@numba.njit(cache=True, nogil=True)
def _local_spacing_rows(first, stop, points, index, start, count, out):  # pragma: no cover - compiled
    """Rows first:stop of `_local_spacing`."""
    k = index.shape[1]
    for i in range(first, stop):
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


def local_spacing(nbh: Neighbourhood, progress: bool | None = None) -> np.ndarray:
    """s_local (N,) float64 in the neighbourhood's order; NaN for points without a distinct
    neighbour."""
    index = nbh.index
    return map_chunks(lambda start, stop: _local_spacing(nbh.points, index[start:stop], start, LOCAL_NEIGHBOURS),
                      len(nbh.points), progress, "spacing")


def _row_distances(points, normals, index, rows, spacing):
    """Per point rows[i], among its neighbours index[i] (nearest first; only those within 45
    degrees of its tangent plane: not the far side of a thin sheet), the nearest in each
    quadrant of its tangent plane: the farthest of those distances where the sampling is
    anisotropic (module docstring), else 0; -1 where they fill two quadrants at most (one row,
    a wire: look further)."""
    m = len(index)
    out = np.zeros(m)
    over_rows(_row_distances_rows, m, points, normals, index, rows, spacing, out)
    return out


@numba.njit(cache=True, nogil=True)
def _row_distances_rows(first, stop, points, normals, index, rows, spacing, out):  # pragma: no cover - compiled
    """Rows first:stop of `_row_distances`."""
    k = index.shape[1]
    for i in range(first, stop):
        p = rows[i]
        nx, ny, nz = normals[p, 0], normals[p, 1], normals[p, 2]
        if nx * nx + ny * ny + nz * nz < 0.25:  # no normal, no tangent plane
            continue
        # a tangent frame (t, s): any one, the quadrants only have to split the plane in four
        if abs(nx) < 0.9:
            tx, ty, tz = 0.0, nz, -ny
        else:
            tx, ty, tz = -nz, 0.0, nx
        inv = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
        tx, ty, tz = tx * inv, ty * inv, tz * inv
        sx, sy, sz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
        nearest2 = np.inf
        farthest2 = 0.0
        farthest_facing = 1.0
        filled = 0
        seen = 0  # a bit per quadrant
        for j in range(k):  # nearest first: the first found in a quadrant is its nearest
            q = index[i, j]
            dx, dy, dz = points[q, 0] - points[p, 0], points[q, 1] - points[p, 1], points[q, 2] - points[p, 2]
            x = dx * tx + dy * ty + dz * tz
            y = dx * sx + dy * sy + dz * sz
            z = dx * nx + dy * ny + dz * nz
            planar = x * x + y * y
            if planar <= 0.0 or z * z > planar:
                continue
            bit = 1 << ((0 if x > 0.0 else 1) if y >= 0.0 else (2 if x <= 0.0 else 3))
            if seen & bit:
                continue
            seen |= bit
            filled += 1
            d2 = planar + z * z
            nearest2 = min(nearest2, d2)
            if d2 > farthest2:
                farthest2 = d2
                farthest_facing = normals[q, 0] * nx + normals[q, 1] * ny + normals[q, 2] * nz
            if filled == 4:
                break
        if filled <= 2:
            out[i] = -1.0
        elif (farthest2 >= ANISOTROPY * ANISOTROPY * nearest2 and farthest_facing >= FLAT_ACROSS_COS
              and ROW_REACH / BOUND_FACTOR * math.sqrt(farthest2) > spacing[p]):
            out[i] = math.sqrt(farthest2)


def anisotropic_spacing(nbh: Neighbourhood, normals: np.ndarray, spacing: np.ndarray,
                        rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The spacing (N,) lifted at those of the points `rows` where the sampling is anisotropic
    (module docstring), and the points it lifted. normals: (N, 3) unit; everything in the
    neighbourhood's order."""
    normals = np.ascontiguousarray(normals, np.float64)
    rows = np.asarray(rows, np.int64)
    spacing = np.asarray(spacing, np.float64)
    across = _row_distances(nbh.points, normals, nbh.index[rows], rows, spacing)
    narrow = np.flatnonzero(across < 0)
    if len(narrow) and min(WIDE_NEIGHBOURS, len(nbh.points)) > nbh.index.shape[1]:
        across[narrow] = _row_distances(nbh.points, normals, nbh.nearest(rows[narrow], WIDE_NEIGHBOURS),
                                        rows[narrow], spacing)
    lift = across > 0
    lifted = spacing.copy()
    lifted[rows[lift]] = ROW_REACH / BOUND_FACTOR * across[lift]
    return lifted, rows[lift]


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
                     surface: np.ndarray | None = None, incidence: np.ndarray | None = None,
                     progress: bool | None = None) -> tuple[np.ndarray, dict]:
    """s = min(s_local, s_ref) (N,) float64 in the neighbourhood's order (module docstring),
    and its report: the reference model and its value.

    ranges: each point's distance to its sensor (sorted order), or None when no sensor is known.
    incidence: with ranges, cos theta of each point (sorted order), 1 where it has no tangent
    plane; None: taken as 1 everywhere.
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
            if incidence is not None:
                reference /= np.maximum(incidence, INCIDENCE_FLOOR)
                report["reference"] += f" / cos of the incidence (at least {INCIDENCE_FLOOR:.2f})"
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


def _bound_semi_axes(axes, radii, bound):
    """`bound_semi_axes` in one pass, with numpy's arithmetic (each length the square root of
    the sum of the squares, in order): the same values to the bit, without its temporaries."""
    n = len(axes)
    out = np.empty((n, 2, 3))
    out_radii = np.empty(n)
    capped = np.empty(n, np.bool_)
    over_rows(_bound_semi_axes_rows, n, axes, radii, bound, out, out_radii, capped)
    return out, out_radii, capped


@numba.njit(cache=True, nogil=True)
def _bound_semi_axes_rows(first, stop, axes, radii, bound, out, out_radii, capped):  # pragma: no cover - compiled
    """Rows first:stop of `_bound_semi_axes`."""
    for i in range(first, stop):
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


def bound_semi_axes(axes: np.ndarray, radii: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """Axes (N, 2, 3) and radii (N,) with every semi-axis at most BOUND_FACTOR x spacing (N,),
    float64, and the (N,) mask of the splats that were capped."""
    bound = BOUND_FACTOR * np.asarray(spacing, np.float64)
    return _bound_semi_axes(np.ascontiguousarray(axes), np.ascontiguousarray(radii), bound)


def reach_next_row(axes: np.ndarray, radii: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                    np.ndarray]:
    """`bound_semi_axes` of the splats whose spacing `anisotropic_spacing` lifted, each grown
    to its bound where its cell stopped short of it: rows so far apart that the cell's
    neighbours all lie on the row end it at the farthest of them (cells.py)."""
    bounded_axes, bounded_radii, capped = bound_semi_axes(axes, radii, spacing)
    longest = np.linalg.norm(bounded_axes, axis=2).max(axis=1)
    grow = np.maximum(BOUND_FACTOR * np.asarray(spacing, np.float64) / np.maximum(longest, 1e-300), 1.0)
    return bounded_axes * grow[:, None, None], bounded_radii * grow, capped
