"""EWA splatting (Zwicker et al. 2001), CPU backend: filter maths and renders of real models."""

from __future__ import annotations

import math

import numpy as np
import pytest

from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.methods import ewa_kernels as k
from surfel.methods.ewa import EwaParams, render_ewa_cpu, splat_inputs
from surfel.options import RenderOptions, SettingError
from surfel.preprocess import INACTIVE_CLIP
from surfel.rendering import Renderer


def _plane(n: int = 40) -> PointCloud:
    """A jittered grid of tilted splats, radius 1.2x the spacing."""
    rng = np.random.default_rng(1)
    g = (np.stack(np.meshgrid(np.arange(n), np.arange(n)), -1).reshape(-1, 2) + rng.uniform(-0.2, 0.2, (n * n, 2))) / n
    pos = np.column_stack([g[:, 0] - 0.5, g[:, 1] - 0.5, np.zeros(n * n)])
    normals = np.tile([0.0, 0.0, 1.0], (n * n, 1))
    r = 1.2 / n
    axes = np.tile([[[r, 0, 0], [0, r, 0]]], (n * n, 1, 1))
    return PointCloud(pos, normals=normals, radii=np.full(n * n, r), axes=axes)


def ewa_cpu(cloud, camera, **options):
    return render_ewa_cpu(cloud, camera, RenderOptions(**options), EwaParams(), Renderer())


def _setup(cloud, camera, sigma=0.5, lowpass=1.0):
    intr = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    ortho = 0.0 if camera.ortho_height is None else camera.height / camera.ortho_height
    return k.setup_splats(cloud.positions, cloud.local_origin, camera.world_to_eye, *splat_inputs(cloud),
                          intr, ortho, camera.near,
                          np.float32(1), np.float32(sigma ** 2), np.float32(lowpass ** 2), np.float32(0.04),
                          np.float32(9.21), np.float32(1), np.float32(4), False, camera.width, camera.height)


def test_kernel_inputs_are_read_only_whatever_the_cloud_holds():
    """numba compiles setup_splats apart for writable and read-only arrays (some 10 s each):
    splat_inputs hands it read-only, contiguous ones for a plain cloud and for one with
    colours, clip lines, a normal field, layer thickness and screen-facing splats alike."""
    plain = _plane(8)
    n = len(plain)
    zeros = np.zeros(n, np.float32)
    rich = plain.with_(colors=np.full((n, 3), 0.5, np.float32), attributes={
        "clip_lines": np.tile(np.float32(INACTIVE_CLIP), (n, 2, 1)), "phong_alpha": zeros, "phong_beta": zeros,
        "thickness": np.full(n, 0.01, np.float32), "screen_facing": (np.arange(n) % 2).astype(np.float32)})
    for cloud in (plain, rich):
        arrays = splat_inputs(cloud)
        assert len(arrays) == 6
        assert all(not a.flags.writeable and a.flags.c_contiguous for a in arrays)
    assert (splat_inputs(rich)[0][1::2] == 0).all()  # the screen-facing splats' normals: zero


@pytest.mark.parametrize("ortho", [None, 1.5])
def test_conic_matches_finite_differences_of_project(ortho):
    cloud = _plane(8)
    cam = frame(cloud.center, 0.7, azimuth=35, elevation=20, size=(128, 128), ortho_height=ortho)
    sigma, lowpass = 0.5, 1.0
    splats, _, _ = _setup(cloud, cam, sigma, lowpass)
    eps = 1e-6
    for i in (0, 17, 40):
        c, (u, v) = cloud.positions[i], cloud.axes[i].astype(np.float64)
        m0 = cam.project(c[None])[0][0]
        jac = np.column_stack([(cam.project((c + eps * a)[None])[0][0] - m0) / eps for a in (u, v)])
        cov = sigma ** 2 * jac @ jac.T + lowpass ** 2 * np.eye(2)
        conic = np.linalg.inv(cov)
        got = splats[i]
        np.testing.assert_allclose(got[[k.MX, k.MY]], m0, rtol=1e-5)
        np.testing.assert_allclose([got[k.CA], got[k.CB], got[k.CC]], [conic[0, 0], conic[0, 1], conic[1, 1]],
                                   rtol=2e-3, atol=1e-6)
        np.testing.assert_allclose(got[k.WS], abs(np.linalg.det(jac)) / math.sqrt(np.linalg.det(cov)), rtol=2e-3)


def test_default_cutoff_keeps_90_percent_of_the_mass():
    params = EwaParams()
    assert 1 - math.exp(-params.cutoff2 / 2) == pytest.approx(0.9)
    assert EwaParams(cutoff_mass=0.99).cutoff2 > params.cutoff2
    with pytest.raises(SettingError, match="cutoff_mass"):
        EwaParams(cutoff_mass=1.0)


@pytest.mark.parametrize("ortho", [None, 1.5])
def test_plane_is_covered_without_holes(ortho):
    cloud = _plane()
    cam = frame(cloud.center, 0.7, size=(96, 96), ortho_height=ortho)
    res = ewa_cpu(cloud, cam, shading="lambert")
    inner = res.alpha[30:66, 30:66]
    assert inner.min() > 0.99
    np.testing.assert_allclose(res.color[30:66, 30:66], 1.0, atol=1e-3)  # lambert, facing the camera
    assert res.alpha[0, 0] == 0 and np.isinf(res.depth[0, 0])
    np.testing.assert_allclose(res.normals[48, 48], [0, 0, 1], atol=1e-4)
    assert res.stats["splats"] == len(cloud)


@pytest.mark.parametrize("model", ["dense_spot", "spot", "turned_part"])
@pytest.mark.parametrize("view", ["front", "right"])
def test_against_mesh(model, view):
    from surfel.gl.context import gl_available
    if not gl_available():
        pytest.skip("the mesh reference needs OpenGL")
    import models
    from surfel.metrics import compare_results
    from surfel.preprocess import complete
    from surfel.rendering import default_camera, render

    cloud = getattr(models, model)()
    cam = default_camera(cloud, (512, 512), view=view)
    ref = render(cloud, cam, "mesh", shading="lambert")
    res = ewa_cpu(complete(cloud, normal_field=True)[0], cam, shading="lambert")
    m = compare_results(ref, res)
    assert m["psnr"] >= 27 and m["holes"] <= 0.001, m
    both = (ref.alpha > 0.99) & (res.alpha > 0.99)
    assert np.median(np.abs(ref.depth[both] - res.depth[both])) < 0.01 * np.median(ref.depth[both])


@pytest.fixture(scope="module")
def spot_scan():
    """The coarse Spot mesh and a raw scan of it (surfel scan's defaults: six views, range
    noise, misregistration, samples lost at grazing angles)."""
    import models
    from surfel.scan import scan

    mesh = models.spot()
    return mesh, scan(mesh)


@pytest.mark.parametrize("azimuth, elevation", [(0, 0), (0, -25), (180, -25)])
def test_raw_scan_is_rendered_without_holes(spot_scan, azimuth, elevation):
    """Where the scan's views overlap, and at the occlusion contours of its legs, the weight
    sum W reads the sampling as partly covered (up to 0.6% of these views fell below alpha
    0.5 over the mesh); the splats' inner ellipses cover those pixels (ewa.py: coverage)."""
    from surfel.gl.context import gl_available
    if not gl_available():
        pytest.skip("the mesh reference needs OpenGL")
    from surfel.metrics import compare_results
    from surfel.rendering import render

    mesh, cloud = spot_scan
    cam = frame(mesh.center, mesh.bounding_radius, azimuth=azimuth, elevation=elevation, size=(256, 256))
    options = {"shading": "lambert", "background": (0.0, 0.0, 0.0)}
    m = compare_results(render(mesh, cam, "mesh", **options), render(cloud, cam, "ewa", backend="cpu", **options))
    assert m["holes"] <= 0.001 and m["psnr"] >= 29, m


def test_minification_error_at_most_that_of_deferred_ewa():
    """The survey's Fig. 10 checkerboard at a grazing angle: the full resampling filter must
    anti-alias the minified far half at least as well as deferred splatting's EWA approximation."""
    from surfel.gl.context import gl_available
    if not gl_available():
        pytest.skip("the deferred comparison needs OpenGL")
    from scenes import checker_plane, checker_reference, far_half_rms, grazing_camera
    from surfel.rendering import render

    cam = grazing_camera((512, 512))
    plane = checker_plane()
    reference = checker_reference(cam, samples=8)
    deferred = far_half_rms(reference, render(plane, cam, "deferred", shading="none", ewa_filter=True))
    ours = far_half_rms(reference, ewa_cpu(plane, cam, shading="none"))
    assert ours <= deferred


def test_partly_covered_front_layer_shows_the_surface_behind():
    """Two layers: a small plane in front of a big one; at the small plane's anti-aliased rim
    the big plane shows through, so there is no dark outline (the A-buffer composite)."""
    back, front = _plane(40), _plane(20)
    front = PointCloud(front.positions * [0.4, 0.4, 0] + [0, 0, 0.2], normals=front.normals,
                       radii=front.radii * 0.4, axes=front.axes * 0.4)
    both = PointCloud(np.vstack([back.positions, front.positions]), normals=np.vstack([back.normals, front.normals]),
                      radii=np.concatenate([back.radii, front.radii]), axes=np.vstack([back.axes, front.axes]))
    cam = frame(back.center, 0.7, size=(96, 96))
    res = ewa_cpu(both, cam, shading="lambert")
    inner = res.alpha[30:66, 30:66]
    assert inner.min() > 0.99
    np.testing.assert_allclose(res.color[30:66, 30:66], 1.0, atol=1e-3)
