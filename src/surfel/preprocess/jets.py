"""Jets: the normals of a clean but coarse sampling, from a quadric fitted at each point.

Cazals & Pouget, "Estimating differential quantities using polynomial fitting of osculating
jets" (SGP 2003; CAGD 22(2), 2005). PCA's plane (normals.py) through a neighbourhood that spans
a curved patch tilts with the curvature: its angle error grows as kappa r (normals.py's E_j),
most where the neighbours lie more on one side, as at many vertices of a coarse figure's limbs
and face. A quadric, the jet of order 2, follows the curvature instead: the order-k
coefficients of a degree-d jet converge as r^(d - k + 1), so the quadric's normal as r^2.
In the frame (e1, e2, n) of the point's PCA normal n, with the offsets to its k neighbours q_j
scaled by h (h^2 their mean squared distance):

    (u_j, v_j, f_j) = ((q_j - p) . e1, (q_j - p) . e2, (q_j - p) . n) / h
    c = argmin sum_j w_j (c0 + c1 u_j + c2 v_j + c3 u_j^2 + c4 u_j v_j + c5 v_j^2 - f_j)^2,
        w_j = exp(-|q_j - p|^2 / h^2)
    normal = (n - c1 e1 - c2 e2) / |n - c1 e1 - c2 e2|

The normal keeps n's side (their dot product is positive), so orientation follows as before.
The Gaussian weight is ours: the far neighbours of a one-sided neighbourhood, which a quadric
fits worst, count less. Where the quadric's weighted RMS residual exceeds MAX_RESIDUAL h, the
neighbourhood is no height field (a crease, a tip, both sides of a thin part) and the PCA normal
stays: there it is the mean of the faces' normals, as a mesh's vertex normal is, which the crease
detection of sharp_features.py reads. So does it where the neighbourhood is degenerate (PCA's
mask) or the normal equations are singular.

Measured on the vertices of ten meshes without their normals (six figures quadric-decimated to
2,000-3,300 vertices: ogre, homer, beast, bunny, nefertiti, horse; fandisk, rocker-arm, spot,
and rocker-arm decimated to 2,500), angle from the mesh's normals:
  * on the six figures, median 5.3-19.1 degrees (PCA, k = 16) -> 4.1-18.6; the mean on
    fandisk 5.4 -> 5.0, rocker-arm 8.6 -> 4.7, spot 5.9 -> 3.4;
  * without the residual test, 3.9-16.3 on the figures (the unweighted fit 4.3-18.0), but 206
    of the 37,831 normals, at creases and tips, ended more than 30 degrees further from the
    mesh's than PCA's, and `deferred` showed more than 0.1% holes in 43 of 180 renders, not 25.
Rendered from those vertices, 18 views each at 512 x 512 (lambert), against the mesh
(`benchmarks/scan_fidelity.py MESH ... --bare --oblique --methods deferred,mls`):
`deferred` 25.85 -> 26.74 dB median (every model +0.2 to +3.1 dB; renders over 0.1% holes 25 ->
32, the decimated rocker-arm's 3 -> 9, which its mesh's own normals leave at 8); `mls` +0.1 to
+1.1 dB on nine of them and -0.1 on the horse, renders over 0.1% holes 58 -> 41. Denser
clouds gain too: the whole meshes' vertices (bunny, igea, homer, ogre; `--bare`, front and
azimuth 60) went 37.02 -> 38.88 dB median with `deferred` (39.53 with the meshes' own normals)
and 37.64 -> 40.24 dB with `phong`, without holes either way.

A quadric follows noise more readily than a plane: on raw range scans (`surfel scan` of bunny,
ogre, fandisk, rocker-arm: 0.1% range noise) the median error went 3.1-5.7 degrees -> 3.6-5.8
(3.4-5.7 with the residual test), where normals.py's scale selection takes it to 1.4-5.2. So
only a cloud that normals.py finds clean is refined; a scan denoised first (`--smooth`) is clean,
and its mean error fell 4.1-7.8 -> 3.9-7.6 degrees.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..threads import over_rows

MAX_RESIDUAL = 0.1  # weighted RMS residual of the quadric, in units of h, above which the PCA normal stays
SINGULAR = 1e-12    # a Cholesky pivot below this times the weight sum: the quadric is undetermined


def jet_normals(points: np.ndarray, index: np.ndarray, normals: np.ndarray, degenerate: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) float64 of the quadrics fitted over each point's neighbours `index`
    (N, k) in the frame of its `normals` (N, 3) unit; the given normal where `degenerate`,
    where the fit is singular, or where its residual exceeds MAX_RESIDUAL h."""
    out = np.array(normals, np.float64)
    over_rows(_jet_rows, len(points), points, index, np.ascontiguousarray(normals, np.float64),
              np.ascontiguousarray(degenerate, np.bool_), out)
    return out


@numba.njit(cache=True, nogil=True)
def _jet_rows(first, stop, points, index, normals, degenerate, out):  # pragma: no cover - compiled
    """Rows first:stop of `jet_normals`."""
    k = index.shape[1]
    a = np.empty((6, 6))
    b = np.empty(6)
    phi = np.empty(6)
    rows = np.empty((k, 4))  # (u, v, f, w) of each neighbour
    for p in range(first, stop):
        if degenerate[p]:
            continue
        n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
        # e1: n x (the axis least along n), e2 = n x e1 (frames.py's basis is another module's,
        # which a kernel here may not read: see _cholesky_solve)
        if abs(n0) <= abs(n1) and abs(n0) <= abs(n2):
            e10, e11, e12 = 0.0, n2, -n1
        elif abs(n1) <= abs(n2):
            e10, e11, e12 = -n2, 0.0, n0
        else:
            e10, e11, e12 = n1, -n0, 0.0
        length = math.sqrt(e10 * e10 + e11 * e11 + e12 * e12)
        e10, e11, e12 = e10 / length, e11 / length, e12 / length
        e20, e21, e22 = n1 * e12 - n2 * e11, n2 * e10 - n0 * e12, n0 * e11 - n1 * e10
        mean2 = 0.0
        for j in range(k):  # the offsets in the frame, unscaled; the frame keeps their lengths
            q = index[p, j]
            dx, dy, dz = points[q, 0] - points[p, 0], points[q, 1] - points[p, 1], points[q, 2] - points[p, 2]
            rows[j, 0] = dx * e10 + dy * e11 + dz * e12
            rows[j, 1] = dx * e20 + dy * e21 + dz * e22
            rows[j, 2] = dx * n0 + dy * n1 + dz * n2
            mean2 += rows[j, 0] ** 2 + rows[j, 1] ** 2 + rows[j, 2] ** 2
        mean2 /= k
        if mean2 <= 0.0:
            continue
        inv_h = 1.0 / math.sqrt(mean2)
        a[:] = 0.0
        b[:] = 0.0
        weights = 0.0
        for j in range(k):
            u, v, f = rows[j, 0] * inv_h, rows[j, 1] * inv_h, rows[j, 2] * inv_h
            w = math.exp(-(u * u + v * v + f * f))  # exp(-|q_j - p|^2 / h^2)
            rows[j, 0], rows[j, 1], rows[j, 2], rows[j, 3] = u, v, f, w
            phi[0], phi[1], phi[2], phi[3], phi[4], phi[5] = 1.0, u, v, u * u, u * v, v * v
            for r in range(6):
                b[r] += w * f * phi[r]
                for c in range(r + 1):
                    a[r, c] += w * phi[r] * phi[c]
            weights += w
        if not _cholesky_solve(a, b, SINGULAR * weights):
            continue
        residual = 0.0
        for j in range(k):
            u, v = rows[j, 0], rows[j, 1]
            e = b[0] + b[1] * u + b[2] * v + b[3] * u * u + b[4] * u * v + b[5] * v * v - rows[j, 2]
            residual += rows[j, 3] * e * e
        if residual >= MAX_RESIDUAL * MAX_RESIDUAL * weights:
            continue  # no quadric: a crease, a tip, the two sides of a thin part
        gx = n0 - b[1] * e10 - b[2] * e20
        gy = n1 - b[1] * e11 - b[2] * e21
        gz = n2 - b[1] * e12 - b[2] * e22
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        out[p, 0], out[p, 1], out[p, 2] = gx / length, gy / length, gz / length


@numba.njit(cache=True, nogil=True, inline="always")
def _cholesky_solve(a, b, tiny):  # pragma: no cover - compiled
    """Solve a x = b in place (a's lower triangle, symmetric positive definite; x into b); False
    where a pivot falls below `tiny`. (Not mls/polynomial.solve_spd: a preprocessing kernel reads
    only its own module, which numba's on-disk cache sees change; test_preprocess_kernels.py.)"""
    n = b.shape[0]
    for c in range(n):
        pivot = a[c, c]
        for j in range(c):
            pivot -= a[c, j] * a[c, j]
        if pivot <= tiny:
            return False
        a[c, c] = math.sqrt(pivot)
        for r in range(c + 1, n):
            s = a[r, c]
            for j in range(c):
                s -= a[r, j] * a[c, j]
            a[r, c] = s / a[c, c]
    for r in range(n):  # L y = b
        s = b[r]
        for j in range(r):
            s -= a[r, j] * b[j]
        b[r] = s / a[r, r]
    for r in range(n - 1, -1, -1):  # L^T x = y
        s = b[r]
        for j in range(r + 1, n):
            s -= a[j, r] * b[j]
        b[r] = s / a[r, r]
    return True
