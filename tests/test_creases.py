"""Splats at a coarse part's creases and borders (methods/splatting.py): curved splats reach a
face's outline, the crease blend rounds the shading of its edges as a mesh's interpolated
normals do, and past a border it blends with nothing farther back."""

import numpy as np
import pytest
from scipy import ndimage

import models
from conftest import requires_gl
from surfel.camera import frame
from surfel.metrics import compare_results
from surfel.rendering import render

pytestmark = requires_gl
SIZE = (512, 512)


@pytest.fixture(scope="module")
def puck():
    """The puck's mesh, its vertices, and its mesh rendered from above at azimuth 0 and 60."""
    mesh = models.puck()
    cams = [frame(mesh.center, mesh.bounding_radius, azimuth=az, elevation=20.0, size=SIZE) for az in (0.0, 60.0)]
    return mesh.with_(faces=None), cams, [render(mesh, cam, "mesh", shading="lambert") for cam in cams]


@pytest.mark.parametrize("backend", ["gl", "cpu"])
@pytest.mark.parametrize("method", ["deferred", "phong"])
def test_a_coarse_parts_faces_reach_its_outline(puck, method, backend):
    """`deferred`'s splats bent by the shading field ended a face half a pixel short of its
    edge (0.7% of the puck's pixels left uncovered along its outline)."""
    cloud, cams, refs = puck
    for cam, ref in zip(cams, refs, strict=True):
        metrics = compare_results(ref, render(cloud, cam, method, shading="lambert", backend=backend))
        assert metrics["holes"] <= 0.001, metrics


@pytest.mark.parametrize("backend", ["gl", "cpu"])
@pytest.mark.parametrize("method", ["deferred", "phong"])
def test_a_plate_thinner_than_its_sampling_keeps_its_outline(method, backend):
    """A puck 0.06 thick, six tenths of its sampling: its rim's splats are cut where the rim
    turns down to the other face (cells.py). Uncut, each stood out past the rim by nearly its
    radius, a scalloped outline: 1.2% and 2.2% of these views spilled (21 and 18 dB). What
    spills now is the rim rounded out to where the two faces' rim planes meet."""
    mesh = models.puck(0.06)
    for azimuth, elevation, spill, psnr in ((0.0, 20.0, 0.004, 26.0), (30.0, 35.0, 0.01, 21.0)):
        cam = frame(mesh.center, mesh.bounding_radius, azimuth=azimuth, elevation=elevation, size=SIZE)
        out = render(mesh.with_(faces=None), cam, method, shading="lambert", backend=backend)
        metrics = compare_results(render(mesh, cam, "mesh", shading="lambert"), out)
        assert metrics["spill"] <= spill and metrics["psnr"] >= psnr, (elevation, metrics)


@pytest.mark.parametrize("backend", ["gl", "cpu"])
def test_the_crease_blend_rounds_a_coarse_parts_edges_as_the_mesh_shades_them(puck, backend):
    """Without the crease blend the faces met at the edges with a step in shading: 33.0 dB."""
    cloud, cams, refs = puck
    for cam, ref in zip(cams, refs, strict=True):
        metrics = compare_results(ref, render(cloud, cam, "phong", shading="lambert", backend=backend))
        assert metrics["psnr"] >= 33.8, metrics


@pytest.mark.parametrize("backend", ["gl", "cpu"])
@pytest.mark.parametrize("method", ["gaussian", "deferred", "phong"])
def test_past_a_border_splats_blend_with_nothing_farther_back(method, backend):
    """Seen through a red plate's opening, the blue plate behind keeps its colour: past the
    opening's border the red splats blend only with a surface they meet. Blending with
    anything no farther than the visible depth, they tinted a sixth of the opening red (2%
    is the red splats' own reach past the jagged border)."""
    mesh = models.plate_with_a_hole_over_a_plate()
    for azimuth, elevation in ((20.0, 15.0), (-30.0, 25.0)):
        cam = frame(mesh.center, mesh.bounding_radius, azimuth=azimuth, elevation=elevation, size=SIZE)
        ref = np.asarray(render(mesh, cam, "mesh", shading="none").color)
        out = np.asarray(render(mesh.with_(faces=None), cam, method, shading="none", backend=backend).color)
        # the opening: the blue pixels of the reference around the opening's centre, 2 pixels in
        blue = ndimage.binary_erosion((ref[..., 2] > 0.5) & (ref[..., 0] < 0.01), iterations=2)
        labels, _ = ndimage.label(blue)
        ((x, y),), _ = cam.project([[0.0, 0.0, 0.0]])
        opening = labels == labels[int(y), int(x)]
        assert opening.sum() > 1000
        assert (out[..., 0][opening] > 0.05).mean() < 0.05, (azimuth, elevation)
