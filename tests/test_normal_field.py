"""Phong splatting's normal field: the fitted slopes reproduce the true normals."""

from __future__ import annotations

import numpy as np

from samples import angles, sphere
from surfel.preprocess import fit_ellipses, fit_normal_field


def test_normal_field_reproduces_sphere_normals():
    p = sphere(20_000, seed=9)
    axes = fit_ellipses(p, p)
    alpha, beta = fit_normal_field(p, p, axes)
    lengths = np.linalg.norm(axes.astype(np.float64), axis=2)
    # on the unit sphere the normal tilts by (semi-axis / radius) at the rim: alpha = |u|, beta = |v|
    assert np.allclose(alpha, lengths[:, 0], rtol=0.1) and np.allclose(beta, lengths[:, 1], rtol=0.1)
    # evaluate at random points of every splat against the true normal there
    rng = np.random.default_rng(10)
    r, phi = np.sqrt(rng.random(len(p))), rng.uniform(0, 2 * np.pi, len(p))
    u, v = r * np.cos(phi), r * np.sin(phi)
    unit_axes = axes / lengths[..., None]
    q = p + u[:, None] * axes[:, 0] + v[:, None] * axes[:, 1]
    field = p + (u * alpha)[:, None] * unit_axes[:, 0] + (v * beta)[:, None] * unit_axes[:, 1]
    constant_error, field_error = angles(p, q).mean(), angles(field, q).mean()
    assert field_error < 0.1 * constant_error
