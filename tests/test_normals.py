"""Normals: PCA directions, scale selection on noisy clouds and quadrics on clean ones, orientation by
propagation or towards a viewpoint, ambiguity."""

from __future__ import annotations

import numpy as np

from models import spot
from samples import angles, dense_samples, sphere
from surfel.cloud import PointCloud
from surfel.preprocess import estimate_normals, estimate_radii, prepare
from surfel.preprocess.jets import jet_normals
from surfel.preprocess.neighbourhood import Neighbourhood, as_points
from surfel.preprocess.normals import (
    NORMAL_NEIGHBOURS,
    SCALES,
    faces_inward,
    is_noisy,
    orient_given,
    pca_normals,
    signs_at_random,
)


def test_pca_normals_plane_and_sphere():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (20_000, 2))
    plane = np.c_[xy, rng.normal(0, 0.001, len(xy))]  # noise 1/14 of the spacing
    normals, _ = estimate_normals(plane)
    assert normals.dtype == np.float32 and normals.shape == plane.shape
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5)
    assert np.percentile(angles(normals, np.tile([0.0, 0, 1], (len(xy), 1)), oriented=False), 95) < 5
    p = sphere(20_000, noise=0.001)
    normals, _ = estimate_normals(p)
    assert np.percentile(angles(normals, p, oriented=False), 95) < 3


def test_orientation_sphere_outward_without_viewpoint():
    p = sphere(20_000)
    normals, ambiguous = estimate_normals(p)
    assert (np.einsum("ij,ij->i", normals, p) > 0).all()
    assert ambiguous == 0


def test_orientation_each_component_outward():
    a, b = sphere(5_000, seed=1), 0.5 * sphere(3_000, seed=2) + [5, 0, 0]  # two separate closed scans
    p = np.concatenate([a, b])
    normals, _ = estimate_normals(p)
    centre = np.where(np.arange(len(p))[:, None] < len(a), 0.0, [5.0, 0, 0])
    assert (np.einsum("ij,ij->i", normals, p - centre) > 0).all()


def test_orientation_matches_mesh():
    vertices, mesh_normals, _ = dense_samples()
    normals, ambiguous = estimate_normals(vertices)
    agree = np.einsum("ij,ij->i", normals, mesh_normals) > 0
    assert agree.mean() >= 0.99
    assert ambiguous < 0.01 * len(vertices)


def test_whether_given_normals_face_inward():
    p = sphere(5_000)
    assert faces_inward(p, -p) and not faces_inward(p, p)
    model = spot()
    assert faces_inward(model.positions, -model.normals) and not faces_inward(model.positions, model.normals)
    rng = np.random.default_rng(4)
    plane = np.c_[rng.uniform(-1, 1, (5_000, 2)), np.zeros(5_000)]
    up = np.tile([0.0, 0, 1], (5_000, 1))
    assert not faces_inward(plane, up) and not faces_inward(plane, -up)  # no outside to face
    signs = np.where(rng.random(5_000) < 0.5, -1.0, 1.0)[:, None]
    assert not faces_inward(p, signs * p)  # half each way: no orientation to turn


def test_given_signs_at_random_are_told_from_a_consistent_orientation():
    model = spot()
    nbh = Neighbourhood.build(model.positions, 9)
    normals = nbh.sort(model.normals.astype(np.float64))
    signs = np.where(np.random.default_rng(5).random(len(normals)) < 0.5, -1.0, 1.0)[:, None]
    assert signs_at_random(nbh, signs * normals)
    assert not signs_at_random(nbh, normals) and not signs_at_random(nbh, -normals)
    # a fifth flipped in patches (normals oriented towards one side, each region its own way) is kept
    patches = np.where(nbh.points[:, 0] > np.quantile(nbh.points[:, 0], 0.8), -1.0, 1.0)[:, None]
    assert not signs_at_random(nbh, patches * normals)
    # a two-sided mesh repeats each vertex, facing away, for its back faces: no sign at random
    doubled = Neighbourhood.build(np.concatenate([model.positions, model.positions]), 9)
    assert not signs_at_random(doubled, doubled.sort(np.concatenate([model.normals, -model.normals])))
    kept, how = orient_given(nbh, normals, closed_mesh=True)
    assert kept is normals and how is None
    turned, how = orient_given(nbh, -normals, closed_mesh=True)
    assert np.array_equal(turned, normals) and how.startswith("a closed mesh's, facing inward")
    kept, how = orient_given(nbh, -normals, closed_mesh=False)  # a point cloud's: maybe seen from inside
    assert np.array_equal(kept, -normals) and how is None
    oriented, how = orient_given(nbh, signs * normals, closed_mesh=False)
    assert how.startswith("with signs that disagree") and (np.einsum("ij,ij->i", oriented, normals) > 0.99).all()


def test_orientation_towards_viewpoint():
    p = sphere(5_000)
    inward, _ = estimate_normals(p, viewpoint=np.zeros(3))  # a sensor inside the sphere
    assert (np.einsum("ij,ij->i", inward, p) < 0).all()
    rng = np.random.default_rng(3)
    plane = np.c_[rng.uniform(-1, 1, (5_000, 2)), np.zeros(5_000)]
    up, _ = estimate_normals(plane, viewpoint=[0, 0, 10])
    assert (up[:, 2] > 0.99).all()
    sensors = plane + np.where(plane[:, :1] > 0, 1.0, -1.0) * [0, 0, 1]  # per-point sensor positions
    mixed, _ = estimate_normals(plane, viewpoint=sensors)
    assert np.array_equal(np.sign(mixed[:, 2]), np.sign(plane[:, 0]))


def test_ambiguous_on_degenerate_input():
    t = np.linspace(0, 1, 500)
    line = np.c_[t, 2 * t, -t]
    _, ambiguous = estimate_normals(line)
    assert ambiguous == len(line)
    rng = np.random.default_rng(4)
    a = rng.uniform(-1, 1, (4_000, 2))
    crossing = np.concatenate([np.c_[a[:2000], np.zeros(2000)], np.c_[a[2000:, 0], np.zeros(2000), a[2000:, 1]]])
    _, ambiguous = estimate_normals(crossing)
    assert 0 < ambiguous < 0.2 * len(crossing)  # along the intersection line only


def test_georeferenced_coordinates_keep_precision():
    rng = np.random.default_rng(5)
    local = np.c_[rng.uniform(0, 50, (5_000, 2)), rng.normal(0, 0.01, 5_000)]
    offset = np.array([636_000.0, 849_000.0, 400.0])
    n0, _ = estimate_normals(local, viewpoint=[25, 25, 100])
    n1, _ = estimate_normals(local + offset, viewpoint=offset + [25, 25, 100])
    assert np.allclose(n0, n1, atol=1e-4)
    assert np.allclose(estimate_radii(local), estimate_radii(local + offset), rtol=1e-4)


def pca_and_quadric_normals(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented PCA normals over 16 neighbours, and the same refined by quadrics (jets.py)."""
    nbh = Neighbourhood.build(as_points(p), NORMAL_NEIGHBOURS, -1, False)
    normals, degenerate, _ = pca_normals(nbh, NORMAL_NEIGHBOURS, False)
    refined = jet_normals(nbh.points, nbh.first(NORMAL_NEIGHBOURS), normals, degenerate)
    return nbh.unsort(normals), nbh.unsort(refined)


def test_scale_selection_on_a_noisy_sphere():
    """Range noise of 0.4% of the radius (about a third of the spacing): each point's scale
    (Mitra & Nguyen's bound) gives normals well within those of the fixed k = 16; a clean
    sphere is not noisy: it keeps k = 16, refined by quadrics."""
    p = sphere(20_000, noise=0.004)
    plain, _ = estimate_normals(p)
    selected, _ = estimate_normals(p, adaptive=True)
    plain_error, selected_error = angles(plain, p, oriented=False), angles(selected, p, oriented=False)
    assert selected_error.mean() < 0.6 * plain_error.mean()
    assert np.percentile(selected_error, 95) < 4
    clean = sphere(20_000)
    adaptive, _ = estimate_normals(clean, adaptive=True)
    assert np.allclose(np.abs(np.einsum("ij,ij->i", adaptive, pca_and_quadric_normals(clean)[1])), 1, atol=1e-6)


def test_a_coarse_mesh_s_vertices_are_not_noisy():
    """Spot's 2,930 vertices scatter a plane fit beyond NOISE_SCATTERING by curvature alone, but
    more at the widest scale than at the first, where noise would scatter less: they are not
    noisy and keep k = 16, refined by quadrics (each point's scale took them 6.06 degrees from
    the mesh's normals on average, k = 16 5.88), as does a coarse sphere."""
    mesh = spot()
    for p in (np.asarray(mesh.positions), sphere(200)):
        first = Neighbourhood.build(as_points(p), SCALES[0], -1, False)
        assert is_noisy(pca_normals(first, SCALES[0], False)[2])
        adaptive, _ = estimate_normals(p, adaptive=True)
        assert np.allclose(np.abs(np.einsum("ij,ij->i", adaptive, pca_and_quadric_normals(p)[1])), 1, atol=1e-6)
        _, report = prepare(PointCloud(p))
        assert report["normals"].startswith("estimated (PCA, k=16, refined by quadrics,")
    assert angles(estimate_normals(np.asarray(mesh.positions))[0], mesh.normals).mean() < 6


def test_quadrics_bring_a_coarse_figure_s_normals_nearer_the_mesh_s():
    """Spot's vertices without normals: the quadrics take the normals' mean angle from the mesh's
    from 5.9 degrees (PCA over 16 neighbours) to 3.4."""
    mesh = spot()
    p = np.asarray(mesh.positions)
    plain, adaptive = estimate_normals(p)[0], estimate_normals(p, adaptive=True)[0]
    assert angles(adaptive, mesh.normals).mean() < 0.65 * angles(plain, mesh.normals).mean()


def test_quadrics_follow_a_coarsely_sampled_curved_patch():
    """A saddle z = x^2 - 0.6 y^2 sampled on a jittered 16 x 16 grid over [-1, 1]^2 (its normals
    turn by 15 degrees from one sample to the next): PCA's planes tilt with the curvature, most
    where the neighbours lie on one side (the patch's rim); the quadrics' normals come at least
    three times nearer the true ones on average, and at the rim too."""
    rng = np.random.default_rng(3)
    g = np.linspace(-1, 1, 16)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.02, 0.02, (256, 2))
    p = np.c_[xy, xy[:, 0] ** 2 - 0.6 * xy[:, 1] ** 2]
    true = np.c_[-2 * xy[:, 0], 1.2 * xy[:, 1], np.ones(len(p))]
    pca, quadric = pca_and_quadric_normals(p)
    pca_error, quadric_error = angles(pca, true, oriented=False), angles(quadric, true, oriented=False)
    rim = np.abs(xy).max(1) > 0.9
    assert quadric_error.mean() < pca_error.mean() / 3
    assert quadric_error[rim].mean() < pca_error[rim].mean() / 3


def test_a_crease_keeps_the_planes_normals():
    """Two faces meeting at a right angle (a roof): no quadric fits a neighbourhood across the
    ridge, so the points there keep their PCA normals exactly (as a mesh's vertex normals, the
    faces' mean, which the crease detection of sharp_features.py reads); on the faces, away from
    the ridge, both are the faces' own normals."""
    g = np.linspace(-1, 1, 21)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    p = np.c_[x, y, -np.abs(x)]
    pca, quadric = pca_and_quadric_normals(p)
    ridge, faces = np.abs(x) < 0.15, np.abs(x) > 0.45
    assert np.array_equal(quadric[ridge], pca[ridge])
    face_normals = np.c_[np.sign(x), np.zeros_like(x), np.ones_like(x)]
    assert angles(quadric[faces], face_normals[faces], oriented=False).max() < 0.01


def test_propagation_tree_is_a_minimum_spanning_forest():
    """Prim's forest of the propagation (numba) weighs what scipy's minimum spanning tree of the
    same symmetric kNN graph weighs: two implementations of one tree."""
    from scipy import sparse
    from scipy.sparse import csgraph

    from surfel.preprocess.neighbourhood import Neighbourhood
    from surfel.preprocess.normals import ORIENT_NEIGHBOURS, _propagate, pca_normals

    rng = np.random.default_rng(4)
    parts = [sphere(3_000, seed=5), 0.3 * sphere(500, seed=6) + [4, 0, 0], rng.uniform(-1, 1, (400, 3)) + [0, 5, 0]]
    nbh = Neighbourhood.build(np.concatenate(parts), 16, progress=False)
    normals = pca_normals(nbh, 16, False)[0]
    cols = np.ascontiguousarray(nbh.first(ORIENT_NEIGHBOURS + 1)[:, 1:])
    sign, parent, component, count, dots = _propagate(cols, normals)
    n = len(cols)
    weight = 1.0 - np.abs(np.einsum("ij,ikj->ik", normals, normals[cols])) + 1e-6
    graph = sparse.csr_matrix((weight.ravel(), cols.ravel(), np.arange(0, cols.size + 1, cols.shape[1])), (n, n))
    expected = csgraph.minimum_spanning_tree(graph.maximum(graph.T)).sum()
    tree = parent >= 0
    got = (1.0 - np.abs(np.einsum("ij,ij->i", normals[tree], normals[parent[tree]])) + 1e-6).sum()
    assert abs(got - expected) < 1e-9 * n
    assert count == csgraph.connected_components(graph, directed=False)[0] and count >= 3
    assert (component[parent[tree]] == component[tree]).all()
    # each point agrees with its parent
    assert (sign[tree] * sign[parent[tree]] * np.sign(dots[tree]) >= 0).all()


def test_geospatial_objects_keep_one_orientation():
    """A closed object in a LAS file (a terrestrial scan, a building's eaves): its normals are
    propagated, not each turned to +Z, so neighbours never face apart (they would read as the
    two sides of a sheet); a terrain patch still faces up."""
    from surfel.cloud import PointCloud
    from surfel.preprocess import prepare

    ball = sphere(20_000) * 10.0 + [500.0, 300.0, 20.0]
    cloud, report = prepare(PointCloud(ball, geospatial=True), progress=False)
    outward = np.einsum("ij,ij->i", cloud.normals, ball - [500.0, 300.0, 20.0])
    assert min((outward > 0).mean(), (outward < 0).mean()) == 0.0, report["normals"]
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 100, (20_000, 2))
    ground = np.c_[xy, 5 * np.sin(xy[:, 0] / 15) + 3 * np.cos(xy[:, 1] / 20)]
    terrain, _ = prepare(PointCloud(ground, geospatial=True), progress=False)
    assert (terrain.normals[:, 2] > 0).all()
