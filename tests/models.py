"""The models the tests render, all carried by the repository or made here.

- Spot (Keenan Crane, CC0; tests/data/spot.obj, see its LICENSE): a coarse organic mesh,
  2,930 vertices, read from the file as users' OBJ files are.
- `dense_spot`: Spot refined by two steps of Loop subdivision (trimesh), 46,850 vertices:
  a smooth organic surface sampled as densely as a scan, standing in for the Stanford bunny
  (whose terms are no clear open licence).
- `turned_part`: a CAD part made here, a lathe profile (flange with a chamfer, a shaft with a
  groove, a chamfered head) revolved about its axis: flat, cylindrical and conical faces
  meeting at sharp convex and concave creases of 90 and 135 degrees, 10,754 vertices,
  standing in for fandisk.
- `ball_over_plate`: a sphere in front of a square plate, an occluding contour over a surface.
- `puck`: a disc a fifth as thick as wide, coarsely tessellated (1,538 vertices): its flat
  faces meet its rim at sharp 90 degree creases one or two vertices apart, as a coarse CAD
  part's flanges do; made thinner than its sampling, a plate whose rim has no vertices
  between its two faces' edges.
- `plate_with_a_hole_over_a_plate`: a red plate with a round opening in front of a blue one:
  an open border over a surface farther back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfel.cloud import PointCloud
from surfel.io import load
from surfel.io.mesh import area_weighted_vertex_normals

DATA = Path(__file__).parent / "data"
SPOT = DATA / "spot.obj"

# (radius, height) corners of the turned part's profile, from the axis at the bottom to the tip
PROFILE = [(0.0, 0.0), (1.0, 0.0), (1.0, 0.3), (0.85, 0.45), (0.5, 0.45), (0.5, 1.0), (0.4, 1.0), (0.4, 1.15),
           (0.5, 1.15), (0.5, 1.5), (0.25, 1.75), (0.0, 1.75)]
SECTIONS = 128  # around the axis
TILT = 25.0  # degrees towards the viewer, so that the front view sees the flange's top faces


def spot() -> PointCloud:
    return load(SPOT)


def mesh_cloud(vertices: np.ndarray, faces: np.ndarray, source: str) -> PointCloud:
    return PointCloud(vertices, normals=area_weighted_vertex_normals(vertices, faces), faces=faces, source=source)


def dense_spot() -> PointCloud:
    """Spot refined twice by Loop subdivision, turned 150 degrees about +y (as the bundled
    demo is) so that the front view shows her face in three-quarter view."""
    from trimesh.remesh import subdivide_loop

    coarse = spot()
    vertices, faces = subdivide_loop(coarse.positions, coarse.faces, iterations=2)
    t = np.radians(150.0)
    rotation = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])
    return mesh_cloud(vertices @ rotation.T, faces, "spot, Loop-subdivided twice")


def turned_part() -> PointCloud:
    """The lathe part of the module docstring: the profile resampled every SPACING along
    its segments (corners kept), revolved in SECTIONS steps, tilted TILT degrees about x."""
    from trimesh.creation import revolve

    spacing = 2 * np.pi / SECTIONS  # the step around the rim of the flange (radius 1)
    points = [np.array(PROFILE[0])]
    for a, b in zip(PROFILE[:-1], PROFILE[1:], strict=True):
        a, b = np.array(a), np.array(b)
        steps = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        points += [a + (b - a) * t for t in np.arange(1, steps + 1) / steps]
    mesh = revolve(np.array(points), sections=SECTIONS)
    mesh.merge_vertices()
    vertices = np.asarray(mesh.vertices)[:, [0, 2, 1]] * [1, 1, -1]  # a rotation: the axis along +y
    vertices[:, 1] -= 0.95
    t = np.radians(TILT)
    rotation = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    return mesh_cloud(vertices @ rotation.T, np.asarray(mesh.faces), "turned part")


def puck(thickness: float = 0.2) -> PointCloud:
    """The puck of the module docstring: the profile of a disc of radius 1 and `thickness`
    resampled every 2 pi / 64 along its segments, revolved in 64 steps about +y."""
    from trimesh.creation import revolve

    sections = 64
    spacing = 2 * np.pi / sections
    corners = np.array([(0.0, 0.0), (1.0, 0.0), (1.0, thickness), (0.0, thickness)])
    profile = [corners[0]]
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        steps = int(np.ceil(np.linalg.norm(b - a) / spacing))
        profile += [a + (b - a) * t for t in np.arange(1, steps + 1) / steps]
    mesh = revolve(np.array(profile), sections=sections)
    mesh.merge_vertices()
    vertices = np.asarray(mesh.vertices)[:, [0, 2, 1]] * [1, 1, -1]  # a rotation: the axis along +y
    return mesh_cloud(vertices, np.asarray(mesh.faces), "puck")


def plate_with_a_hole_over_a_plate() -> PointCloud:
    """Two 2 x 2 plates facing +z, grids of 41 x 41 vertices: a red one at z = 0 without the
    triangles within 0.4 of its centre, and a blue one 0.3 behind it."""
    grid, faces = plate(41, 1.0)
    open_faces = faces[np.linalg.norm(grid[faces].mean(axis=1)[:, :2], axis=1) > 0.4]
    front = np.unique(open_faces)
    renumber = np.full(len(grid), -1)
    renumber[front] = np.arange(len(front))
    vertices = np.concatenate([grid[front], grid + [0.0, 0.0, -0.3]])
    all_faces = np.concatenate([renumber[open_faces], faces + len(front)]).astype(np.int32)
    colors = np.concatenate([np.tile([1.0, 0.0, 0.0], (len(front), 1)), np.tile([0.0, 0.0, 1.0], (len(grid), 1))])
    return mesh_cloud(vertices, all_faces, "plate with a hole over a plate").with_(colors=colors.astype(np.float32))


def unit_sphere() -> PointCloud:
    """The unit sphere about the origin, an icosphere of 10,242 vertices (trimesh): facets
    within 5e-5 of the sphere, far below the range noise the scanner tests add."""
    from trimesh.creation import icosphere

    sphere = icosphere(subdivisions=5)
    return mesh_cloud(np.asarray(sphere.vertices, np.float64), np.asarray(sphere.faces, np.int32), "unit sphere")


def ball_over_plate() -> PointCloud:
    """A sphere of radius 0.5 (an icosphere of 2,562 vertices) 0.6 in front of a 2.4 x 2.4
    plate (a grid of 81 x 81 vertices) facing +z: seen from the front, the sphere's outline
    is an occluding contour over the plate."""
    from trimesh.creation import icosphere

    ball = icosphere(subdivisions=4)
    ball_vertices = np.asarray(ball.vertices) * 0.5 + [0.1, 0.05, 0.6]
    grid, plate_faces = plate(81, 1.2)
    faces = np.concatenate([np.asarray(ball.faces), plate_faces + len(ball_vertices)]).astype(np.int32)
    return mesh_cloud(np.concatenate([ball_vertices, grid]), faces, "ball over a plate")


def plate(n: int, half: float) -> tuple[np.ndarray, np.ndarray]:
    """A square plate at z = 0 facing +z from -half to half, a grid of n x n vertices in two
    triangles a cell: (vertices (n², 3), faces (2 (n - 1)², 3))."""
    x, y = np.meshgrid(np.linspace(-half, half, n), np.linspace(-half, half, n))
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    corner = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([corner, corner + 1, corner + n + 1], axis=1),
                            np.stack([corner, corner + n + 1, corner + n], axis=1)])
    return grid, faces
