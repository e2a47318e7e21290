"""MLS smoothing of positions (preprocess/smoothing.py, `surfel prepare --smooth`): noise
removed against an analytic surface, creases and thin sheets kept, the command's output."""

from __future__ import annotations

import numpy as np

from conftest import invoke
from samples import sphere
from surfel.cloud import PointCloud
from surfel.io import load, write_ply
from surfel.preprocess import prepare


def test_smoothing_brings_a_noisy_sphere_closer_to_the_sphere():
    noisy = sphere(20_000, noise=0.004)
    smoothed, report = prepare(PointCloud(noisy), smooth=True)
    before = np.sqrt(np.mean((np.linalg.norm(noisy, axis=1) - 1) ** 2))
    after = np.sqrt(np.mean((np.linalg.norm(smoothed.positions, axis=1) - 1) ** 2))
    assert after < 0.4 * before
    assert "MLS projection" in report["smooth"]
    # the radius is kept: the sphere neither shrinks nor swells by more than a fraction of the noise
    assert abs(np.mean(np.linalg.norm(smoothed.positions, axis=1)) - 1) < 0.001


def test_a_crease_stays_sharp():
    """A noisy 90-degree wedge (the planes y = 0 and x = 0 for x, y >= 0): points near the edge
    come closer to their own plane, not rounded off towards the corner's bisector."""
    rng = np.random.default_rng(1)
    n = 10_000
    u, z = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    floor = np.c_[u, np.zeros(n), z]
    wall = np.c_[np.zeros(n), u, z]
    points = np.concatenate([floor, wall])
    noisy = points + rng.normal(0, 0.002, points.shape)
    on_floor = np.r_[np.ones(n, bool), np.zeros(n, bool)]
    smoothed, _ = prepare(PointCloud(noisy), smooth=True)

    def off_plane(p):
        return np.where(on_floor, np.abs(p[:, 1]), np.abs(p[:, 0]))

    near_edge = np.where(on_floor, noisy[:, 0], noisy[:, 1]) < 0.03
    assert np.mean(off_plane(smoothed.positions)[near_edge]) < 0.8 * np.mean(off_plane(noisy)[near_edge])
    assert np.mean(off_plane(smoothed.positions)) < 0.6 * np.mean(off_plane(noisy))
    # points on the edge itself are not pulled in between the planes (by 1.09 times the noise's
    # 99th percentile when a crease point's sums took both faces)
    between = np.minimum(np.abs(smoothed.positions[:, 0]), np.abs(smoothed.positions[:, 1]))
    noisy_between = np.minimum(np.abs(noisy[:, 0]), np.abs(noisy[:, 1]))
    assert np.percentile(between[near_edge], 99) < 0.9 * np.percentile(noisy_between[near_edge], 99)


def test_an_obtuse_crease_is_not_rounded_in():
    """A noisy convex crease where the surface turns by 40 degrees (a CAD part's chamfer): the
    estimated normals of points on it lie about 20 degrees from both faces. With neighbours
    taken up to 25 degrees off, those points averaged both faces and moved into the solid
    (0.36 of the noise on average), which shrank a CAD part's outline by a pixel (fandisk's
    scan); now they move in by less than 0.3 of it."""
    rng = np.random.default_rng(1)
    n, noise, turn = 10_000, 0.002, np.radians(40.0)
    u, z = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    points = np.concatenate([np.c_[u, np.zeros(n), z], np.c_[-u * np.cos(turn), -u * np.sin(turn), z]])
    normals = np.array([[0.0, 1, 0], [-np.sin(turn), np.cos(turn), 0]])  # outward: the solid lies below both

    def depth(p):  # below the nearer face: inside the solid
        return np.min(-(p @ normals.T), axis=1)

    noisy = points + rng.normal(0, noise, points.shape)
    smoothed, _ = prepare(PointCloud(noisy), smooth=True)
    near_crease = np.r_[u, u] < 0.03
    assert np.mean(depth(smoothed.positions)[near_crease]) < 0.3 * noise
    assert np.mean(np.abs(depth(smoothed.positions))) < 0.4 * np.mean(np.abs(depth(noisy)))  # still denoised


def test_a_thin_sheet_keeps_its_two_sides():
    """Two sides of a plate 0.01 apart (about the point spacing), each seen from its own side:
    smoothing does not pull them together."""
    rng = np.random.default_rng(2)
    n = 10_000
    xy = rng.uniform(0, 1, (2 * n, 2))
    z = np.r_[np.full(n, 0.005), np.full(n, -0.005)]
    points = np.c_[xy, z + rng.normal(0, 0.0005, 2 * n)]
    sensors = np.array([[0.5, 0.5, 3.0], [0.5, 0.5, -3.0]])
    scan = np.r_[np.zeros(n, np.int8), np.ones(n, np.int8)]
    cloud = PointCloud(points, sensors=sensors, attributes={"scan": scan})
    smoothed, _ = prepare(cloud, smooth=True)
    top, bottom = smoothed.positions[:n, 2], smoothed.positions[n:, 2]
    assert np.median(top) > 0.004 and np.median(bottom) < -0.004


def test_prepare_smooth_command(tmp_path):
    noisy = sphere(20_000, noise=0.004)
    source, out = tmp_path / "noisy.ply", tmp_path / "smooth.ply"
    write_ply(PointCloud(noisy), source)
    result = invoke("prepare", source, "-o", out, "--smooth")
    assert result.exit_code == 0, result.output
    smoothed = load(str(out))
    error = np.abs(np.linalg.norm(smoothed.positions, axis=1) - 1).mean()
    assert error < 0.5 * np.abs(np.linalg.norm(noisy, axis=1) - 1).mean()
    assert smoothed.normals is not None and smoothed.radii is not None
    assert "smooth: MLS projection" in result.output


def test_points_without_a_tangent_plane_stay_where_they_are():
    """A tile's ground is denoised; the scattered returns of a crown above it (no tangent plane,
    drawn facing the camera) are not gathered onto a surface they do not have."""
    rng = np.random.default_rng(4)
    ground = np.c_[rng.uniform(0, 20, (6000, 2)), rng.normal(0, 0.05, 6000)]
    crown = rng.normal([10, 10, 8], 1.5, (3000, 3))
    cloud = PointCloud(np.vstack([ground, crown]), geospatial=True)
    smoothed, report = prepare(cloud, smooth=True)
    facing = smoothed.attributes["screen_facing"] > 0.5
    moved = np.linalg.norm(smoothed.positions - cloud.positions, axis=1)
    assert facing[6000:].mean() > 0.9 and facing[:6000].mean() < 0.05  # the crown, not the ground
    assert np.all(moved[6000:][facing[6000:]] == 0)
    assert np.abs(smoothed.positions[:6000, 2]).mean() < 0.5 * np.abs(ground[:, 2]).mean()
