"""The `mesh` ground truth against an independent CPU rasterization of the same mesh."""

import numba
import numpy as np
import pytest

from conftest import requires_gl
from models import dense_spot
from surfel.camera import frame
from surfel.metrics import psnr
from surfel.rendering import render

pytestmark = requires_gl


@numba.njit(cache=True)
def _rasterize(xy, depth, normals, faces, width, height, samples):
    """Z-buffered barycentric rasterization at samples x samples points per pixel;
    returns per-sample interpolated normal (unnormalised) and coverage."""
    w, h = width * samples, height * samples
    zbuf = np.full((h, w), np.inf)
    nbuf = np.zeros((h, w, 3))
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay = xy[a, 0] * samples, xy[a, 1] * samples
        bx, by = xy[b, 0] * samples, xy[b, 1] * samples
        cx, cy = xy[c, 0] * samples, xy[c, 1] * samples
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue
        x0 = max(int(np.floor(min(ax, bx, cx))), 0)
        x1 = min(int(np.ceil(max(ax, bx, cx))), w - 1)
        y0 = max(int(np.floor(min(ay, by, cy))), 0)
        y1 = min(int(np.ceil(max(ay, by, cy))), h - 1)
        for j in range(y0, y1 + 1):
            py = j + 0.5
            for i in range(x0, x1 + 1):
                px = i + 0.5
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / area
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0 or w1 < 0 or w2 < 0:
                    continue
                # perspective-correct: interpolate 1/z and attribute/z
                iz = w0 / depth[a] + w1 / depth[b] + w2 / depth[c]
                z = 1.0 / iz
                if z < zbuf[j, i]:
                    zbuf[j, i] = z
                    for k in range(3):
                        nbuf[j, i, k] = z * (w0 * normals[a, k] / depth[a] + w1 * normals[b, k] / depth[b]
                                             + w2 * normals[c, k] / depth[c])
    return zbuf, nbuf


def independent_lambert(cloud, camera, samples=4):
    xy, depth = camera.project(cloud.positions)
    eye_normals = cloud.normals.astype(np.float64) @ camera.world_to_eye[:3, :3].T
    zbuf, nbuf = _rasterize(xy, depth, eye_normals, cloud.faces, camera.width, camera.height, samples)
    covered = np.isfinite(zbuf)
    n = nbuf / np.maximum(np.linalg.norm(nbuf, axis=-1, keepdims=True), 1e-12)
    shade = np.where(covered, 0.2 + 0.8 * np.abs(n[..., 2]), 0.0)
    h, w = camera.height, camera.width
    color = shade.reshape(h, samples, w, samples).mean(axis=(1, 3))
    return color, covered.reshape(h, samples, w, samples).mean(axis=(1, 3))


@pytest.mark.parametrize("view", ["front", "right"])
def test_mesh_matches_independent_rasterization(view):
    cloud = dense_spot()
    camera = frame(cloud.center, cloud.bounding_radius, view=view, size=(256, 256))
    ours = render(cloud, camera, "mesh", shading="lambert")
    color, alpha = independent_lambert(cloud, camera)
    assert np.abs(ours.alpha - alpha).mean() < 0.01
    ref8 = np.round(np.repeat(color[..., None], 3, -1) * 255)
    assert psnr(ref8, np.round(ours.color * 255)) >= 35
