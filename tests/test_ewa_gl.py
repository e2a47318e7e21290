"""EWA splatting (Zwicker et al. 2001), OpenGL backend: it must reproduce the CPU backend."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import requires_gl
from surfel.camera import frame
from surfel.methods.ewa import EwaParams, render_ewa_cpu
from surfel.metrics import compare_results
from surfel.options import RenderOptions
from surfel.rendering import Renderer

pytestmark = requires_gl

MIN_PSNR = 35.0


def _both(cloud, camera, supersample=None, **params):
    from surfel.methods.ewa_gl import render_ewa_gl

    opts, params = RenderOptions(shading="lambert", supersample=supersample), EwaParams(**params)
    # Clip planes around the splats, as render() sets them.
    camera = camera.fit_clip_planes(cloud.center, 1.1 * cloud.bounding_radius)
    renderer = Renderer()
    return render_ewa_cpu(cloud, camera, opts, params, renderer), render_ewa_gl(cloud, camera, opts, params, renderer)


@pytest.mark.parametrize("size", [256, 512])
def test_gl_matches_cpu_on_dense_spot(dense_spot, size):
    cam = frame(dense_spot.center, dense_spot.bounding_radius, view="front", size=(size, size))
    cpu, gl = _both(dense_spot, cam)
    assert gl.alpha.sum() > 0.05 * size * size  # the model is there
    assert compare_results(cpu, gl)["psnr"] >= MIN_PSNR
    assert gl.stats["splats"] == len(dense_spot) and gl.stats["fragments"] > 0


def test_clip_lines_and_normal_fields_match_cpu(turned_part):
    """A CAD part: splats cut at its creases, shaded with Phong normal fields, on both backends."""
    from surfel.preprocess import complete

    cloud = complete(turned_part, normal_field=True)[0]
    assert (cloud.attributes["clip_lines"][:, 0, 2] < 1).mean() > 0.1
    for view in ("front", "right"):
        cam = frame(cloud.center, cloud.bounding_radius, view=view, size=(256, 256))
        cpu, gl = _both(cloud, cam)
        assert compare_results(cpu, gl)["psnr"] >= MIN_PSNR


def test_orthographic_matches_cpu(dense_spot):
    cam = frame(dense_spot.center, dense_spot.bounding_radius, view="right", size=(256, 256),
                ortho_height=2.2 * dense_spot.bounding_radius)
    cpu, gl = _both(dense_spot, cam)
    assert gl.alpha.sum() > 0.05 * 256 * 256
    assert compare_results(cpu, gl)["psnr"] >= MIN_PSNR


def test_supersampling_and_culling_match_cpu(dense_spot):
    cam = frame(dense_spot.center, dense_spot.bounding_radius, view="front", size=(128, 128))
    cpu, gl = _both(dense_spot, cam, supersample=2, backface_culling=True)
    assert gl.color.shape == (128, 128, 3)
    assert compare_results(cpu, gl)["psnr"] >= MIN_PSNR
    np.testing.assert_allclose(gl.stats["full_weight"], cpu.stats["full_weight"], rtol=0.05)


def test_coverage_of_a_raw_scan_matches_cpu():
    """The coverage by the splats' inner ellipses (ewa.py), MIN-blended as 1 - coverage in the
    visibility pass: a raw scan's views overlap and leave W below the full weight in places,
    where alpha comes from it on both backends alike, and no hole opens over the mesh."""
    import models
    from surfel.preprocess import complete
    from surfel.scan import scan

    mesh = models.spot()
    cloud = complete(scan(mesh), normal_field=True)[0]
    cam = frame(mesh.center, mesh.bounding_radius, azimuth=0, elevation=-25, size=(256, 256))
    cpu, gl = _both(cloud, cam)
    reference = Renderer().render(mesh, cam.fit_clip_planes(cloud.center, 1.1 * cloud.bounding_radius), "mesh",
                                  options=RenderOptions(shading="lambert"))
    assert compare_results(reference, gl)["holes"] <= 0.001
    differ = np.abs(cpu.alpha - gl.alpha) > 0.1
    assert differ.mean() < 1e-3
    assert compare_results(cpu, gl)["psnr"] >= MIN_PSNR
