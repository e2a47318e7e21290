"""Denoising positions: projection onto the moving least-squares surface of the points.

The surface is the zero set of the implicit function of Adamson & Alexa 2003 ("Approximating
and intersecting surfaces from points", Proc. Eurographics Symposium on Geometry Processing,
230-239; its projection analysed in Alexa & Adamson 2004, "On normals and projection operators
for surfaces defined by point sets", SPBG), built from the points p_i and their oriented
normals n_i:

    theta(d) = exp(-d^2 / h^2)                                   (Gaussian weight)
    a(x)     = sum_i theta(|x - p_i|) p_i / sum_i theta(|x - p_i|)     (weighted centre)
    n(x)     = sum_i theta(|x - p_i|) n_i / |sum_i theta(|x - p_i|) n_i|  (weighted normal)
    f(x)     = n(x) . (x - a(x))

and each point moves onto it by the projection x <- x - f(x) n(x), repeated SMOOTH_STEPS
times. Neighbours whose normal is more than SAME_SURFACE_ANGLE from the point's
(n_i . n_p <= cos SAME_SURFACE_ANGLE) are left out of its sums: they lie on another surface, the
other face of a crease or the other side of a thin sheet (a shell's inside seen through an
opening), which the average would otherwise round off or pull the point towards. The angle is
far tighter than the sharp-feature angle (45 degrees, sharp_features.py): the estimated
normals of points on a crease average the faces' and lie half the crease's turn from both
(45 degrees on a 90-degree crease, 20 on a 40-degree chamfer), so a point on a crease that
turns by less than twice the angle took both faces in its sums, whose mean lies inside the
solid, and the crease was rounded off: a CAD part's outline shrank by a pixel. On fandisk's
scan seen from azimuth 60, the share of its silhouette left uncovered with `phong` was 0.44%
at 45 degrees, 0.15% at 25 and is 0.08% at 15. Over the scans of eight models (the shared
three, four figures and two CAD parts; `benchmarks/scan_fidelity.py --smooth`, front and
azimuth 60) 15 degrees moved the median PSNR from 34.1 to 34.3 dB (`deferred`) and from 34.9 to
35.2 dB (`phong`), each render by -0.3 to +0.9 dB except the CAD parts seen face on (fandisk
and casting from the front, -0.6 to -1.0 dB), whose outlines keep more of their noise.
The sums run over the point's SMOOTH_NEIGHBOURS nearest neighbours (the point moves by about
the noise, far less than h, so its neighbourhood stays its own); h, per point, is SMOOTH_WIDTH
times the distance to its WIDTH_NEIGHBOUR-th nearest neighbour, so that about
that many neighbours weigh in whatever the local sampling. Averaging over them, range noise of
standard deviation sigma falls to about sigma / sqrt(WIDTH_NEIGHBOUR), and the slightly
misregistered layers of overlapping scans meet on one surface. What it costs: the weighted
plane cuts convex bumps narrower than h, by about kappa h^2 / 4 at curvature kappa.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..threads import over_rows
from .chunked import map_chunks
from .neighbourhood import Neighbourhood

SMOOTH_NEIGHBOURS = 24  # neighbours of each point's surface fit
WIDTH_NEIGHBOUR = 8     # h is SMOOTH_WIDTH times the distance to this neighbour
SMOOTH_WIDTH = 1.0
SMOOTH_STEPS = 2        # projections: the second corrects a(x), n(x) at the moved point
SAME_SURFACE_ANGLE = 15.0  # degrees: neighbours with normals farther from the point's are another surface


def _project(points, normals, index, start, width_neighbour, width, steps, same_surface):
    """Positions (m, 3) of points start + i projected onto the MLS surface (module docstring)."""
    m = len(index)
    out = np.empty((m, 3))
    over_rows(_project_rows, m, points, normals, index, start, width_neighbour, width, steps, same_surface, out)
    return out


@numba.njit(cache=True, nogil=True)
def _project_rows(first, stop, points, normals, index, start, width_neighbour, width, steps, same_surface,
                  out):  # pragma: no cover - compiled
    """Rows first:stop of `_project`."""
    k = index.shape[1]
    for i in range(first, stop):
        p = start + i
        w_far = min(width_neighbour, k - 1)
        q = index[i, w_far]
        h2 = 0.0
        for r in range(3):
            h2 += (points[q, r] - points[p, r]) ** 2
        h2 *= width * width
        x0, x1, x2 = points[p, 0], points[p, 1], points[p, 2]
        if h2 <= 0.0:
            out[i, 0], out[i, 1], out[i, 2] = x0, x1, x2
            continue
        for _ in range(steps):
            total = 0.0
            a0 = a1 = a2 = 0.0
            n0 = n1 = n2 = 0.0
            for j in range(k):
                q = index[i, j]
                if normals[q, 0] * normals[p, 0] + normals[q, 1] * normals[p, 1] + normals[q, 2] * normals[p, 2] \
                        <= same_surface:
                    continue  # another face of a crease, or the other side of a thin sheet
                d2 = (points[q, 0] - x0) ** 2 + (points[q, 1] - x1) ** 2 + (points[q, 2] - x2) ** 2
                w = math.exp(-d2 / h2)
                total += w
                a0 += w * points[q, 0]
                a1 += w * points[q, 1]
                a2 += w * points[q, 2]
                n0 += w * normals[q, 0]
                n1 += w * normals[q, 1]
                n2 += w * normals[q, 2]
            length = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if total <= 0.0 or length <= 0.0:
                break
            n0, n1, n2 = n0 / length, n1 / length, n2 / length
            f = n0 * (x0 - a0 / total) + n1 * (x1 - a1 / total) + n2 * (x2 - a2 / total)
            x0, x1, x2 = x0 - f * n0, x1 - f * n1, x2 - f * n2
        out[i, 0], out[i, 1], out[i, 2] = x0, x1, x2


def smoothed_points(nbh: Neighbourhood, normals: np.ndarray, progress: bool | None = None) -> np.ndarray:
    """The sorted points of `nbh` projected onto their MLS surface (N, 3), from their oriented
    normals (N, 3) in the same order."""
    wide = nbh.widened(SMOOTH_NEIGHBOURS, progress=progress)
    index = wide.first(SMOOTH_NEIGHBOURS)
    unit = np.ascontiguousarray(normals, np.float64)
    same_surface = math.cos(math.radians(SAME_SURFACE_ANGLE))
    return map_chunks(lambda start, stop: _project(wide.points, unit, index[start:stop], start, WIDTH_NEIGHBOUR,
                                                   SMOOTH_WIDTH, SMOOTH_STEPS, same_surface), len(nbh.points), progress,
                      "smoothing")
