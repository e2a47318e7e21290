"""Synthetic test scenes with analytic ground truth (shared by several test files)."""

from __future__ import annotations

import numpy as np

from surfel.camera import Camera
from surfel.cloud import PointCloud

SQUARES = 64


def checker(xy: np.ndarray) -> np.ndarray:
    """Black/white checkerboard with SQUARES squares across [-1, 1]^2."""
    ij = np.floor((xy + 1) / 2 * SQUARES).astype(np.int64)
    return ((ij[..., 0] + ij[..., 1]) % 2).astype(np.float32)


def checker_plane(n_side: int = 608, seed: int = 0) -> PointCloud:
    """About 370k jittered samples of the plane z = 0 over [-1, 1]^2 with checker colours."""
    rng = np.random.default_rng(seed)
    g = (np.arange(n_side) + 0.5) / n_side * 2 - 1
    x, y = np.meshgrid(g, g)
    xy = np.c_[x.ravel(), y.ravel()] + rng.uniform(-0.3, 0.3, (n_side * n_side, 2)) * (2 / n_side)
    xy = np.clip(xy, -1, 1)
    c = checker(xy)
    pos = np.c_[xy, np.zeros(len(xy))]
    radius = np.full(len(xy), 2 / n_side * 1.0, np.float32)
    axes = np.zeros((len(xy), 2, 3), np.float32)
    axes[:, 0, 0] = radius
    axes[:, 1, 1] = radius
    return PointCloud(pos, normals=np.tile([0, 0, 1.0], (len(xy), 1)), colors=np.repeat(c[:, None], 3, 1),
                      radii=radius, axes=axes)


def grazing_camera(size=(512, 512)) -> Camera:
    cam = Camera.look_at([0, -3.5, 0.3], [0, 0.3, 0], [0, 0, 1], fov=30, size=size)
    return cam.fit_clip_planes([0, 0, 0], 1.5)


def checker_reference(camera: Camera, samples: int = 16):
    """16x16-supersampled analytic render: (rgb over black, alpha, hit distance per pixel)."""
    h, w = camera.height, camera.width
    inv = np.linalg.inv(camera.world_to_eye)
    color = np.zeros((h, w), np.float64)
    alpha = np.zeros((h, w), np.float64)
    offsets = (np.arange(samples) + 0.5) / samples
    for oy in offsets:
        for ox in offsets:
            j, i = np.meshgrid(np.arange(w) + ox, np.arange(h) + oy)
            d = np.stack([(j - camera.cx) / camera.fx, (camera.cy - i) / camera.fy, -np.ones_like(j)], -1)
            d_world = d @ inv[:3, :3].T
            eye = camera.eye
            t = -eye[2] / d_world[..., 2]
            hit = eye + t[..., None] * d_world
            inside = (t > 0) & (np.abs(hit[..., 0]) <= 1) & (np.abs(hit[..., 1]) <= 1)
            color += np.where(inside, checker(hit[..., :2]), 0)
            alpha += inside
    n = samples * samples
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(j - camera.cx) / camera.fx, (camera.cy - i) / camera.fy, -np.ones_like(j)], -1) @ inv[:3, :3].T
    t = -camera.eye[2] / d[..., 2]
    return color / n, alpha / n, np.where(t > 0, t, np.inf)


def far_half_rms(reference, result) -> float:
    """RMS error of grey level over the far half (by distance) of the pixels the plane covers."""
    ref_color, ref_alpha, distance = reference
    covered = ref_alpha >= 0.999
    far = covered & (distance > np.median(distance[covered]))
    err = result.color.mean(axis=-1) - ref_color
    return float(np.sqrt(np.mean(err[far] ** 2)))


def sheet_on_body(rng, height: float = 0.1):
    """A body z = 0 sampled at a spacing of about 1 (jittered) with a thin sheet lying on it
    (y < 0, `height` above) whose rolled rim along y = 0 is sampled four times as densely, its
    normals turning from 30 degrees above outward to straight down (a belt on a body: ogre's
    belt points among a body point's neighbours face -0.5 to 0.6 of its way).
    Returns (points, normals, body)."""
    g = np.arange(-12.0, 12.5)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2) + rng.uniform(-0.25, 0.25, (len(g) ** 2, 2))
    body = np.c_[xy, np.zeros(len(xy))]
    top = body[body[:, 1] < -0.5] + [0.3, 0.3, height]
    along = np.arange(-12.0, 12.0, 0.25)
    turn = np.radians(np.linspace(-90.0, 30.0, 5))
    a, t = (m.ravel() for m in np.meshgrid(along, turn))
    rim_normals = np.c_[np.zeros(len(t)), np.cos(t), np.sin(t)]
    rim = np.c_[a, np.zeros(len(a)), np.full(len(a), 0.5 * height)] + 0.5 * height * rim_normals
    points = np.concatenate([body, top, rim])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(body) + len(top), 1)), rim_normals])
    return points, normals, np.arange(len(points)) < len(body)



def sheet_over_body(rng, height: float = 0.3):
    """A body z = 0 (blue) and a sheet `height` above it over y < 0 (red), both sampled at a
    spacing of about 1 (jittered), normals +z: two surfaces closer than a splat radius (about
    0.9), as cloth on a body. Returns the cloud and the sheet's mask."""
    g = np.arange(-20.0, 20.5)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    body = np.c_[xy + rng.uniform(-0.25, 0.25, xy.shape), np.zeros(len(xy))]
    under = xy[xy[:, 1] < 0]
    sheet = np.c_[under + rng.uniform(-0.25, 0.25, under.shape), np.full(len(under), height)]
    points = np.concatenate([body, sheet])
    colors = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(body), 1)), np.tile([1.0, 0.0, 0.0], (len(sheet), 1))])
    cloud = PointCloud(points, normals=np.tile([0.0, 0.0, 1.0], (len(points), 1)), colors=colors)
    return cloud, np.arange(len(points)) >= len(body)
