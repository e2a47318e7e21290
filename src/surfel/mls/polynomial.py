"""The local bivariate quadratic of an MLS fit: its row layout and the small dense algebra
the fit and the ray tracers share (numba, also mirrored in gpu.glsl).

A fit over the reference plane H (origin q, unit normal n, tangent frame e1, e2 from
`tangent_frame`) holds, in units of the local kernel width l,

    g(u, v) = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2,
    (u, v, f) = coordinates of (x - q) / l in (e1, e2, n).

Projection moves x along n onto g: P(x) = x + l (g(u, v) - f) n. The surface's normal there is
n - g_u e1 - g_v e2, normalised. A ray o + t d is linear in (u, v, f), so meeting g is the
quadratic A t^2 + B t + C = 0 (`poly_ray`), solved with the numerically stable pair of roots.
The quadratic's 6x6 normal equations are solved by Cholesky.
"""

from __future__ import annotations

import math

import numba

# Layout of one fitted polynomial row: q, n, e1, e2, coefficients c0..c5, colour, local width l.
P_Q, P_N, P_E1, P_E2, P_C, P_COLOR, P_SCALE = 0, 3, 6, 9, 12, 18, 21
POLY_SIZE = 22


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
    """Unit normal of the polynomial surface at (the foot point of) x: n - g_u e1 - g_v e2
    (on the side of the plane normal n, which faces the fit's reference normal)."""
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
