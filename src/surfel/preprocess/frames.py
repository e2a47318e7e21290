"""Tangent frames: the circular splat axes of a normal and a radius.

The branch-free orthonormal basis of Duff, Burgess, Christensen, Hery, Kensler, Liani &
Villemin 2017, "Building an orthonormal basis, revisited" (JCGT 6(1), listing 3): for a unit
normal n = (x, y, z), with sigma = copysign(1, z) and a = -1 / (sigma + z), b = x y a (no
singularity: Frisvad 2012's formula, which this revises, breaks down near z = -1),

    t = (1 + sigma x^2 a, sigma b, -sigma x),    s = (b, sigma + y^2 a, -y),

so that (t, s, n) is orthonormal and right-handed. A circular splat of radius r has the axes
(r t, r s).
"""

from __future__ import annotations

import numpy as np


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of v scaled to unit length (zero rows stay zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def orthonormal_basis(normals: np.ndarray) -> np.ndarray:
    """Unit tangents (N, 2, 3) float64, (t, s): (t, s, n) right-handed for unit normals (N, 3)."""
    n = np.asarray(normals, np.float64)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sign = np.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    s = np.stack([b, sign + y * y * a, -y], axis=1)
    return np.stack([t, s], axis=1)


def tangent_frames(normals: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Circular splat axes (N, 2, 3) float32: orthonormal tangents of the (unit) normals, scaled
    by the radii; (u, v, n) is right-handed."""
    tangents = orthonormal_basis(unit(np.asarray(normals, np.float64)))
    return (tangents * np.asarray(radii, np.float64)[:, None, None]).astype(np.float32)
