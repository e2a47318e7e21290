"""Tangent frames: the circular splat axes of a normal and a radius, and elliptical ones.

The branch-free orthonormal basis of Duff, Burgess, Christensen, Hery, Kensler, Liani &
Villemin 2017, "Building an orthonormal basis, revisited" (JCGT 6(1), listing 3): for a unit
normal n = (x, y, z), with sigma = copysign(1, z) and a = -1 / (sigma + z), b = x y a (no
singularity: Frisvad 2012's formula, which this revises, breaks down near z = -1),

    t = (1 + sigma x^2 a, sigma b, -sigma x),    s = (b, sigma + y^2 a, -y),

so that (t, s, n) is orthonormal and right-handed. A circular splat of radius r has the axes
(r t, r s).

The kernels run in one compiled pass over the rows: every estimation of `complete.py` asks
for unit normals and tangent frames of millions of points, which numpy's temporaries made
a visible share of a hierarchy build. For the same reason `unit` gives back an array it made
itself as it is, so that the unit normals made once are passed on to every estimation, each
of which asks for them again.
"""

from __future__ import annotations

import math
import weakref

import numba
import numpy as np

from ..cloud import read_only


@numba.njit(cache=True, inline="always")
def _unit_row(v, i):  # pragma: no cover - compiled
    """Row i of v (N, 3) float64 divided by max(|v_i|, 1e-300)."""
    length = max(math.sqrt(v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]), 1e-300)
    return v[i, 0] / length, v[i, 1] / length, v[i, 2] / length


@numba.njit(cache=True, inline="always")
def _row_basis(x, y, z):  # pragma: no cover - compiled
    """(t, s) of the module docstring for the unit normal (x, y, z), as six values."""
    sign = math.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    return 1.0 + sign * x * x * a, sign * b, -sign * x, b, sign + y * y * a, -y


@numba.njit(parallel=True, cache=True)
def _unit_rows(v):  # pragma: no cover - compiled
    """Rows of v (N, 3) float64 divided by max(|v_i|, 1e-300)."""
    out = np.empty_like(v)
    for i in numba.prange(len(v)):
        out[i, 0], out[i, 1], out[i, 2] = _unit_row(v, i)
    return out


@numba.njit(parallel=True, cache=True)
def _basis(n):  # pragma: no cover - compiled
    """(t, s) of the module docstring for each row of n (N, 3) float64."""
    frames = np.empty((len(n), 2, 3))
    for i in numba.prange(len(n)):
        (frames[i, 0, 0], frames[i, 0, 1], frames[i, 0, 2],
         frames[i, 1, 0], frames[i, 1, 1], frames[i, 1, 2]) = _row_basis(n[i, 0], n[i, 1], n[i, 2])
    return frames


@numba.njit(parallel=True, cache=True)
def _axes(v, radii):  # pragma: no cover - compiled
    """(t, s) of the unit rows of v (N, 3) float64, times radii (N,) float64, as float32: the
    steps of `_unit_rows` and `_basis` in one pass (one rounding to float32 at the end), so
    that no (N, 2, 3) float64 temporaries are written and read back."""
    axes = np.empty((len(v), 2, 3), np.float32)
    for i in numba.prange(len(v)):
        x, y, z = _unit_row(v, i)
        tx, ty, tz, sx, sy, sz = _row_basis(x, y, z)
        r = radii[i]
        axes[i, 0, 0], axes[i, 0, 1], axes[i, 0, 2] = tx * r, ty * r, tz * r
        axes[i, 1, 0], axes[i, 1, 1], axes[i, 1, 2] = sx * r, sy * r, sz * r
    return axes


# the arrays `unit` made (read-only, so they still hold unit rows), by id
_MADE: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of v (N, 3) scaled to unit length, float64 (zero rows stay zero), read-only; an
    array unit made is given back as it is (dividing its rows by their lengths, one up to an
    ulp, could round them differently)."""
    if _MADE.get(id(v)) is v:
        return v
    rows = read_only(_unit_rows(np.ascontiguousarray(v, np.float64)))
    _MADE[id(rows)] = rows
    return rows


def orthonormal_basis(normals: np.ndarray) -> np.ndarray:
    """Unit tangents (N, 2, 3) float64, (t, s): (t, s, n) right-handed for unit normals (N, 3)."""
    return _basis(np.ascontiguousarray(normals, np.float64))


def tangent_frames(normals: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Circular splat axes (N, 2, 3) float32: orthonormal tangents of the (unit) normals, scaled
    by the radii; (u, v, n) is right-handed."""
    return _axes(np.ascontiguousarray(normals, np.float64), np.ascontiguousarray(radii, np.float64))


def ellipse_axes(frames: np.ndarray, semi: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Axes (m, 2, 3) of ellipses with semi-axes `semi` (m, 2) along `direction` (m, 2: cos,
    sin) in the tangent frames (t, s) = frames (m, 2, 3): u the major axis, (u, v, n)
    right-handed."""
    t, s = frames[:, 0], frames[:, 1]
    co, si = direction[:, 0:1], direction[:, 1:2]
    major = semi[:, 0] >= semi[:, 1]
    e1 = co * t + si * s
    e2 = -si * t + co * s
    # u is the major axis; (e2, -e1) keeps (u, v, n) right-handed
    u = np.where(major[:, None], e1 * semi[:, 0:1], e2 * semi[:, 1:2])
    v = np.where(major[:, None], e2 * semi[:, 1:2], -e1 * semi[:, 0:1])
    return np.stack([u, v], axis=1)
