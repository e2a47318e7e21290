"""The moving least squares (MLS) point set surface and its projection operator.

Adamson & Alexa, "Ray tracing point set surfaces", SMI 2003 (survey section 2.3.1, Fig. 14).
The surface S is the set of points that the projection operator maps onto themselves.
Projecting a point r, with neighbours p_i within the support 2.5 h_i of r:

    w_i  = exp(-|p_i - r|^2 / h_i^2)                      Gaussian weight, h_i = h_scale * s_i,
                                                          s_i the smoothed local point spacing
    q    = sum w_i p_i / sum w_i                          origin of the reference plane H
    C    = sum w_i (p_i - q)(p_i - q)^T                   weighted covariance
    n    = eigenvector of C with the smallest eigenvalue  normal of H (e1, e2 span H)
    g    = argmin sum w_i (g(u_i, v_i) - f_i)^2           bivariate quadratic over H,
           g(u, v) = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2,
           (u_i, v_i, f_i) = coordinates of p_i - q in (e1, e2, n)
    P(r) = q + u_r e1 + v_r e2 + g(u_r, v_r) n            (u_r, v_r) = coordinates of r - q in H

`project` iterates r <- P(r) until |P(r) - r| < tolerance * spacing. A domain test keeps
the surface from bridging holes and from running past the data's boundary: a fit is only
valid where some sample lies within `domain * s_i` of the point being projected. Failures
are statuses (FIT_*), never exceptions.

Everything is plain arrays so numba compiles it: neighbour search on a uniform grid whose
cells are the largest support radius, points sorted by cell with cell start offsets.
A fitted polynomial is a float64 row of POLY_SIZE values (see the P_* offsets).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..cloud import PointCloud
from ..options import Settings, positive, setting

# Fit statuses.
FIT_OK = 0
FIT_TOO_FEW = 1        # fewer than MIN_NEIGHBOURS samples in the support
FIT_DEGENERATE = 2     # the covariance has no unique smallest eigenvector, or the system is singular
FIT_OUTSIDE = 3        # the domain test failed: no sample near enough (a hole or past the boundary)
FIT_NOT_CONVERGED = 4  # projection did not reach the tolerance in the allowed iterations
STATUS_NAMES = ("ok", "too_few_neighbours", "degenerate", "outside_domain", "not_converged")

MIN_NEIGHBOURS = 6     # a bivariate quadratic has 6 coefficients
SUPPORT = 2.5          # Gaussian truncated at SUPPORT * h (weight exp(-6.25) = 0.002)
MAX_NEIGHBOURS = 512   # neighbour buffer of one fit (a support holds ~50 on even sampling)
SPACING_K = 8          # spacing s_i = mean distance to the 8 nearest neighbours, smoothed

# Layout of one fitted polynomial row.
P_Q, P_N, P_E1, P_E2, P_C, P_COLOR, P_SCALE = 0, 3, 6, 9, 12, 18, 21
POLY_SIZE = 22


@dataclass(frozen=True)
class MlsKernel(Settings):
    """The surface's definition, shared by the `mls` and `mls-gpu` parameters."""

    h_scale: float = setting(1.5, positive)  # kernel width h_i = h_scale * local spacing s_i
    domain: float = setting(2.0, positive)  # domain test (and bounding sphere) radius, in units of s_i


DEFAULT_KERNEL = MlsKernel()


@dataclass(frozen=True, eq=False)
class MLSSurface:
    """A point set prepared for MLS projection (positions relative to `origin`).

    points (N,3) f64, spacing (N,) s_i, h (N,) kernel widths, colors (N,3) f64 (white if
    none), domain factor; grid: cell size, lower corner, dims (3,), order (N,) point indices
    sorted by cell, starts (cells+1,) offsets into order.
    """

    origin: np.ndarray
    points: np.ndarray
    spacing: np.ndarray
    h: np.ndarray
    colors: np.ndarray
    domain: float
    cell: float
    lower: np.ndarray
    dims: np.ndarray
    order: np.ndarray
    starts: np.ndarray

    @property
    def scale(self) -> float:
        """Typical kernel width: the unit of the local polynomial coordinates and of tolerances."""
        return float(np.median(self.h))


def local_spacing(points: np.ndarray, k: int = SPACING_K) -> np.ndarray:
    """Mean distance to the k nearest neighbours, averaged once more over those neighbours
    (smooths scan noise), clamped to [0.5, 2] x the median so one outlier cannot blow up the grid."""
    k = min(k, len(points) - 1)
    if k < 1:
        return np.ones(len(points))
    dist, idx = cKDTree(points).query(points, k + 1)
    raw = dist[:, 1:].mean(axis=1)
    smooth = raw[idx].mean(axis=1)
    med = float(np.median(smooth)) or 1.0
    return np.clip(smooth, 0.5 * med, 2.0 * med)


def build_surface(cloud: PointCloud, kernel: MlsKernel = DEFAULT_KERNEL) -> MLSSurface:
    """Spacing, kernel widths and the neighbour grid of `cloud` (h_i = h_scale * s_i)."""
    origin = cloud.local_origin
    points = np.ascontiguousarray(cloud.positions - origin)
    spacing = local_spacing(points)
    h = kernel.h_scale * spacing
    colors = np.ones((len(points), 3)) if cloud.colors is None else cloud.colors.astype(np.float64)
    cell = float(SUPPORT * h.max())
    lower = points.min(axis=0) - 1e-9
    extent = points.max(axis=0) - lower
    # Keep the dense cell table under 2^24 entries for sparse, wide scenes.
    while np.prod(np.floor(extent / cell) + 1) > 2**24:
        cell *= 1.5
    dims = (np.floor(extent / cell) + 1).astype(np.int64)
    ijk = np.minimum(((points - lower) / cell).astype(np.int64), dims - 1)
    keys = (ijk[:, 2] * dims[1] + ijk[:, 1]) * dims[0] + ijk[:, 0]
    order = np.argsort(keys, kind="stable").astype(np.int64)
    starts = np.searchsorted(keys[order], np.arange(int(np.prod(dims)) + 1)).astype(np.int64)
    return MLSSurface(origin, points, spacing, h, np.ascontiguousarray(colors), float(kernel.domain), cell,
                      lower, dims, order, starts)


@numba.njit(cache=True, fastmath=True)
def smallest_eigenvector(c00, c01, c02, c11, c12, c22, out):
    """Unit eigenvector of the symmetric 3x3 matrix for its smallest eigenvalue (analytic:
    trigonometric eigenvalues, then the largest cross product of two rows of C - l I).
    Returns False when it is not unique (isotropic or line-like data)."""
    p1 = c01 * c01 + c02 * c02 + c12 * c12
    q = (c00 + c11 + c22) / 3.0
    p2 = (c00 - q) ** 2 + (c11 - q) ** 2 + (c22 - q) ** 2 + 2.0 * p1
    if p2 <= 1e-30 * (q * q + 1e-300):
        return False
    p = math.sqrt(p2 / 6.0)
    b00, b11, b22 = (c00 - q) / p, (c11 - q) / p, (c22 - q) / p
    b01, b02, b12 = c01 / p, c02 / p, c12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = min(1.0, max(-1.0, r))
    phi = math.acos(r) / 3.0
    lam = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    a00, a11, a22 = c00 - lam, c11 - lam, c22 - lam
    # rows (a00 c01 c02), (c01 a11 c12), (c02 c12 a22); the null vector is orthogonal to all
    x0, y0, z0 = c01 * c12 - c02 * a11, c02 * c01 - a00 * c12, a00 * a11 - c01 * c01
    x1, y1, z1 = c01 * a22 - c02 * c12, c02 * c02 - a00 * a22, a00 * c12 - c01 * c02
    x2, y2, z2 = a11 * a22 - c12 * c12, c12 * c02 - c01 * a22, c01 * c12 - a11 * c02
    n0, n1, n2 = x0 * x0 + y0 * y0 + z0 * z0, x1 * x1 + y1 * y1 + z1 * z1, x2 * x2 + y2 * y2 + z2 * z2
    if n0 >= n1 and n0 >= n2:
        x, y, z, nn = x0, y0, z0, n0
    elif n1 >= n2:
        x, y, z, nn = x1, y1, z1, n1
    else:
        x, y, z, nn = x2, y2, z2, n2
    # Unique only if the second-smallest eigenvalue is well separated from the smallest.
    if nn <= 1e-20 * (p * p) ** 2:
        return False
    inv = 1.0 / math.sqrt(nn)
    out[0], out[1], out[2] = x * inv, y * inv, z * inv
    return True


@numba.njit(cache=True, fastmath=True)
def tangent_frame(n, e1, e2):
    """A deterministic orthonormal basis (e1, e2) of the plane with normal n (also in gpu.glsl)."""
    if abs(n[0]) < 0.6:
        ax, ay, az = 1.0, 0.0, 0.0
    else:
        ax, ay, az = 0.0, 1.0, 0.0
    x, y, z = ay * n[2] - az * n[1], az * n[0] - ax * n[2], ax * n[1] - ay * n[0]
    inv = 1.0 / math.sqrt(x * x + y * y + z * z)
    e1[0], e1[1], e1[2] = x * inv, y * inv, z * inv
    e2[0] = n[1] * e1[2] - n[2] * e1[1]
    e2[1] = n[2] * e1[0] - n[0] * e1[2]
    e2[2] = n[0] * e1[1] - n[1] * e1[0]


@numba.njit(cache=True, fastmath=True)
def solve_spd(a, b, n):
    """Solve a x = b in place (b <- x) for the leading n x n block by Cholesky; False if singular."""
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if d <= 1e-12 * (a[0, 0] + 1e-300):
            return False
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s / d
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= a[i, k] * b[k]
        b[i] = s / a[i, i]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= a[k, i] * b[k]
        b[i] = s / a[i, i]
    return True


@numba.njit(cache=True, fastmath=True)
def fit(x, points, spacing, h, colors, domain, cell, lower, dims, order, starts, scale, poly, work, nb):
    """Fit the local MLS polynomial at x into `poly` (POLY_SIZE); returns a FIT_* status.

    `work` is a scratch (7, 7) array, `nb` a scratch (MAX_NEIGHBOURS, 4) array holding the
    neighbours found by the one grid scan (offset from x, weight). Coordinates over H are
    divided by `scale` so that the normal equations stay well conditioned in any units.
    """
    c0 = int((x[0] - lower[0]) / cell)
    c1 = int((x[1] - lower[1]) / cell)
    c2 = int((x[2] - lower[2]) / cell)
    sw = 0.0
    mx = my = mz = 0.0
    cr = cg = cb = 0.0
    count = 0
    inside = False
    # one grid scan: weights, weighted mean, colour, domain test
    for kz in range(max(c2 - 1, 0), min(c2 + 2, dims[2])):
        for ky in range(max(c1 - 1, 0), min(c1 + 2, dims[1])):
            row = (kz * dims[1] + ky) * dims[0]
            lo = starts[row + max(c0 - 1, 0)]
            hi_ = starts[row + min(c0 + 2, dims[0])]
            for s in range(lo, hi_):
                i = order[s]
                ddx, ddy, ddz = points[i, 0] - x[0], points[i, 1] - x[1], points[i, 2] - x[2]
                d2 = ddx * ddx + ddy * ddy + ddz * ddz
                hi = h[i]
                if d2 >= (SUPPORT * hi) ** 2 or count >= MAX_NEIGHBOURS:
                    continue
                if d2 < (domain * spacing[i]) ** 2:
                    inside = True
                w = math.exp(-d2 / (hi * hi))
                nb[count, 0], nb[count, 1], nb[count, 2], nb[count, 3] = ddx, ddy, ddz, w
                sw += w
                mx += w * ddx
                my += w * ddy
                mz += w * ddz
                cr += w * colors[i, 0]
                cg += w * colors[i, 1]
                cb += w * colors[i, 2]
                count += 1
    if count < MIN_NEIGHBOURS:
        return FIT_TOO_FEW
    if not inside:
        return FIT_OUTSIDE
    mx /= sw
    my /= sw
    mz /= sw
    # covariance about the weighted mean, in units of scale
    inv_s = 1.0 / scale
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    for k in range(count):
        w = nb[k, 3]
        px, py, pz = (nb[k, 0] - mx) * inv_s, (nb[k, 1] - my) * inv_s, (nb[k, 2] - mz) * inv_s
        c00 += w * px * px
        c01 += w * px * py
        c02 += w * px * pz
        c11 += w * py * py
        c12 += w * py * pz
        c22 += w * pz * pz
    nrm = poly[P_N:P_N + 3]
    if not smallest_eigenvector(c00, c01, c02, c11, c12, c22, nrm):
        return FIT_DEGENERATE
    e1 = poly[P_E1:P_E1 + 3]
    e2 = poly[P_E2:P_E2 + 3]
    tangent_frame(nrm, e1, e2)
    # weighted least squares quadratic over H: normal equations (lower triangle) and rhs in row 6
    for a in range(7):
        for b in range(7):
            work[a, b] = 0.0
    for k in range(count):
        w = nb[k, 3]
        px, py, pz = (nb[k, 0] - mx) * inv_s, (nb[k, 1] - my) * inv_s, (nb[k, 2] - mz) * inv_s
        u = px * e1[0] + py * e1[1] + pz * e1[2]
        v = px * e2[0] + py * e2[1] + pz * e2[2]
        f = px * nrm[0] + py * nrm[1] + pz * nrm[2]
        bs = (1.0, u, v, u * u, u * v, v * v)
        for a in range(6):
            wa = w * bs[a]
            work[6, a] += wa * f
            for b in range(a + 1):
                work[a, b] += wa * bs[b]
    coef = work[6, :6]
    if not solve_spd(work, coef, 6):
        return FIT_DEGENERATE
    poly[P_Q] = x[0] + mx
    poly[P_Q + 1] = x[1] + my
    poly[P_Q + 2] = x[2] + mz
    for a in range(6):
        poly[P_C + a] = coef[a]
    poly[P_COLOR] = cr / sw
    poly[P_COLOR + 1] = cg / sw
    poly[P_COLOR + 2] = cb / sw
    poly[P_SCALE] = scale
    return FIT_OK


@numba.njit(cache=True, fastmath=True)
def poly_local(poly, x):
    """x in the polynomial's scaled frame over H: (u, v) along e1, e2 and the height f along n."""
    s = poly[P_SCALE]
    rx, ry, rz = (x[0] - poly[P_Q]) / s, (x[1] - poly[P_Q + 1]) / s, (x[2] - poly[P_Q + 2]) / s
    u = rx * poly[P_E1] + ry * poly[P_E1 + 1] + rz * poly[P_E1 + 2]
    v = rx * poly[P_E2] + ry * poly[P_E2 + 1] + rz * poly[P_E2 + 2]
    f = rx * poly[P_N] + ry * poly[P_N + 1] + rz * poly[P_N + 2]
    return u, v, f


@numba.njit(cache=True, fastmath=True)
def poly_project(poly, x, out):
    """P(x): x moved along n onto the polynomial over H; returns the squared step."""
    s = poly[P_SCALE]
    u, v, f = poly_local(poly, x)
    c = poly[P_C:P_C + 6]
    g = c[0] + c[1] * u + c[2] * v + c[3] * u * u + c[4] * u * v + c[5] * v * v
    step = (g - f) * s
    for a in range(3):
        out[a] = x[a] + step * poly[P_N + a]
    return step * step


@numba.njit(cache=True, fastmath=True)
def poly_normal(poly, x, out):
    """Unit normal of the polynomial surface at (the foot point of) x: n - g_u e1 - g_v e2."""
    u, v, _ = poly_local(poly, x)
    c = poly[P_C:P_C + 6]
    gu = c[1] + 2.0 * c[3] * u + c[4] * v
    gv = c[2] + c[4] * u + 2.0 * c[5] * v
    length = 0.0
    for a in range(3):
        out[a] = poly[P_N + a] - gu * poly[P_E1 + a] - gv * poly[P_E2 + a]
        length += out[a] * out[a]
    length = math.sqrt(length)
    for a in range(3):
        out[a] /= length


@numba.njit(cache=True, fastmath=True)
def poly_ray(poly, o, d, t_lo, t_hi):
    """Smallest t in [t_lo, t_hi] where the ray o + t d meets the polynomial, or -1.

    In the frame of H the ray is linear, (u, v, f)(t) = (u0, v0, f0) + t (du, dv, df), so
    g(u(t), v(t)) - f(t) = 0 is a quadratic A t^2 + B t + C = 0.
    """
    s = poly[P_SCALE]
    rx, ry, rz = (o[0] - poly[P_Q]) / s, (o[1] - poly[P_Q + 1]) / s, (o[2] - poly[P_Q + 2]) / s
    u0 = rx * poly[P_E1] + ry * poly[P_E1 + 1] + rz * poly[P_E1 + 2]
    v0 = rx * poly[P_E2] + ry * poly[P_E2 + 1] + rz * poly[P_E2 + 2]
    f0 = rx * poly[P_N] + ry * poly[P_N + 1] + rz * poly[P_N + 2]
    du = (d[0] * poly[P_E1] + d[1] * poly[P_E1 + 1] + d[2] * poly[P_E1 + 2]) / s
    dv = (d[0] * poly[P_E2] + d[1] * poly[P_E2 + 1] + d[2] * poly[P_E2 + 2]) / s
    df = (d[0] * poly[P_N] + d[1] * poly[P_N + 1] + d[2] * poly[P_N + 2]) / s
    c = poly[P_C:P_C + 6]
    qa = c[3] * du * du + c[4] * du * dv + c[5] * dv * dv
    qb = c[1] * du + c[2] * dv + 2.0 * c[3] * u0 * du + c[4] * (u0 * dv + v0 * du) + 2.0 * c[5] * v0 * dv - df
    qc = c[0] + c[1] * u0 + c[2] * v0 + c[3] * u0 * u0 + c[4] * u0 * v0 + c[5] * v0 * v0 - f0
    if abs(qa) * (t_hi - t_lo) < 1e-9 * abs(qb):
        if qb == 0.0:
            return -1.0
        t = -qc / qb
        return t if t_lo <= t <= t_hi else -1.0
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0:
        return -1.0
    sq = math.sqrt(disc)
    # numerically stable pair of roots
    k = -0.5 * (qb + (sq if qb >= 0.0 else -sq))
    t1 = k / qa
    t2 = qc / k if k != 0.0 else t1
    if t1 > t2:
        t1, t2 = t2, t1
    if t_lo <= t1 <= t_hi:
        return t1
    if t_lo <= t2 <= t_hi:
        return t2
    return -1.0


@numba.njit(cache=True)
def project_points(xs, points, spacing, h, colors, domain, cell, lower, dims, order, starts, scale,
                   tolerance, max_iter, out, status, iterations):
    """Iterate r <- P(r) for every row of xs until the step is below tolerance * scale."""
    poly = np.empty(POLY_SIZE)
    work = np.empty((7, 7))
    nb = np.empty((MAX_NEIGHBOURS, 4))
    x = np.empty(3)
    y = np.empty(3)
    for k in range(len(xs)):
        x[:] = xs[k]
        status[k] = FIT_NOT_CONVERGED
        for it in range(max_iter):
            st = fit(x, points, spacing, h, colors, domain, cell, lower, dims, order, starts, scale, poly, work, nb)
            iterations[k] = it + 1
            if st != FIT_OK:
                status[k] = st
                break
            step2 = poly_project(poly, x, y)
            x[:] = y
            if step2 < (tolerance * scale) ** 2:
                status[k] = FIT_OK
                break
        out[k] = x


@numba.njit(cache=True, parallel=True)
def fit_points(points, spacing, h, colors, domain, cell, lower, dims, order, starts, scale, polys, status):
    """The polynomial of every sample point (the per-point pre-pass of both ray tracers)."""
    for k in numba.prange(len(points)):
        work = np.empty((7, 7))
        nb = np.empty((MAX_NEIGHBOURS, 4))
        status[k] = fit(points[k], points, spacing, h, colors, domain, cell, lower, dims, order, starts,
                        scale, polys[k], work, nb)


def surface_args(surface: MLSSurface) -> tuple:
    """The array arguments of `fit`, in order, after x."""
    return (surface.points, surface.spacing, surface.h, surface.colors, surface.domain, surface.cell,
            surface.lower, surface.dims, surface.order, surface.starts, surface.scale)


@dataclass(frozen=True)
class Projection:
    """Result of `project`: projected points, FIT_* status and iteration count per point."""

    points: np.ndarray
    status: np.ndarray
    iterations: np.ndarray


def project(surface: MLSSurface, xs: np.ndarray, tolerance: float = 1e-4, max_iter: int = 20) -> Projection:
    """Project points (in the surface's local coordinates) onto the MLS surface."""
    xs = np.ascontiguousarray(np.atleast_2d(xs), dtype=np.float64)
    out = np.empty_like(xs)
    status = np.empty(len(xs), np.int64)
    iterations = np.zeros(len(xs), np.int64)
    project_points(xs, *surface_args(surface), float(tolerance), int(max_iter), out, status, iterations)
    return Projection(out, status, iterations)


def point_polynomials(surface: MLSSurface) -> tuple[np.ndarray, np.ndarray]:
    """(N, POLY_SIZE) polynomial of each sample point and its FIT_* status."""
    n = len(surface.points)
    polys = np.zeros((n, POLY_SIZE))
    status = np.empty(n, np.int64)
    fit_points(*surface_args(surface), polys, status)
    return polys, status
