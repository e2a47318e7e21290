"""Normals, radii, tangent frames, ellipses and normal fields from raw points."""

import numpy as np
from scipy.spatial import cKDTree

from conftest import data_file
from surfel.cloud import PointCloud
from surfel.io import load
from surfel.preprocess import (estimate_normals, estimate_radii, fit_ellipses, fit_normal_field, prepare,
                               tangent_frames)


def sphere(n=4000, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return p * (1 + noise * rng.normal(size=(n, 1))), p.copy()


def covered_fraction(samples, centers, normals, axes, radius_reach):
    """Fraction of surface samples inside some splat ellipse (near its plane)."""
    tree = cKDTree(centers)
    inside = np.zeros(len(samples), bool)
    for j, cand in enumerate(tree.query_ball_point(samples, radius_reach)):
        if not cand:
            continue
        d = samples[j] - centers[cand]
        u = np.einsum("ij,ij->i", d, axes[cand, 0]) / np.einsum("ij,ij->i", axes[cand, 0], axes[cand, 0])
        v = np.einsum("ij,ij->i", d, axes[cand, 1]) / np.einsum("ij,ij->i", axes[cand, 1], axes[cand, 1])
        inside[j] = (u * u + v * v <= 1).any()
    return inside.mean()


def mesh_samples(cloud, count, seed=1):
    rng = np.random.default_rng(seed)
    tri = cloud.positions[cloud.faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), count, p=area / area.sum())
    a, b = rng.random((2, count, 1))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[pick]
    return t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])


def test_pca_normals_on_a_sphere_are_accurate_and_outward():
    points, truth = sphere(noise=0.002)
    normals, ambiguous = estimate_normals(points, k=16)
    dots = np.einsum("ij,ij->i", normals, truth)
    assert np.median(dots) > 0.99 and (dots > 0).all()  # outward everywhere, without a viewpoint
    assert ambiguous == 0


def test_orientation_towards_a_viewpoint():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, (2000, 2))
    points = np.c_[xy, 0.001 * rng.normal(size=2000)]
    normals, _ = estimate_normals(points, viewpoint=[0.0, 0.0, -5.0])
    assert (normals[:, 2] < -0.99).all()


def test_degenerate_neighbourhoods_are_reported():
    t = np.linspace(0, 1, 500)
    line = np.c_[t, 2 * t, -t] + 1e-6 * np.random.default_rng(0).normal(size=(500, 3))
    _, ambiguous = estimate_normals(line)
    assert ambiguous > 250


def test_bunny_normals_agree_with_the_mesh():
    mesh = load(data_file("stanford-bunny.obj"))
    normals, _ = estimate_normals(mesh.positions)
    agree = np.einsum("ij,ij->i", normals, mesh.normals) > 0
    assert agree.mean() >= 0.99


def test_estimated_radii_cover_the_surface_without_holes():
    mesh = load(data_file("stanford-bunny.obj"))
    samples = mesh_samples(mesh, 100_000)
    for step in (1, 4):  # the scan, and the scan thinned to every 4th point
        idx = np.arange(0, len(mesh), step)
        centers, normals = mesh.positions[idx], mesh.normals[idx]
        radii = estimate_radii(centers, normals)
        axes = tangent_frames(normals, radii).astype(np.float64)
        # the surface sample lies within a splat's disk after projection onto the splat plane
        assert covered_fraction(samples, centers, normals, axes, float(radii.max())) >= 0.999


def test_tangent_frames_are_orthonormal_and_scaled():
    _, normals = sphere(500)
    radii = np.linspace(0.5, 2, 500)
    axes = tangent_frames(normals, radii)
    u, v = axes[:, 0] / radii[:, None], axes[:, 1] / radii[:, None]
    for a, b in ((u, v), (u, normals), (v, normals)):
        assert np.abs(np.einsum("ij,ij->i", a, b)).max() < 1e-5
    assert np.allclose(np.linalg.norm(u, axis=1), 1, atol=1e-5)


def test_ellipses_cover_at_least_the_circles():
    mesh = load(data_file("spot.obj"))
    radii = estimate_radii(mesh.positions, mesh.normals)
    axes = fit_ellipses(mesh.positions, mesh.normals, radii)
    lengths = np.linalg.norm(axes, axis=2)
    assert (lengths >= radii[:, None] * 0.999).all()
    assert np.abs(np.einsum("ij,ij->i", axes[:, 0], axes[:, 1])).max() < 1e-4
    assert (lengths[:, 0] > 1.05 * lengths[:, 1]).any()  # elongated where the sampling is


def test_normal_field_reproduces_a_sphere_better_than_constant_normals():
    points, truth = sphere(6000)
    radii = estimate_radii(points, truth)
    axes = tangent_frames(truth, radii)
    alpha, beta = fit_normal_field(points, truth, axes)
    # on the unit sphere N(u, v) = n + u û |a| + ...: the slope equals the semi-axis length
    assert np.allclose(alpha, radii, rtol=0.1) and np.allclose(beta, radii, rtol=0.1)
    j = 0
    q = points[1:200]
    d = q - points[j]
    u = d @ axes[j, 0] / (axes[j, 0] @ axes[j, 0])
    v = d @ axes[j, 1] / (axes[j, 1] @ axes[j, 1])
    near = u * u + v * v <= 1
    field = truth[j] + u[:, None] * alpha[j] * axes[j, 0] / radii[j] + v[:, None] * beta[j] * axes[j, 1] / radii[j]
    field /= np.linalg.norm(field, axis=1, keepdims=True)
    if near.any():
        assert (np.einsum("ij,ij->i", field[near], truth[1:200][near])
                >= np.einsum("j,ij->i", truth[j], truth[1:200][near]) - 1e-9).all()


def test_prepare_fills_only_what_is_missing():
    points, truth = sphere(1000)
    full = PointCloud(points, normals=truth)
    prepared, report = prepare(full)
    assert "normals" not in report and {"radii", "axes"} <= set(report)
    assert np.array_equal(prepared.normals, full.normals)
    raw, report = prepare(PointCloud(points), normal_field=True)
    assert {"normals", "radii", "axes", "normal_field"} <= set(report)
    assert "phong_alpha" in raw.extras and raw.axes.shape == (1000, 2, 3)
    again, report = prepare(raw)
    assert report == {} and again is raw
