"""Preprocessing: normals (PCA + orientation), covering radii, frames, ellipses, normal fields."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from surfel.cloud import PointCloud
from surfel.preprocess import estimate_normals, estimate_radii, fit_ellipses, fit_normal_field, prepare, tangent_frames


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sphere(n: int, seed: int = 0, noise: float = 0.0) -> np.ndarray:
    """Unit-sphere samples (also their exact outward normals when noise = 0)."""
    rng = np.random.default_rng(seed)
    p = unit(rng.normal(size=(n, 3)))
    return p + rng.normal(0, noise, p.shape) if noise else p


def angles(a: np.ndarray, b: np.ndarray, oriented: bool = True) -> np.ndarray:
    """Angle in degrees between unit row vectors (ignoring sign unless oriented)."""
    dot = np.einsum("ij,ij->i", unit(a), unit(b))
    return np.degrees(np.arccos(np.clip(dot if oriented else np.abs(dot), -1, 1)))


# --- a dense organic mesh: its vertices as the cloud, its faces as the true surface -------------


@pytest.fixture(scope="module")
def dense():
    """Spot refined to 46,850 vertices (tests/models.py); normals and surface samples here."""
    from models import dense_spot

    mesh = dense_spot()
    vertices, faces = mesh.positions, mesh.faces
    used = np.unique(faces)
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    normals = np.zeros_like(vertices)
    for corner in range(3):  # area-weighted vertex normals: |cross| is twice the area
        np.add.at(normals, faces[:, corner], cross)
    rng = np.random.default_rng(1)
    area = np.linalg.norm(cross, axis=1)
    tri = rng.choice(len(faces), 200_000, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(len(tri))), rng.random(len(tri))
    w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    surface = np.einsum("nc,ncj->nj", w, vertices[faces[tri]])
    return vertices[used], unit(normals[used]), surface


def coverage(surface: np.ndarray, centres: np.ndarray, normals: np.ndarray, axes: np.ndarray) -> float:
    """Fraction of surface samples inside some splat: within half its largest semi-axis of its
    plane, and inside its ellipse in the plane (u^2 + v^2 <= 1). Candidates: the 24 nearest
    splat centres (a miss among them only lowers the measured coverage)."""
    axes = axes.astype(np.float64)
    length2 = np.einsum("ntj,ntj->nt", axes, axes)
    _, cand = cKDTree(centres).query(surface, 24)
    d = surface[:, None] - centres[cand]
    u = np.einsum("skj,skj->sk", d, axes[cand, 0]) / length2[cand, 0]
    v = np.einsum("skj,skj->sk", d, axes[cand, 1]) / length2[cand, 1]
    height = np.abs(np.einsum("skj,skj->sk", d, normals[cand].astype(np.float64)))
    inside = (u * u + v * v <= 1) & (height <= 0.5 * np.sqrt(length2[cand].max(axis=2)))
    return float(inside.any(axis=1).mean())


def nn_spacing(points: np.ndarray) -> float:
    return float(cKDTree(points).query(points, 2)[0][:, 1].mean())


# --- normals ---------------------------------------------------------------------------------------


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


def test_orientation_matches_mesh(dense):
    vertices, mesh_normals, _ = dense
    normals, ambiguous = estimate_normals(vertices)
    agree = np.einsum("ij,ij->i", normals, mesh_normals) > 0
    assert agree.mean() >= 0.99
    assert ambiguous < 0.01 * len(vertices)


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


# --- radii and ellipses: hole-free coverage of the true surface ---------------------------------


@pytest.mark.parametrize("step", [1, 4])
def test_radii_and_ellipses_cover_a_dense_mesh(dense, step):
    vertices, _, surface = dense
    points = vertices[::step]
    normals, _ = estimate_normals(points)
    radii = estimate_radii(points, normals=normals)
    assert radii.dtype == np.float32 and (radii > 0).all()
    assert coverage(surface, points, normals, tangent_frames(normals, radii)) >= 0.999
    ellipses = fit_ellipses(points, normals)
    assert coverage(surface, points, normals, ellipses) >= 0.999
    # not needlessly large: about the nearest-neighbour spacing, ellipses smaller than the disks
    assert radii.mean() < 2.0 * nn_spacing(points)
    area = np.prod(np.linalg.norm(ellipses, axis=2), axis=1)
    assert area.mean() <= (radii.astype(np.float64) ** 2).mean()


def scan_lines(rng, angle: float, line: float, along: float, half: float = 25.0) -> np.ndarray:
    """An aerial-LiDAR-like strip: noisy scan lines `line` apart, `along` spacing on a line."""
    rows = []
    y = -half
    while y < half:
        x = np.arange(-half, half, along) + rng.uniform(-0.35, 0.35) * along
        x = x + rng.normal(0, 0.15 * along, len(x))
        rows.append(np.c_[x, y + rng.normal(0, 0.08 * line, len(x)) + 0.003 * rng.normal() * x])
        y += line * rng.uniform(0.7, 1.3)
    c, s = np.cos(angle), np.sin(angle)
    return np.concatenate(rows) @ np.array([[c, s], [-s, c]])


def test_radii_and_ellipses_cover_lidar_scan_lines():
    rng = np.random.default_rng(6)
    strip = scan_lines(rng, 0.0, line=1.0, along=0.3)
    overlap = scan_lines(rng, 0.5, line=1.3, along=0.25)  # a second flight line over half the tile
    xy = np.concatenate([strip, overlap[overlap[:, 0] > 0]])

    def height(xy):
        return 0.5 * np.sin(xy[:, 0] / 7)

    points = np.c_[xy, height(xy) + rng.normal(0, 0.02, len(xy))]
    normals, _ = estimate_normals(points)
    radii = estimate_radii(points, normals=normals)
    sample = rng.uniform(-22, 22, (200_000, 2))
    surface = np.c_[sample, height(sample)]
    assert coverage(surface, points, normals, tangent_frames(normals, radii)) >= 0.999
    assert coverage(surface, points, normals, fit_ellipses(points, normals)) >= 0.999


def test_isolated_point_gets_no_blob():
    rng = np.random.default_rng(7)
    points = np.c_[rng.uniform(-1, 1, (5_000, 2)), np.zeros(5_000)]
    points = np.concatenate([points, [[0.0, 0.0, 0.5]]])  # a stray return above the surface
    radii = estimate_radii(points)
    assert radii[-1] <= 3 * np.median(radii)  # its cell alone would be 0.5 across, 15 x the median


def test_tangent_frames_orthonormal():
    rng = np.random.default_rng(8)
    poles = [[0, 0, 1], [0, 0, -1], [1e-9, 0, -1], [1, 0, 0], [1, 0, -0.0]]  # where naive frames break
    normals = unit(np.concatenate([rng.normal(size=(1_000, 3)), poles]))
    radii = rng.uniform(0.5, 2, len(normals))
    axes = tangent_frames(normals, radii)
    assert axes.shape == (len(normals), 2, 3) and axes.dtype == np.float32
    u, v = axes[:, 0] / radii[:, None], axes[:, 1] / radii[:, None]
    assert np.allclose(np.linalg.norm(u, axis=1), 1, atol=1e-5) and np.allclose(np.linalg.norm(v, axis=1), 1, atol=1e-5)
    assert np.abs(np.einsum("ij,ij->i", u, v)).max() < 1e-5
    assert np.abs(np.einsum("ij,ij->i", u, normals)).max() < 1e-5
    assert np.allclose(np.cross(u, v), normals, atol=1e-5)  # right-handed (u, v, n)


def test_ellipse_axes_are_tangent_and_right_handed():
    p = sphere(5_000)
    axes = fit_ellipses(p, p).astype(np.float64)
    lengths = np.linalg.norm(axes, axis=2)
    assert (lengths[:, 0] >= lengths[:, 1] - 1e-7).all()  # u is the major axis
    assert np.abs(np.einsum("ntj,nj->nt", axes, p)).max() < 1e-5 * lengths.max()
    assert (np.einsum("ij,ij->i", np.cross(axes[:, 0], axes[:, 1]), p) > 0).all()


def test_ellipses_follow_the_principal_curvature_directions():
    """On a cylinder sampled at random the neighbours spread evenly, so only the normals tell
    the principal directions: around (curvature 1) and along the axis (curvature 0)."""
    rng = np.random.default_rng(12)
    phi, height = rng.uniform(0, 2 * np.pi, 20_000), rng.uniform(-3, 3, 20_000)
    normals = np.c_[np.cos(phi), np.sin(phi), np.zeros_like(phi)]
    points = normals + np.c_[np.zeros((len(phi), 2)), height]
    axes = fit_ellipses(points, normals)
    lengths = np.linalg.norm(axes.astype(np.float64), axis=2)
    axial = np.abs(axes[:, 0, 2]) / lengths[:, 0]  # |cos| of u's angle to the cylinder's axis
    assert ((axial > 0.97) | (axial < 0.25)).mean() > 0.99
    alpha, beta = fit_normal_field(points, normals, axes)
    around, along = np.where(axial > 0.97, beta, alpha), np.where(axial > 0.97, alpha, beta)
    around_length = np.where(axial > 0.97, lengths[:, 1], lengths[:, 0])
    # eq. 8 then holds exactly: the tilt at the rim is semi-axis / radius around, 0 along
    assert np.median(np.abs(around / around_length - 1)) < 0.01
    assert np.median(np.abs(along) / around_length) < 0.001


# --- Phong splatting's normal field -------------------------------------------------------------


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


# --- prepare ---------------------------------------------------------------------------------------


def test_prepare_fills_exactly_what_is_missing():
    p = sphere(3_000)
    bare, report = prepare(PointCloud(p))
    assert bare.normals is not None and bare.radii is not None and bare.axes is not None
    assert report["ambiguous_normals"] == 0 and "normals" in report and "radii" in report and "axes" in report
    assert np.allclose(np.cross(bare.axes[:, 0], bare.axes[:, 1]), bare.normals * bare.radii[:, None] ** 2, atol=1e-6)

    given = PointCloud(p, normals=-p)  # inward on purpose: kept as given
    filled, report = prepare(given)
    assert np.array_equal(filled.normals, given.normals)
    assert "normals" not in report and "ambiguous_normals" not in report and "radii" in report

    complete = filled
    same, report = prepare(complete)
    assert same is complete and report == {}

    ellipses, report = prepare(PointCloud(p, normals=p, radii=np.full(len(p), 0.05)), elliptical=True,
                               normal_field=True)
    assert np.array_equal(ellipses.radii, np.full(len(p), 0.05, np.float32))
    assert report["axes"].startswith("fitted ellipses") and "normal_field" in report and "radii" not in report
    assert ellipses.attributes["phong_alpha"].shape == (len(p),) and (ellipses.attributes["phong_alpha"] > 0).all()

    axes_only, report = prepare(PointCloud(p, axes=bare.axes))
    assert np.allclose(axes_only.normals, bare.normals, atol=1e-5) and np.array_equal(axes_only.axes, bare.axes)


def test_prepare_geospatial_faces_up():
    rng = np.random.default_rng(11)
    xy = rng.uniform(0, 100, (5_000, 2))
    cloud = PointCloud(np.c_[xy, 0.1 * xy[:, 0] + 400] + [636_000, 849_000, 0], geospatial=True)
    prepared, report = prepare(cloud, progress=True)
    assert (prepared.normals[:, 2] > 0).all() and "up" in report["normals"]


def test_tiny_clouds():
    for n in (1, 2, 3):
        cloud, report = prepare(PointCloud(np.arange(3 * n, dtype=float).reshape(n, 3) ** 1.5))
        assert (cloud.radii > 0).all() and report["ambiguous_normals"] == n


def test_normals_passed_as_k_are_refused():
    p = sphere(100)
    with pytest.raises(TypeError, match="k must be a positive integer"):
        estimate_radii(p, p)  # normals= is a keyword: the second argument is k


# --- sharp features ------------------------------------------------------------------------------


def edge_wedge(h: float = 0.05):
    """Two faces meeting at a 90 degree convex edge along y (the solid is x <= 0, z <= 0): face A
    (z = 0, x <= 0, normal +z) and face B (x = 0, z <= 0, normal +x), sampled on a jittered grid
    of spacing h; the edge points carry the averaged normal, as a mesh's vertices do."""
    rng = np.random.default_rng(3)
    s = np.arange(0, 1 + 1e-9, h)
    a, y = np.meshgrid(-s, s, indexing="ij")

    def jitter(shape):
        return rng.uniform(-0.2 * h, 0.2 * h, shape)

    face_a = np.stack([a[1:].ravel() + jitter(a[1:].size), y[1:].ravel() + jitter(a[1:].size), np.zeros(a[1:].size)], 1)
    face_b = np.stack([np.zeros(a[1:].size), y[1:].ravel() + jitter(a[1:].size), a[1:].ravel() + jitter(a[1:].size)], 1)
    edge = np.stack([np.zeros(len(s)), s, np.zeros(len(s))], 1)
    normals = np.concatenate([np.tile([0.0, 0, 1], (len(face_a), 1)), np.tile([1.0, 0, 0], (len(face_b), 1)),
                              np.tile(unit(np.array([1.0, 0, 1])), (len(edge), 1))])
    labels = np.repeat([0, 1, 2], [len(face_a), len(face_b), len(edge)])
    return PointCloud(np.concatenate([face_a, face_b, edge]), normals=normals), labels


def covered_by(cloud: PointCloud, members: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Whether each sample point (lying in the members' common plane) is inside one of their
    clipped splats: within the ellipse and on the kept side of both clip lines."""
    c, axes = cloud.positions[members], cloud.axes[members].astype(np.float64)
    lines = cloud.attributes["clip_lines"][members]
    d = samples[:, None, :] - c[None]
    u = np.einsum("skj,kj->sk", d, axes[:, 0]) / np.einsum("kj,kj->k", axes[:, 0], axes[:, 0])
    v = np.einsum("skj,kj->sk", d, axes[:, 1]) / np.einsum("kj,kj->k", axes[:, 1], axes[:, 1])
    inside = u * u + v * v <= 1
    for line in range(lines.shape[1]):
        inside &= lines[None, :, line, 0] * u + lines[None, :, line, 1] * v <= lines[None, :, line, 2]
    return inside.any(axis=1)


def test_sharp_edge_splats_end_at_the_edge():
    """Splats at a crease are cut at the other face's plane and still cover their own face up
    to the edge; the edge's own points (normals averaged over both faces) are dropped."""
    h = 0.05
    cloud, labels = edge_wedge(h)
    prepared, report = prepare(cloud)
    lines = prepared.attributes["clip_lines"]
    assert "sharp_features" in report
    dropped = lines[:, 0, 2] < -1
    assert dropped[labels == 2].mean() > 0.8 and not dropped[labels < 2].any()
    rng = np.random.default_rng(4)
    # face A: nothing sticks out past x = 0, and the strip next to the edge is covered
    face_a = np.flatnonzero(labels == 0)
    beyond = np.stack([rng.uniform(0.002, 2 * h, 4000), rng.uniform(0.1, 0.9, 4000), np.zeros(4000)], 1)
    assert not covered_by(prepared, face_a, beyond).any()
    strip = np.stack([rng.uniform(-2 * h, 0, 4000), rng.uniform(0.1, 0.9, 4000), np.zeros(4000)], 1)
    assert covered_by(prepared, face_a, strip).all()
    # without sharp features the edge's splats are whole disks, and they stick out of the solid
    plain, _ = prepare(cloud, sharp_features=False)
    assert "clip_lines" not in plain.attributes
    edge = np.flatnonzero(labels == 2)
    uv = rng.uniform(-0.7, 0.7, (500, 2))
    disk = (plain.positions[edge][:, None] + uv[None, :, :1] * plain.axes[edge][:, None, 0]
            + uv[None, :, 1:] * plain.axes[edge][:, None, 1])
    assert ((disk[..., 0] > 0.01 * h) | (disk[..., 2] > 0.01 * h)).mean() > 0.5


def test_smooth_surfaces_get_no_clip_lines():
    """A coarsely sampled sphere has neighbours with very different normals, but no faces:
    its splats stay whole disks."""
    p = sphere(300, seed=5)
    prepared, report = prepare(PointCloud(p, normals=p))
    lines = prepared.attributes.get("clip_lines")
    assert lines is None or (lines[:, :, 2] >= 1).all()
