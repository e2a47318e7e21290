"""RenderResult.from_samples: its compiled box filter (one sample a pixel too) against the same
filter in numpy."""

import numpy as np
import pytest

from surfel.options import RenderOptions
from surfel.result import RenderResult


def numpy_box_filter(shaded, coverage, depth, normals, s, background):
    """The output buffers of docs/conventions.md from s x s samples a pixel, by block means."""
    h, w = coverage.shape[0] // s, coverage.shape[1] // s

    def blocks(a):
        return a.reshape(h, s, w, s, *a.shape[2:]).astype(np.float64)

    cov = np.clip(coverage, 0, 1)
    alpha = blocks(cov).mean(axis=(1, 3))
    color = np.clip(blocks(shaded * cov[..., None]).mean(axis=(1, 3)) + (1 - alpha[..., None]) * background, 0, 1)
    nearest = blocks(np.where(cov > 0, depth, np.inf)).min(axis=(1, 3))
    total = blocks(normals * cov[..., None]).sum(axis=(1, 3))
    length = np.linalg.norm(total, axis=-1, keepdims=True)
    return color, alpha, nearest, np.where(length > 1e-12, total / np.maximum(length, 1e-12), 0)


@pytest.mark.parametrize("s", [1, 2, 3])
def test_the_box_filter_matches_block_means(s):
    """Coverage outside [0, 1] is clamped, empty samples (depth inf) give nothing, a pixel with
    no sample covered keeps the background, depth inf and a zero normal."""
    rng = np.random.default_rng(s)
    h, w = 7 * s, 5 * s
    coverage = rng.uniform(-0.3, 1.3, (h, w)).astype(np.float32)
    coverage[:s, :s] = 0  # one output pixel wholly empty
    depth = np.where(coverage > 0, rng.uniform(1, 5, (h, w)), np.inf)
    shaded = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    normals = rng.normal(size=(h, w, 3))
    background = (0.2, 0.4, 0.9)
    result = RenderResult.from_samples(shaded, coverage, depth, normals, supersample=s,
                                       options=RenderOptions(background=background), stats={})
    expected = numpy_box_filter(shaded, coverage, depth, normals, s, np.asarray(background))
    for name, got, want in zip(("color", "alpha", "depth", "normals"),
                               (result.color, result.alpha, result.depth, result.normals), expected, strict=True):
        assert got.dtype == np.float32 and got.shape == want.shape, name
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6, err_msg=name)
    assert result.alpha[0, 0] == 0 and np.isinf(result.depth[0, 0]) and not result.normals[0, 0].any()
    assert np.allclose(result.color[0, 0], background)
