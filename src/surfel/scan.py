"""A virtual range scanner: what a structured-light or time-of-flight scanner would measure of a
mesh, for judging a pipeline on raw scans (issue 17) without a physical scan.

Each of V views is a pinhole sensor on a sphere around the model (golden-angle spiral in
azimuth, elevations within +-ELEVATION_LIMIT degrees, looking at the centre, framed as
`camera.frame` frames it) that measures the mesh's depth at R x R pixels through the `mesh`
method (the GL rasterizer's depth and normal buffers). Per sample, at pixel centre (u, v)
with eye depth z:

  ray      d = normalize(((u - cx) / fx, (cy - v) / fy, -1))    (eye space)
  point    p = (r + e) d,  r = z / |d_z|,  e ~ N(0, (noise x S)^2)   (range noise along the ray)
  incidence cos(theta) = |n . d|, n the mesh's eye-space normal
  returns  kept with probability clip((cos(theta) - cos(G)) / (cos(G / 2) - cos(G)), 0, 1):
           all up to half the grazing limit G, fewer and fewer beyond, none past G

where S = 2 x the bounding radius (the model's size). Each view is then misregistered as a
registration step leaves it (Bernardini & Rushmeier 2002, "The 3D model acquisition pipeline",
Computer Graphics Forum 21(2), section 4): a rotation about the model's centre by
2 x misalignment radians about a random axis (points at the bounding radius move about
misalignment x S) and a translation of misalignment x S in a random direction. The view's
sensor position is moved alike, so that it stays the origin of its own rays.

The result has no normals: positions, the integer attribute `scan` (the view of each point)
and `sensors` (V, 3), the registered sensor positions. A mesh with colours is scanned as a
scanner with a colour camera scans it (structured light and RGB-D sensors record texture):
each sample takes the mesh's unlit colour at its pixel, so that its renders compare with the
mesh's without a colour difference all over (a grey CAD part scanned white: 19 dB obliquely,
where its geometry alone is 28).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .camera import frame
from .cloud import PointCloud
from .errors import SurfelError
from .files import check_output
from .io import load, write_ply
from .options import RenderOptions
from .rendering import Renderer
from .request import SCAN, parse_values

ELEVATION_LIMIT = 60.0  # degrees: the views circle the model as a scanner on a tripod would
GOLDEN_ANGLE = 180.0 * (3.0 - math.sqrt(5.0))  # degrees between consecutive views' azimuths


@dataclass(frozen=True)
class ScanSettings:
    """The scanner: views, pixels per side, range noise and misregistration (fractions of the
    model's size), the grazing limit in degrees, and the random seed."""

    views: int = 6
    resolution: int = 256
    noise: float = 0.001
    misalignment: float = 0.0005
    grazing: float = 80.0
    seed: int = 0

    def __post_init__(self):
        checks = [("views", 1 <= self.views <= 64, "must be in 1..64"),
                  ("resolution", 8 <= self.resolution <= 4096, "must be in 8..4096"),
                  ("noise", 0 <= self.noise < 0.1, "must be in [0, 0.1)"),
                  ("misalignment", 0 <= self.misalignment < 0.1, "must be in [0, 0.1)"),
                  ("grazing", 0 < self.grazing <= 90, "must be in (0, 90] degrees"),
                  ("seed", self.seed >= 0, "must not be negative")]
        for name, good, problem in checks:
            if not good:
                raise SurfelError(f"--{name}: {problem}, got {getattr(self, name)!r}")


def view_directions(views: int) -> list[tuple[float, float]]:
    """(azimuth, elevation) in degrees of each view: a golden-angle spiral, evenly in sin(elevation)."""
    top = math.sin(math.radians(ELEVATION_LIMIT))
    return [((k * GOLDEN_ANGLE) % 360.0, math.degrees(math.asin(top * (1 - 2 * (k + 0.5) / views))))
            for k in range(views)]


def random_rotation(rng: np.random.Generator, angle: float) -> np.ndarray:
    """The 3 x 3 rotation by `angle` radians about a uniformly random axis (Rodrigues)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def scan_view(mesh: PointCloud, camera, settings: ScanSettings, rng: np.random.Generator,
              renderer: Renderer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The world positions (M, 3) one view measures, their unlit colours (M, 3) and its sensor
    position (3,), positions and sensor registered."""
    result = renderer.render(mesh, camera, "mesh",
                             options=RenderOptions(supersample=1, background=(0, 0, 0), shading="none"))
    rows, cols = np.nonzero((result.alpha > 0.5) & np.isfinite(result.depth))
    direction = np.stack([(cols + 0.5 - camera.cx) / camera.fx, (camera.cy - (rows + 0.5)) / camera.fy,
                          -np.ones(len(rows))], axis=1)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    incidence = np.abs(np.einsum("ij,ij->i", result.normals[rows, cols].astype(np.float64), direction))
    limit = math.cos(math.radians(settings.grazing))
    kept = rng.random(len(rows)) < np.clip((incidence - limit) / (math.cos(math.radians(settings.grazing / 2))
                                                                   - limit), 0, 1)
    size = 2 * mesh.bounding_radius
    ranges = result.depth[rows, cols][kept] / np.abs(direction[kept, 2])
    ranges = ranges + rng.normal(0.0, settings.noise * size, len(ranges))
    eye_points = direction[kept] * ranges[:, None]
    to_world = np.linalg.inv(camera.world_to_eye)
    world = eye_points @ to_world[:3, :3].T + to_world[:3, 3]
    sensor = camera.eye
    # misregistration: the whole view, sensor included, moved rigidly
    rotation = random_rotation(rng, 2 * settings.misalignment)
    shift = rng.normal(size=3)
    shift *= settings.misalignment * size / np.linalg.norm(shift)
    centre = mesh.center
    colors = result.color[rows, cols][kept]
    return (world - centre) @ rotation.T + centre + shift, colors, (sensor - centre) @ rotation.T + centre + shift


def scan(mesh: PointCloud, settings: ScanSettings = ScanSettings(), renderer: Renderer | None = None) -> PointCloud:
    """A simulated range scan of `mesh` (see the module docstring): positions, `scan`, `sensors`,
    and colours where the mesh has them."""
    if not mesh.is_mesh:
        raise SurfelError(f"{mesh.source}: scan needs a mesh (faces) to measure")
    renderer = renderer or Renderer()
    rng = np.random.default_rng(settings.seed)
    points, colors, sensors, owner = [], [], [], []
    for index, (azimuth, elevation) in enumerate(view_directions(settings.views)):
        camera = frame(mesh.center, mesh.bounding_radius, azimuth=azimuth, elevation=elevation,
                       size=(settings.resolution, settings.resolution))
        measured, seen, sensor = scan_view(mesh, camera, settings, rng, renderer)
        points.append(measured)
        colors.append(seen)
        sensors.append(sensor)
        owner.append(np.full(len(measured), index, np.int16))
    positions = np.concatenate(points)
    if not len(positions):
        raise SurfelError(f"{mesh.source}: the scanner measured no point")
    return PointCloud(positions, colors=None if mesh.colors is None else np.concatenate(colors).astype(np.float32),
                      attributes={"scan": np.concatenate(owner)}, sensors=np.array(sensors), source=mesh.source)


def scan_command(mesh_path: str, output: str, values: dict) -> PointCloud:
    """`surfel scan`: the options checked, the mesh scanned and written to `output` (.ply)."""
    settings = ScanSettings(**parse_values(values, SCAN))
    if not output.lower().endswith(".ply"):
        raise SurfelError(f"{output}: --output writes a PLY: name it .ply")
    check_output(output, "--output")
    cloud = scan(load(mesh_path), settings)
    write_ply(cloud, output)
    return cloud
