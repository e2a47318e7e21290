"""Object-space EWA splatting (Ren et al. 2002): the rendered surface against the mesh."""

import pytest

from conftest import requires_gl
from surfel.camera import frame
from surfel.metrics import compare_results
from surfel.rendering import render


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
