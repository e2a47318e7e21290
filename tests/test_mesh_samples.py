"""`surfel sample` (preprocess/mesh_samples.py): points spread evenly over a mesh's faces, with
crease-angle normals and the vertices' colours, for meshes whose vertices do not sample their
surface: a CAD part's STL, whose flat faces have vertices only on their outlines."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from conftest import assert_refused, invoke, requires_gl
from models import DATA, SPOT, mesh_cloud
from surfel.cloud import PointCloud
from surfel.io import load
from surfel.preprocess.mesh_samples import SampleSettings, corner_normals, open_face_share, sample_surface

POCKETS = DATA / "octagonal_pocket.stl"  # trimesh's models: a CAD plate with octagonal pockets


def cube() -> PointCloud:
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))])
    return mesh_cloud(corners, faces, "cube")


def test_samples_are_as_many_as_asked_and_evenly_spaced():
    """Dart throwing keeps about the points asked for, no two much closer than the rest: the
    nearest neighbour of every point lies at least 0.8 times the median's distance away (of as
    many independent samples over the same faces, the closest pair lies at 0.013 times it)."""
    mesh = load(SPOT)
    cloud = sample_surface(mesh, SampleSettings(points=20_000))
    assert 0.95 * 20_000 <= len(cloud) <= 20_000
    nearest = cKDTree(cloud.positions).query(cloud.positions, 2)[0][:, 1]
    assert nearest.min() >= 0.8 * np.median(nearest)
    on_mesh = cKDTree(mesh.positions).query(cloud.positions)[0]
    assert on_mesh.max() < 0.05 * mesh.bounding_radius


def test_creases_stay_sharp_and_tessellated_curves_smooth():
    """A cube's faces meet at 90 degrees: with the default crease angle every sample keeps its
    face's axis normal, blended (180 degrees) those near its edges tilt. An icosphere of 80 faces
    (neighbours 18 to 22 degrees apart) shades as the sphere, not as its facets."""
    samples = sample_surface(cube(), SampleSettings(points=3000))
    assert np.abs(samples.normals).max(axis=1).min() > 0.9999
    blended = sample_surface(cube(), SampleSettings(points=3000, crease_angle=180))
    assert np.mean(np.abs(blended.normals).max(axis=1) < 0.99) > 0.1

    from trimesh.creation import icosphere

    ball = icosphere(subdivisions=1)
    sphere = mesh_cloud(np.asarray(ball.vertices, np.float64), np.asarray(ball.faces, np.int64), "icosphere")

    def error(angle):
        cloud = sample_surface(sphere, SampleSettings(points=5000, crease_angle=angle))
        radial = cloud.positions / np.linalg.norm(cloud.positions, axis=1, keepdims=True)
        return np.degrees(np.arccos(np.clip(np.sum(radial * cloud.normals, axis=1), -1, 1))).mean()

    assert error(30.0) < 0.1 * error(0.0)


def test_corner_normals_blend_only_within_the_crease():
    """At 30 degrees each cube corner keeps its own face's normal; at 100 the three faces
    around each corner blend."""
    mesh = cube()
    triangles = mesh.positions[mesh.faces]
    own = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    own /= np.linalg.norm(own, axis=1, keepdims=True)
    assert np.allclose(corner_normals(mesh.positions, mesh.faces, 30.0), own[:, None, :])
    blended = corner_normals(mesh.positions, mesh.faces, 100.0)
    assert np.abs(blended).min() > 0.2
    assert np.allclose(np.linalg.norm(blended, axis=2), 1.0)


def test_colours_follow_the_vertices():
    """A triangle with red, green and blue corners: each sample's colour is its barycentric mix."""
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    triangle = PointCloud(corners, colors=np.eye(3, dtype=np.float32), faces=np.array([[0, 1, 2]]))
    cloud = sample_surface(triangle, SampleSettings(points=500))
    x, y = cloud.positions[:, 0], cloud.positions[:, 1]
    assert np.allclose(cloud.colors, np.stack([1 - x - y, x, y], axis=1), atol=1e-5)
    assert np.allclose(np.abs(cloud.normals[:, 2]), 1.0)


def test_attributes_blend_by_their_kind():
    """Intensity (continuous) is the samples' barycentric mix, rounded to its integer type; a
    class (categorical) is the nearest corner's, never a blend."""
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    triangle = PointCloud(corners, faces=np.array([[0, 1, 2]]),
                          attributes={"intensity": np.array([0, 1000, 2000], np.uint16),
                                      "classification": np.array([2, 5, 9], np.uint8)})
    cloud = sample_surface(triangle, SampleSettings(points=500))
    x, y = cloud.positions[:, 0], cloud.positions[:, 1]
    intensity = cloud.attributes["intensity"]
    assert intensity.dtype == np.uint16 and np.abs(intensity - (1000 * x + 2000 * y)).max() <= 0.5 + 1e-6
    nearest = np.argmax(np.stack([1 - x - y, x, y], axis=1), axis=1)
    assert np.array_equal(cloud.attributes["classification"], np.array([2, 5, 9], np.uint8)[nearest])
    assert cloud.schema["classification"].kind == "categorical"


@requires_gl
def test_a_cad_part_renders_closed_from_its_samples():
    """The plate's flat faces have vertices only on their outlines: its vertices leave most of it
    open, its samples none of it, and match the mesh shaded with the same crease normals."""
    from surfel.camera import frame
    from surfel.metrics import compare_results
    from surfel.options import RenderOptions
    from surfel.rendering import Renderer

    mesh = load(str(POCKETS))
    normals = corner_normals(mesh.positions, mesh.faces, 30.0)
    creased = PointCloud(mesh.positions[mesh.faces].reshape(-1, 3), normals=normals.reshape(-1, 3),
                         faces=np.arange(3 * len(mesh.faces)).reshape(-1, 3))
    camera = frame(mesh.center, mesh.bounding_radius, azimuth=60.0, elevation=20.0, size=(256, 256))
    options = RenderOptions(shading="lambert", background=(0.0, 0.0, 0.0))
    with Renderer() as renderer:
        reference = renderer.render(creased, camera, "mesh", options=options)
        vertices = compare_results(reference, renderer.render(mesh.take(np.arange(len(mesh))), camera, "deferred",
                                                              options=options))
        sampled = compare_results(reference, renderer.render(sample_surface(mesh, SampleSettings(points=60_000)),
                                                             camera, "deferred", options=options))
    assert vertices["holes"] > 0.1
    assert sampled["holes"] < 0.001 and sampled["psnr"] > 30.0


def fan_capped_disc(sides: int = 64, thickness: float = 0.3) -> PointCloud:
    """A disc of radius 1 as CAD exporters tessellate one: its rims' vertices only, each cap a
    fan of long triangles from one rim vertex across to the others; no face is large against
    the median edge (the longest, 2, is under 8 times the wall's height, 0.3)."""
    angles = 2 * np.pi * np.arange(sides) / sides
    rim = np.c_[np.cos(angles), np.sin(angles)]
    vertices = np.concatenate([np.c_[rim, np.zeros(sides)], np.c_[rim, np.full(sides, thickness)]])
    k = np.arange(1, sides - 1)
    bottom = np.c_[np.zeros_like(k), k + 1, k]
    top = np.c_[np.full_like(k, sides), sides + k, sides + k + 1]
    j = np.arange(sides)
    following = (j + 1) % sides
    wall = np.concatenate([np.c_[j, following, sides + following], np.c_[j, sides + following, sides + j]])
    return mesh_cloud(vertices, np.concatenate([bottom, top, wall]), "fan-capped disc")


def test_open_faces_are_those_no_vertex_splat_reaches():
    """A face is open where it is far larger than the mesh's median edge (the plate's pockets),
    or where its point farthest from its corners lies past every corner's bound on its splat
    (the disc's caps, whose fans are long but not against its median edge)."""
    disc = fan_capped_disc()
    cap, wall = 32 * np.sin(2 * np.pi / 64), 64 * 2 * np.sin(np.pi / 64) * 0.3
    caps = 2 * cap / (2 * cap + wall)  # 0.769 of its area; the fans' first slivers are reached
    assert 0.95 * caps < open_face_share(disc) <= caps + 1e-9
    assert open_face_share(load(POCKETS)) == pytest.approx(0.772, abs=0.001)
    assert open_face_share(load(SPOT)) == 0.0


def test_rendering_a_cad_export_points_to_sample(tmp_path):
    """`surfel render` of a mesh whose open faces hold much of its area says so, once, naming
    the file and `surfel sample`; an organic mesh's render does not."""
    result = invoke("render", POCKETS, "-o", tmp_path / "part.png", "--size", "64x64")
    assert result.exit_code == 0, result.output
    notice = [line for line in result.output.splitlines() if "surfel sample" in line]
    assert len(notice) == 1 and notice[0].startswith(f"{POCKETS}: 77% of its area")
    result = invoke("render", SPOT, "-o", tmp_path / "spot.png", "--size", "64x64")
    assert result.exit_code == 0 and "surfel sample" not in result.output


def test_info_gives_the_share_of_open_faces():
    import json

    part = json.loads(invoke("info", POCKETS, "--json").output)
    organic = json.loads(invoke("info", SPOT, "--json").output)
    assert part["open_faces"] == pytest.approx(0.772, abs=0.001) and organic["open_faces"] == 0.0


def test_cli_writes_the_samples(tmp_path):
    out = tmp_path / "part.ply"
    result = invoke("sample", POCKETS, "-o", out, "--points", "5000", "--crease-angle", "45")
    assert result.exit_code == 0, result.output
    cloud = load(str(out))
    direct = sample_surface(load(str(POCKETS)), SampleSettings(points=5000, crease_angle=45.0))
    assert np.array_equal(cloud.positions, direct.positions.astype(cloud.positions.dtype))
    assert np.allclose(cloud.normals, direct.normals, atol=1e-6)


@pytest.mark.parametrize("args, message", [
    (["--points", "0"], "--points: must be in 1.."),
    (["--points", "many"], "--points: needs an integer"),
    (["--crease-angle", "181"], "--crease-angle: must be in [0, 180]"),
])
def test_cli_refuses_bad_options(tmp_path, args, message):
    out = tmp_path / "part.ply"
    assert_refused(invoke("sample", POCKETS, "-o", out, *args), message)
    assert not out.exists()


def test_cli_refuses_a_point_cloud_and_a_wrong_output(tmp_path):
    points = tmp_path / "points.ply"
    assert invoke("sample", POCKETS, "-o", points, "--points", "100").exit_code == 0
    assert_refused(invoke("sample", points, "-o", tmp_path / "b.ply"), str(points), "needs a mesh")
    assert_refused(invoke("sample", POCKETS, "-o", tmp_path / "b.png"), "--output must be named .ply")
    assert_refused(invoke("sample", POCKETS, "-o", tmp_path), "--output")
