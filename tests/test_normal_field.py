"""Phong splatting's normal field: the fitted slopes reproduce the true normals; the field that
shapes a curved splat leaves a face's rim out."""

from __future__ import annotations

import numpy as np

from samples import angles, capped_cylinder, sphere
from surfel.attributes import FIELD_SLOPES
from surfel.cloud import PointCloud
from surfel.preprocess import fit_ellipses, fit_normal_field, prepare


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


def test_the_field_fits_the_normals_inside_its_splat():
    """Where the curvature grows away from a splat (z = x^2 + 30 x^4, a splat of 0.75 grid
    spacings at x = 0), its slope is the curvature there, 2 r, to within 20%: the neighbours
    beyond its rim, which curve more, weigh less (unweighted, the slope was 36% too steep)."""
    spacing, radius = 0.05, 0.0375
    grid = np.arange(-1, 1 + 1e-9, spacing)
    x, y = (m.ravel() for m in np.meshgrid(grid, grid))
    slope = 2 * x + 120 * x**3
    normals = np.c_[-slope, np.zeros_like(x), np.ones_like(x)]
    tangents = np.c_[np.ones_like(x), np.zeros_like(x), slope]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    axes = np.stack([tangents, np.tile([0.0, 1.0, 0.0], (len(x), 1))], axis=1) * radius
    alpha, beta = fit_normal_field(np.c_[x, y, x**2 + 30 * x**4], normals, axes.astype(np.float32))
    centre = np.flatnonzero((np.abs(x) < 1e-9) & (np.abs(y) < 1e-9))[0]
    assert 2 * radius <= abs(alpha[centre]) <= 1.2 * 2 * radius
    assert abs(beta[centre]) < 1e-6  # no curvature along y


def test_the_far_side_of_a_thin_tube_does_not_flatten_its_field():
    """A tube of radius 1 sampled as rings of 8 points 2.5 apart (a coarse tail): a splat's
    16 neighbours include the far side of the tube, facing away and off its plane. Fitted as
    the same sheet seen from behind, their normals, nearly opposite its own and so barely
    tilted at small offsets, flattened the slope around the tube to 0.01; fitted on its own
    side only, it is the side's: tilt tan 45 degrees at the ring neighbours' sin 45 degrees,
    over 1 at the rim of a splat half a radius wide."""
    rings = np.arange(-5, 6) * 2.5
    theta = np.arange(8) * (2 * np.pi / 8)
    x, t = (m.ravel() for m in np.meshgrid(rings, theta))
    normals = np.c_[np.zeros_like(x), np.cos(t), np.sin(t)]
    around = np.c_[np.zeros_like(x), -np.sin(t), np.cos(t)]
    axes = np.stack([np.tile([1.25, 0.0, 0.0], (len(x), 1)), 0.5 * around], axis=1)
    alpha, beta = fit_normal_field(np.c_[x, normals[:, 1:]], normals, axes.astype(np.float32))
    middle = np.abs(x) < 1e-9
    np.testing.assert_allclose(beta[middle], 0.5 * np.tan(np.pi / 4) / np.sin(np.pi / 4), rtol=0.1)
    np.testing.assert_allclose(alpha[middle], 0.0, atol=1e-6)  # straight along the tube


def test_a_face_is_shaped_flat_up_to_its_rim_and_shaded_round():
    """A flat cap meeting a cylinder 12 vertices round, as a CAD part's mesh has them: the
    rim's normals are averaged over cap and side. The cap's shading field tilts towards the
    rim, as the mesh's interpolated normals shade it; the field that shapes its curved splats
    leaves the rim out and is flat, so that they reach the edge instead of bending down short
    of it. Scanned with noise and no normals, a normal far off is noise: one field."""
    side, cap, circle, normals = capped_cylinder()
    step = 2 * np.pi / len(circle)
    prepared, _ = prepare(PointCloud(np.concatenate([side, cap, circle]), normals=normals), normal_field=True)
    slopes = {key: np.abs(prepared.attributes[key]) for key in FIELD_SLOPES}
    cap_points = np.arange(len(side), len(side) + len(cap))
    by_rim = cap_points[np.hypot(*cap[:, :2].T) > 1 - step]
    assert np.median(np.maximum(slopes["phong_alpha"], slopes["phong_beta"])[by_rim]) > 0.15
    assert np.maximum(slopes["curve_alpha"], slopes["curve_beta"])[cap_points].max() < 1e-6
    # the side below its first ring, curved, is shaped by its curvature as it is shaded
    below = np.flatnonzero(side[:, 2] < -1.5 * step)
    for shading, shape in (("phong_alpha", "curve_alpha"), ("phong_beta", "curve_beta")):
        np.testing.assert_allclose(slopes[shape][below], slopes[shading][below], atol=0.05)
    assert np.maximum(slopes["curve_alpha"], slopes["curve_beta"])[below].min() > 0.2

    # scanned: sampled finer (48 round, the noise a sixth of the step) so that noise, not the
    # coarse part's curvature, scatters its neighbourhoods (normals.py: a noisy cloud)
    points = np.concatenate(capped_cylinder(48)[:3])
    scanned = points + np.random.default_rng(0).normal(0, 0.02, points.shape)
    noisy, report = prepare(PointCloud(scanned), normal_field=True)
    assert "(noisy)" in report["normals"]
    for shading, shape in (("phong_alpha", "curve_alpha"), ("phong_beta", "curve_beta")):
        np.testing.assert_array_equal(noisy.attributes[shading], noisy.attributes[shape])
