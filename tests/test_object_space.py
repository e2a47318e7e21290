"""Object-space EWA splatting (Ren et al. 2002): the resampling filter and the rendered surface."""

import numpy as np
import pytest

from conftest import requires_gl
from surfel.camera import frame
from surfel.methods.object_space import ResamplingFilter, decompose, resampling_matrix
from surfel.metrics import compare_results
from surfel.rendering import render


def test_eigen_decomposition_reproduces_the_filter():
    rng = np.random.default_rng(0)
    for _ in range(50):
        a = rng.normal(size=(2, 2))
        m = a @ a.T + 0.1 * np.eye(2)
        assert np.allclose(decompose(m).matrix(), m, atol=1e-9)


def test_quad_corners_circumscribe_the_cutoff_ellipse():
    f = ResamplingFilter(theta=0.4, r0=2.0, r1=0.5)
    corners = f.quad_corners(cutoff=2.0)
    # in the filter's own frame the corners sit at (±c r0, ±c r1): edge midpoints on the ellipse
    local = (f.rotation.T @ corners.T).T / [f.r0, f.r1]
    assert np.allclose(np.abs(local), 2.0)


def test_resampling_matrix_adds_the_lowpass_mapped_to_object_space():
    v = np.diag([1.0, 4.0])
    j = np.diag([10.0, 5.0])  # pixels per object unit
    m = resampling_matrix(v, j, lowpass_std=1.0)
    assert np.allclose(m, v + np.diag([0.01, 0.04]))


@requires_gl
@pytest.mark.parametrize("normalization", ["per-pixel", "per-surfel"])
def test_object_space_against_the_mesh(dense_spot, normalization):
    cam = frame(dense_spot.center, dense_spot.bounding_radius, size=(256, 256))
    ref = render(dense_spot, cam, "mesh", shading="lambert")
    result = render(dense_spot.with_(faces=None), cam, "object-space", shading="lambert", normalization=normalization)
    metrics = compare_results(ref, result)
    assert metrics["holes"] <= 0.001
    if normalization == "per-pixel":
        assert metrics["psnr"] >= 28 and metrics["interior_psnr"] >= 30
    else:  # the paper's approximation: darker and mottled, but a surface
        assert metrics["psnr"] >= 18
    assert result.stats["vertices"] == 4 * len(dense_spot)


@requires_gl
def test_level_of_detail_applies_to_methods_without_the_shader_test(dense_spot):
    """object-space selects the sequential point tree's cut on the CPU and still covers."""
    cam = frame(dense_spot.center, dense_spot.bounding_radius, size=(256, 256), zoom=4)
    ref = render(dense_spot, cam, "mesh", shading="lambert")
    result = render(dense_spot.with_(faces=None), cam, "object-space", shading="lambert", lod_error=1.0)
    assert result.stats["splats"] < 0.3 * len(dense_spot)
    assert compare_results(ref, result)["holes"] <= 0.001
