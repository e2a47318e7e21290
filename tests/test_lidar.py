"""LiDAR and raw scans: splats bounded by the sampling on real tiles, surfaces hole-free, points on
no surface drawn as round splats facing the camera in every method, degenerate clouds, E57 scans
merged by their poses, the sensor position, and COPC estimates reused from view to view."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import models
from conftest import requires_gl
from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.errors import InputError, SurfelError
from surfel.io import load
from surfel.lod import build_lod
from surfel.lod.copc import CopcSource
from surfel.metrics import top_view_footprint
from surfel.preprocess import prepare, tangent_frames
from surfel.preprocess.spacing import BOUND_FACTOR
from surfel.rendering import Renderer, render
from surfel.request import open_input, parse_render
from surfel.scan import ScanSettings, scan

DATA = Path(__file__).parent / "data"
SPLAT_METHODS = ("points", "gaussian", "deferred", "phong", "object-space", "ewa")


def top_camera(cloud: PointCloud, pixels: int = 512):
    """An orthographic top view whose image is the tile's horizontal extent."""
    lo, hi = cloud.bounds
    width, height = hi[:2] - lo[:2]
    size = (pixels, max(1, round(pixels * height / width))) if width >= height else \
        (max(1, round(pixels * width / height)), pixels)
    return frame(cloud.center, cloud.bounding_radius, view="top", geospatial=True, size=size,
                 ortho_height=float(height) * 1.02)


# --- the sampling bound on real tiles ----------------------------------------------------------

@requires_gl
@pytest.mark.parametrize("name", ["simple.las", "vegetation_1_3.las"])
def test_top_view_of_real_tiles_stays_near_the_returns_and_covers_them(name):
    cloud = load(DATA / name)
    camera = top_camera(cloud)
    result = render(cloud, camera)  # the defaults
    far, uncovered = top_view_footprint(result, camera, cloud.positions)
    assert far <= 0.02 and uncovered <= 0.01, (far, uncovered)
    bound = result.stats["estimated"]["splat_bound"]
    horizontal, _ = cKDTree(cloud.positions[:, :2]).query(cloud.positions[:, :2], k=2)
    assert bound["reference_spacing"] == pytest.approx(np.median(horizontal[:, 1]), rel=0.1)
    assert bound["factor"] == BOUND_FACTOR and bound["capped"] > 0


@requires_gl
def test_a_regular_surface_stays_hole_free():
    cloud = load(DATA / "plane.laz")  # a flat real surface, quantised to 1 cm: many coincident returns
    camera = top_camera(cloud)
    _, uncovered = top_view_footprint(render(cloud, camera), camera, cloud.positions, distinct=True)
    assert uncovered <= 0.01
    # seen obliquely: every pixel between projected returns is covered
    oblique = frame(cloud.center, cloud.bounding_radius, geospatial=True, size=(512, 512), azimuth=30, elevation=35)
    result = render(cloud, oblique)
    inside = _inside_hull(oblique.project(cloud.positions)[0], result.alpha.shape)
    assert (result.alpha[inside] > 0.5).mean() >= 0.99


def _inside_hull(points: np.ndarray, shape: tuple[int, int], shrink: float = 4.0) -> np.ndarray:
    """(H, W) bool: pixel centres inside the convex hull of `points`, `shrink` pixels from its edge."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    j, i = np.meshgrid(np.arange(shape[1]) + 0.5, np.arange(shape[0]) + 0.5)
    centres = np.stack([j.ravel(), i.ravel()], 1)
    # hull.equations: n . x + d <= 0 inside, n unit
    margin = centres @ hull.equations[:, :2].T + hull.equations[:, 2]
    return (margin <= -shrink).all(axis=1).reshape(shape)


def test_sparse_returns_stay_dots_and_dense_ground_covers():
    """Ground sampled every metre around a lake with a return every 8 m: the lake's splats
    stay within the bound of the tile's spacing, the ground's cover it."""
    rng = np.random.default_rng(3)
    ground = np.stack(np.meshgrid(np.arange(0, 60.0), np.arange(0, 60.0)), -1).reshape(-1, 2)
    lake = np.hypot(*(ground - 30).T) < 15
    water = np.stack(np.meshgrid(np.arange(18, 43.0, 8), np.arange(18, 43.0, 8)), -1).reshape(-1, 2)
    xy = np.concatenate([ground[~lake], water]) + rng.normal(0, 0.05, (int((~lake).sum()) + len(water), 2))
    cloud = PointCloud(np.c_[xy, rng.normal(0, 0.02, len(xy))] + [500_000, 4_000_000, 100], geospatial=True)
    prepared, report = prepare(cloud)
    assert report["splat_bound"]["reference_spacing"] == pytest.approx(1.0, rel=0.1)
    is_water = np.hypot(*(xy - 30).T) < 14
    assert prepared.radii[is_water].max() <= BOUND_FACTOR * 1.1
    assert np.linalg.norm(prepared.axes[is_water], axis=2).max() <= BOUND_FACTOR * 1.1
    assert report["splat_bound"]["capped"] >= is_water.sum()
    dry = ~is_water
    assert (prepared.radii[dry] >= 0.7).mean() > 0.95  # about the spacing: the ground closes


def test_sparse_returns_stay_dots_on_terrain_sampled_at_random():
    """The same lake in ground sampled at random, where the nearest-neighbour spacing is 0.57 of
    the local spacing and the surfaces' floor applies: the water's splats still reach less than
    the 4 spacings that count as far from every return (issue 14)."""
    rng = np.random.default_rng(3)
    ground = rng.uniform(0, 60, (3600, 2))
    water = np.stack(np.meshgrid(np.arange(18, 43.0, 8), np.arange(18, 43.0, 8)), -1).reshape(-1, 2)
    xy = np.concatenate([ground[np.hypot(*(ground - 30).T) >= 15], water])
    cloud = PointCloud(np.c_[xy, rng.normal(0, 0.02, len(xy))] + [500_000, 4_000_000, 100], geospatial=True)
    prepared, report = prepare(cloud, progress=False)
    bound = report["splat_bound"]
    assert bound["surface_reference_spacing"] > bound["reference_spacing"]
    is_water = np.hypot(*(xy - 30).T) < 14
    reach = np.linalg.norm(prepared.axes[is_water], axis=2).max()
    assert reach < 3.5 * bound["reference_spacing"], reach / bound["reference_spacing"]


def test_an_object_stored_as_las_keeps_its_surface_closed():
    """A ball sampled at random, stored as a geospatial cloud (a terrestrial scan in a LAS file):
    seen from above its two halves overlap and its sides pile up, so the horizontal spacing
    understates its surface's. The bound must not cut its splats until the far side shows
    through: seen from the front, every pixel of the disk shows the near half."""
    rng = np.random.default_rng(5)
    unit = rng.normal(size=(20_000, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    centre = np.array([500.0, 300.0, 20.0])
    cloud = PointCloud(unit * 10.0 + centre, geospatial=True)
    prepared, report = prepare(cloud, progress=False)
    bound = report["splat_bound"]
    assert bound["reference_spacing"] < 0.4 * bound["surface_reference_spacing"]
    assert bound["capped"] < 0.3 * len(cloud), bound
    camera = frame(centre, 10.0, view="front", size=(256, 256), ortho_height=24.0)
    result = render(prepared, camera, "deferred", backend="cpu", shading="lambert")
    pixels, _ = camera.project(prepared.positions)
    disk = _inside_hull(pixels, (256, 256), shrink=6.0)
    _, (centre_depth,) = camera.project(centre[None])
    assert (result.alpha[disk] < 0.99).mean() < 1e-3
    assert (result.depth[disk] > centre_depth).mean() < 2e-3  # the far half shows through nowhere


def test_the_spacing_of_a_scan_grows_with_the_range_from_its_sensor():
    """A wall scanned from a sensor at a constant angular step: the reference spacing is that step
    times the range, so the far part of the wall keeps splats as large as its sampling needs."""
    step = math.radians(0.2)
    azimuth, elevation = np.meshgrid(np.arange(-1.0, 1.0, step), np.arange(-0.3, 0.3, step))
    direction = np.stack([np.cos(elevation) * np.sin(azimuth), np.cos(elevation) * np.cos(azimuth),
                          np.sin(elevation)], -1).reshape(-1, 3)
    sensor = np.array([10.0, -20.0, 1.5])
    points = sensor + direction * (10.0 / direction[:, 1:2])  # the wall y = -10
    cloud = PointCloud(points, sensors=sensor[None], geospatial=True)
    prepared, report = prepare(cloud)
    assert report["splat_bound"]["angular_step"] == pytest.approx(step, rel=0.3)
    assert "facing the sensor" in report["normals"]
    assert (prepared.normals[:, 1] < -0.99).all()  # towards the sensor, on the -y side
    assert report["splat_bound"]["capped"] < 0.05 * len(points)
    ranges = np.linalg.norm(points - sensor, axis=1)
    far = ranges > np.percentile(ranges, 90)
    near = ranges < np.percentile(ranges, 10)
    assert prepared.radii[far].mean() > 1.5 * prepared.radii[near].mean()


def _square_mesh(centre, turn_degrees: float, rows: int = 20) -> PointCloud:
    """A 2 x 2 square facing +z, turned about y by `turn_degrees` (its normal towards +x), at `centre`."""
    grid, faces = models.plate(rows + 1, 1.0)
    cos, sin = math.cos(math.radians(turn_degrees)), math.sin(math.radians(turn_degrees))
    rotation = np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]])
    return PointCloud(grid @ rotation.T + centre, faces=faces)


@requires_gl
def test_a_surface_scanned_at_a_grazing_angle_stays_hole_free():
    """One view of two squares, one facing the scanner and one turned 65 degrees from its rays:
    the turned one's samples lie farther apart along its tilt, and most of its returns are lost
    at that angle, at random. Its splats must still cover it: the spacing bound grows with the
    incidence (spacing.py), where it had cut a quarter of the square into scattered dots."""
    facing, turned = _square_mesh([-1.2, 0.0, 0.0], 0.0), _square_mesh([1.2, 0.0, 0.0], 65.0)
    mesh = PointCloud(np.concatenate([facing.positions, turned.positions]),
                      faces=np.concatenate([facing.faces, turned.faces + len(facing)]))
    raw = scan(mesh, ScanSettings(views=1, resolution=256, misalignment=0.0), Renderer())
    on_turned = raw.positions[:, 0] > 0.05
    assert 0.02 < on_turned.mean() < 0.1  # far sparser than the square facing the scanner
    prepared, report = prepare(raw, progress=False)
    normal = np.array([math.sin(math.radians(65.0)), 0.0, math.cos(math.radians(65.0))])
    camera = frame(np.zeros(3), 1.5, eye=[1.2, 0.0, 0.0] + 6.0 * normal, target=[1.2, 0.0, 0.0], size=(256, 256))
    result = render(prepared, camera, "deferred", backend="cpu", shading="lambert")
    pixels, _ = camera.project(prepared.positions[on_turned])
    inside = _inside_hull(pixels, (256, 256), shrink=6.0)
    assert inside.sum() > 0.25 * inside.size
    assert (result.alpha[inside] < 0.5).mean() < 0.005
    assert "incidence" in report["splat_bound"]["reference"]


def test_the_ground_around_a_terrestrial_scanner_stays_closed_at_grazing_ranges():
    """A scanner on a tripod sees the ground ever more obliquely with range: its rings of samples
    lie 1 / cos theta farther apart than its angular step there, and fewer returns come back.
    The spacing bound follows the incidence (spacing.py), so the ground seen from above is one
    surface out to the edge of the scan, not rings of dots (87% of it covered before)."""
    rng = np.random.default_rng(1)
    step = math.radians(0.4)
    azimuth, elevation = np.meshgrid(np.arange(-math.pi, math.pi, step),
                                     np.arange(math.radians(-60.0), math.radians(-4.0), step))
    rays = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)],
                    -1).reshape(-1, 3)
    sensor = np.array([0.0, 0.0, 1.5])
    ranges = 1.5 / -rays[:, 2] + rng.normal(0.0, 0.005, len(rays))
    returned = rng.random(len(rays)) < np.clip((-rays[:, 2] - 0.05) / 0.3, 0.0, 1.0)  # lost at grazing angles
    points = sensor + rays * ranges[:, None]
    points = points[returned & (np.abs(points[:, :2]) < 10.0).all(axis=1)]
    prepared, report = prepare(PointCloud(points, sensors=sensor[None], geospatial=True), progress=False)
    camera = frame(np.zeros(3), 10.0, view="top", geospatial=True, size=(256, 256), ortho_height=20.0)
    result = render(prepared, camera, "deferred", backend="cpu", shading="lambert")
    assert (result.alpha > 0.5).mean() > 0.98
    assert "incidence" in report["splat_bound"]["reference"]


# --- screen-facing splats ----------------------------------------------------------------------

def facing_cloud(count: int = 8, radius: float = 2.0) -> PointCloud:
    """Splats flagged screen_facing at positions whose axis-aligned projections never overlap
    (x, y and z are three permutations of a 6 m grid), with random normals: drawn as oriented
    disks they would shrink with |cos| of their tilt."""
    rng = np.random.default_rng(5)
    grid = np.arange(count) * 6.0
    positions = np.stack([rng.permutation(grid), rng.permutation(grid), rng.permutation(grid)], 1)
    normals = rng.normal(size=(count, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    radii = np.full(count, radius)
    return PointCloud(positions, normals=normals, radii=radii, axes=tangent_frames(normals, radii),
                      attributes={"screen_facing": np.ones(count, np.float32)})


def ortho_view(cloud: PointCloud, view: str, pixels: int = 512):
    return frame(cloud.center, cloud.bounding_radius, view=view, size=(pixels, pixels),
                 ortho_height=2.4 * cloud.bounding_radius)


@requires_gl
@pytest.mark.parametrize("method", SPLAT_METHODS)
def test_screen_facing_splats_are_round_disks_facing_every_view(method):
    cloud = facing_cloud()
    areas = []
    for view in ("front", "top", "right"):
        camera = ortho_view(cloud, view)
        result = render(cloud, camera, method, shading="lambert")
        covered = result.alpha > 0.5
        areas.append(covered.sum())
        solid = result.alpha > 0.99
        # the normal is the direction to the eye: lit head-on, white
        assert (result.normals[solid, 2] > 0.99).all(), view
        assert (result.color[solid] > 0.97).all(), view
        if method != "ewa":  # EWA's coverage follows its Gaussian's weight, not the disk's rim
            pixels_per_unit = camera.height / camera.ortho_height
            disk = math.pi * (cloud.radii[0] * pixels_per_unit) ** 2
            assert covered.sum() == pytest.approx(len(cloud) * disk, rel=0.1), view
    assert max(areas) <= 1.05 * min(areas), areas


@requires_gl
def test_screen_facing_splats_agree_on_the_gpu_and_the_cpu():
    from surfel.metrics import compare_results

    cloud = facing_cloud()
    for view in ("front", "top"):
        camera = frame(cloud.center, cloud.bounding_radius, view=view, size=(256, 256))  # perspective
        gpu = render(cloud, camera, "ewa", backend="gl", shading="lambert")
        cpu = render(cloud, camera, "ewa", backend="cpu", shading="lambert")
        assert compare_results(cpu, gpu)["psnr"] > 40
        assert abs(int((gpu.alpha > 0.5).sum()) - int((cpu.alpha > 0.5).sum())) <= 0.01 * (cpu.alpha > 0.5).sum()


@requires_gl
def test_vegetation_faces_the_camera_and_surfaces_keep_their_orientation():
    prepared, report = prepare(load(DATA / "vegetation_1_3.las"))
    facing = prepared.attributes["screen_facing"] > 0.5
    assert report["screen_facing"] == facing.sum() > 0.5 * len(prepared)  # a tree's crown
    ground, _ = prepare(load(DATA / "simple.las"))  # mostly ground and roofs
    assert (ground.attributes["screen_facing"] > 0.5).mean() < 0.5
    assert (ground.normals[ground.attributes["screen_facing"] < 0.5, 2] > 0).all()  # up, no sensor known


# --- degenerate clouds (issue 15, item 11) -----------------------------------------------------

@requires_gl
@pytest.mark.parametrize("positions", [[[0.0, 0, 0]], [[0.0, 0, 0], [1, 0, 0]],
                                       [[t, 2 * t, -t] for t in np.linspace(0, 1, 20)]],
                         ids=["one point", "two points", "collinear"])
def test_clouds_without_a_tangent_plane_render_round_dots(positions):
    cloud = PointCloud(np.array(positions))
    for method, backend in [(m, None) for m in SPLAT_METHODS] + [("ewa", "cpu")]:
        result = Renderer().render(cloud, frame(cloud.center, cloud.bounding_radius, size=(128, 128)), method,
                                   backend=backend)
        covered = (result.alpha > 0.5).mean()
        assert 0 < covered < 0.5, (method, backend, covered)
        assert result.stats["estimated"]["screen_facing"] == len(cloud)
        if len(cloud) == 2:  # two dots, one at each end
            assert (result.alpha[:, :64] > 0.5).any() and (result.alpha[:, 64:] > 0.5).any()


# --- level of detail ---------------------------------------------------------------------------

def test_inner_nodes_of_screen_facing_splats_face_the_camera_and_enclose_them():
    prepared, _ = prepare(load(DATA / "vegetation_1_3.las"))
    tree = build_lod(prepared, progress=False)
    facing = tree.screen_facing
    inner = np.arange(tree.n_leaves, len(tree))
    children_facing = np.zeros(len(tree))
    weight = np.zeros(len(tree))
    for node in inner:  # every child facing: the node faces too
        kids = tree.children[tree.child_start[node]:tree.child_start[node + 1]]
        children_facing[node] = facing[kids].min()
        weight[node] = facing[kids].mean()
    assert (facing[inner][children_facing[inner] > 0.5] > 0.5).all()
    assert (facing[inner][weight[inner] == 0] == 0).all()
    # a facing node's disk reaches every leaf disk below it, whichever way it is seen
    leaf_of = np.arange(len(tree))
    ancestors = {node: [] for node in inner}
    for leaf in range(tree.n_leaves):
        node = tree.parent[leaf]
        while node >= 0:
            ancestors[node].append(leaf)
            node = tree.parent[node]
    for node in inner[facing[inner] > 0.5][::25]:
        leaves = leaf_of[ancestors[node]]
        reach = np.linalg.norm(tree.positions[leaves] - tree.positions[node], axis=1) + tree.radii[leaves]
        assert reach.max() <= tree.radii[node] * (1 + 1e-5)


# --- E57 scans ---------------------------------------------------------------------------------

def rotation_z(degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def test_e57_scans_merge_by_their_poses():
    cloud = load(DATA / "pump_two_scans.e57")  # poses: 30 degrees about z, then 180 (see its LICENSE)
    scan = cloud.attributes["scan"]
    assert cloud.schema["scan"].kind == "categorical" and np.bincount(scan).tolist() == [6467, 6467]
    np.testing.assert_allclose(cloud.sensors, [[2.0, -1.0, 0.5], [4.0, -14.0, 0.0]])
    assert cloud.geospatial and cloud.colors is not None and 0 < cloud.colors.max() <= 1
    assert cloud.attributes["intensity"].dtype == np.float32 and np.ptp(cloud.attributes["intensity"]) > 0
    # the two scans are two subsamples of one station: undoing each pose lays them on one another
    local = [(cloud.positions[scan == i] - cloud.sensors[i]) @ rotation_z(angle) for i, angle in ((0, 30), (1, 180))]
    spacing = np.median(cKDTree(local[0]).query(local[0], k=2)[0][:, 1])
    assert np.median(cKDTree(local[0]).query(local[1])[0]) < 1.5 * spacing
    assert np.median(cKDTree(cloud.positions[scan == 0]).query(cloud.positions[scan == 1])[0]) > 20 * spacing


def test_normals_face_the_sensor_of_their_own_scan():
    cloud = load(DATA / "pump_two_scans.e57")
    own, other = cloud.sensor_positions(), cloud.sensors[1 - cloud.attributes["scan"]]
    prepared, report = prepare(cloud)
    assert "facing the sensor" in report["normals"] and "range" in report["splat_bound"]["reference"]

    def facing(normals, sensors):
        return float((np.einsum("ij,ij->i", normals, sensors - cloud.positions) > 0).mean())

    assert facing(prepared.normals, own) == 1.0 and facing(prepared.normals, other) < 0.6
    unknown, _ = prepare(cloud.with_(sensors=None))  # the geospatial rule: up
    assert facing(unknown.normals, own) < 0.9


def test_e57_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.e57"
    bad.write_bytes(b"ASTM-E57" + bytes(2000))
    with pytest.raises(InputError, match="bad.e57"):
        load(bad)
    truncated = tmp_path / "truncated.e57"
    truncated.write_bytes((DATA / "pump_two_scans.e57").read_bytes()[:50_000])
    with pytest.raises(InputError, match="truncated.e57"):
        load(truncated)


def test_sensor_option(tmp_path):
    request = parse_render({"input": str(DATA / "simple.las"), "output": str(tmp_path / "x.png"),
                            "sensor": "636000,849000,1500"})
    assert request.sensor == (636000.0, 849000.0, 1500.0) and "--sensor" in request.argv
    cloud = request.open_input()
    np.testing.assert_array_equal(cloud.sensors, [[636000.0, 849000.0, 1500.0]])
    prepared, report = prepare(cloud)
    assert "facing the sensor" in report["normals"]
    towards = np.einsum("ij,ij->i", prepared.normals, cloud.sensors[0] - cloud.positions)
    assert (towards > 0).all()
    assert open_input(DATA / "simple.las").sensors is None
    with pytest.raises(SurfelError, match="--sensor"):
        parse_render({"input": "x.las", "output": "x.png", "sensor": "1,2"})


# --- COPC: estimation reused from view to view -------------------------------------------------

def test_copc_estimates_each_node_once():
    source = CopcSource(DATA / "simple_with_page.copc.laz")  # laspy's: no normals, no radii
    assert source.describe()["normals"] is False

    def camera(zoom, view="top"):
        return frame(source.center, source.bounding_radius, geospatial=True, size=(256, 256), view=view, zoom=zoom)

    first, stats = source.select(camera(1.0), 1.0)
    assert stats["estimated_points"] == len(first) and stats["reused_points"] == 0
    again, stats = source.select(camera(1.0, "iso"), 1.0)  # another view of the same nodes
    assert stats["estimated_points"] == 0 and "estimated" not in stats
    np.testing.assert_array_equal(again.normals, first.normals)
    closer, stats = source.select(camera(0.3), 1.0)  # finer nodes: only those are estimated
    assert len(closer) > len(first)
    assert stats["estimated_points"] == len(closer) - stats["reused_points"] > 0
    assert stats["reused_points"] == len(first)
    _, shared, index = np.intersect1d(_keys(first), _keys(closer), return_indices=True)
    np.testing.assert_array_equal(closer.normals[index], first.normals[shared])
    # the reused estimates render as a fresh source's own estimates do
    fresh, _ = CopcSource(DATA / "simple_with_page.copc.laz").select(camera(0.3), 1.0)
    assert (np.einsum("ij,ij->i", closer.normals, fresh.normals) > 0.9).mean() > 0.9


def _keys(cloud: PointCloud) -> np.ndarray:
    """A sortable key per point: its position, as a structured row."""
    return np.ascontiguousarray(cloud.positions).view([("x", float), ("y", float), ("z", float)]).ravel()


@requires_gl
def test_copc_orbit_renders_estimate_once():
    source = open_input(DATA / "simple_with_page.copc.laz")
    with Renderer() as renderer:
        estimated = []
        for azimuth in range(0, 360, 90):
            camera = frame(source.center, source.bounding_radius, geospatial=True, size=(128, 128),
                           azimuth=azimuth, elevation=30)
            result = renderer.render(source, camera)
            estimated.append(result.stats["estimated_points"])
            assert (result.alpha > 0).any()
    assert estimated[0] > 0 and estimated[1:] == [0, 0, 0]
