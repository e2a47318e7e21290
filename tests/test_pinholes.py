"""surfel.pinholes on sample buffers made by hand: which samples it fills and with what, and
what it must leave alone (slopes, a valley seen along its line, outlines, float rounding)."""

import numpy as np

from surfel.pinholes import fill_pinholes

H = W = 12


def plane(slope_x=0.01, slope_y=0.02, base=3.0):
    """Buffers of a covered, tilted plane: colour varying over the image, normals +z."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    depth = (base + slope_x * x + slope_y * y).astype(np.float32)
    shaded = np.stack([x / W, y / H, np.full_like(x, 0.5)], axis=-1).astype(np.float32)
    coverage = np.ones((H, W), np.float32)
    normals = np.zeros((H, W, 3), np.float32)
    normals[..., 2] = 1
    return shaded, coverage, depth, normals


def neighbours(a, y, x):
    return np.concatenate([a[y - 1, x - 1:x + 2], a[y, [x - 1, x + 1]], a[y + 1, x - 1:x + 2]])


def test_a_sample_showing_the_far_side_takes_its_neighbours_surface():
    shaded, coverage, depth, normals = plane()
    expected_color = neighbours(shaded, 5, 6).mean(axis=0)
    expected_depth = neighbours(depth, 5, 6).mean()
    depth[5, 6] += 0.5  # the far side of the object, seen through a gap between splats
    shaded[5, 6] = 0.1
    normals[5, 6] = (0, 0, -1)
    shaded, coverage, depth, normals, _, filled = fill_pinholes(shaded, coverage, depth, normals)
    assert filled == 1
    np.testing.assert_allclose(shaded[5, 6], expected_color, rtol=1e-6)
    np.testing.assert_allclose(depth[5, 6], expected_depth, rtol=1e-6)
    np.testing.assert_allclose(normals[5, 6], (0, 0, 1))


def test_an_uncovered_sample_inside_the_surface_is_covered():
    shaded, coverage, depth, normals = plane()
    coverage[4, 4] = 0
    coverage[3, 3] = 0.5  # a neighbour partly covered: the filled coverage is the mean
    shaded, coverage, depth, normals, _, filled = fill_pinholes(shaded, coverage, depth, normals)
    assert filled == 1
    assert np.isclose(coverage[4, 4], 7.5 / 8)
    assert np.isfinite(depth[4, 4])


def test_a_pinhole_of_two_samples_is_filled_in_two_rounds():
    shaded, coverage, depth, normals = plane()
    depth[5, 5] += 0.5
    depth[5, 6] += 0.6
    _, _, depth, _, _, filled = fill_pinholes(shaded, coverage, depth, normals)
    assert filled == 2
    assert depth[5, 5] < 3.3 and depth[5, 6] < 3.3


def test_the_second_round_fills_a_sample_with_seven_neighbours_in_front():
    """Three samples deepening along a row: the first is a pinhole (its deeper neighbour the
    only one behind it); the second has the first in front, too far for its spread, until the
    first is filled; then it has seven neighbours in front, the third behind."""
    shaded, coverage, depth, normals = plane()
    base = depth.copy()
    depth[5, 5] += 0.5
    depth[5, 6] += 0.6
    depth[5, 7] += 0.7
    _, _, depth, _, _, filled = fill_pinholes(shaded, coverage, depth, normals)
    assert filled == 2
    assert depth[5, 5] < 3.3 and depth[5, 6] < 3.3
    assert depth[5, 7] == np.float32(base[5, 7] + 0.7)  # a third round's


def test_a_hole_of_a_pixel_in_a_supersampled_render_is_filled_and_a_groove_is_not():
    """2 x 2 samples a pixel: a hole of 2 x 2 samples has no sample that 7 neighbours
    surround, so only the samples a pixel apart find it; a groove two samples wide, seen along
    its line, is left alone at either step."""
    shaded, coverage, depth, normals = plane()
    expected = depth.copy()
    depth[4:6, 6:8] += 0.5
    assert fill_pinholes(*(a.copy() for a in (shaded, coverage, depth, normals)))[5] == 0
    _, _, filled_depth, _, _, filled = fill_pinholes(shaded, coverage, depth, normals, pixel=2)
    assert filled == 4
    np.testing.assert_allclose(filled_depth[4:6, 6:8], expected[4:6, 6:8], rtol=1e-6)
    shaded, coverage, depth, normals = plane(slope_x=0, slope_y=0)
    depth[5:7, :] += 0.4
    before = depth.copy()
    _, _, depth, _, _, filled = fill_pinholes(shaded, coverage, depth, normals, pixel=2)
    assert filled == 0 and np.array_equal(depth, before)


def unchanged(shaded, coverage, depth, normals) -> bool:
    before = [a.copy() for a in (shaded, coverage, depth, normals)]
    *after, _, filled = fill_pinholes(shaded, coverage, depth, normals)
    return filled == 0 and all(np.array_equal(a, b) for a, b in zip(after, before, strict=True))


def test_slopes_grooves_outlines_and_rounding_are_left_alone():
    assert unchanged(*plane(slope_x=0.3, slope_y=-0.2))  # steep: neighbours far in front and far behind
    shaded, coverage, depth, normals = plane(slope_x=0, slope_y=0)
    depth[6, :] += 0.4  # a groove one sample wide: the two along it are no nearer than each of its samples
    assert unchanged(shaded, coverage, depth, normals)
    shaded, coverage, depth, normals = plane(slope_x=0, slope_y=0)
    coverage[:, 9:] = 0  # an outline: the background beyond it
    coverage[:5, 8] = 0  # with a step in it
    assert unchanged(shaded, coverage, depth, normals)
    shaded, coverage, depth, normals = plane(slope_x=0, slope_y=0)
    depth[2, 2] += 4e-6  # float rounding of a plane facing the view
    assert unchanged(shaded, coverage, depth, normals)


def test_a_categorical_pinhole_copies_the_commonest_category_and_never_blends():
    shaded, coverage, depth, normals = plane()
    indices = np.full((H, W), 2, np.int32)
    indices[4:7, 7] = 5  # three of the eight neighbours in category 5, five in category 2
    shaded[indices == 5] = (1.0, 0.0, 0.0)
    shaded[indices == 2] = (0.0, 0.0, 1.0)
    depth[5, 6] += 0.5
    indices[5, 6] = 9
    shaded, _, depth, _, indices, filled = fill_pinholes(shaded, coverage, depth, normals, indices)
    assert filled == 1
    assert indices[5, 6] == 2
    np.testing.assert_array_equal(shaded[5, 6], (0.0, 0.0, 1.0))
    assert depth[5, 6] in neighbours(depth, 5, 6)


def reference_fill(shaded, coverage, depth, normals, rounds=2):
    """The module docstring's rule in numpy, every sample tested in every round."""
    shaded, coverage, depth, normals = (a.astype(np.float64) for a in (shaded, coverage, depth, normals))
    filled = 0
    offsets = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
    for _ in range(rounds):
        z = np.where(coverage > 0, depth, np.inf)
        inner = (slice(1, -1), slice(1, -1))
        around = np.stack([z[1 + dy:H - 1 + dy, 1 + dx:W - 1 + dx] for dy, dx in offsets])
        front = around < z[inner]
        near = np.where(front, around, np.inf).min(axis=0)
        far = np.where(front, around, -np.inf).max(axis=0)
        hole = (front.sum(axis=0) >= 7) & (z[inner] - far > (far - near) + 1e-5 * np.abs(far))
        if not hole.any():
            break
        filled += int(hole.sum())
        values = []
        for a in (shaded, coverage[..., None], depth[..., None], normals):
            stacked = np.stack([a[1 + dy:H - 1 + dy, 1 + dx:W - 1 + dx] for dy, dx in offsets])
            values.append((stacked * front[..., None]).sum(axis=0) / front.sum(axis=0)[..., None])
        values[3] /= np.linalg.norm(values[3], axis=-1, keepdims=True)
        for a, v in zip((shaded, coverage[..., None], depth[..., None], normals), values, strict=True):
            a[inner][hole] = v[hole]
    return shaded, coverage, depth, normals, filled


def test_every_round_finds_what_testing_every_sample_finds():
    """Rounds after the first test only the samples next to those just filled: on a rough
    surface full of pinholes, single and clustered, that finds what testing every sample finds."""
    rng = np.random.default_rng(7)
    shaded, coverage, depth, normals = plane(slope_x=0.002, slope_y=0.001)
    depth += rng.normal(0, 1e-4, depth.shape).astype(np.float32)
    holes = rng.random((H, W)) < 0.12
    depth[holes] += rng.uniform(0.2, 0.6, holes.sum()).astype(np.float32)
    coverage[rng.random((H, W)) < 0.03] = 0
    normals += rng.normal(0, 0.1, normals.shape).astype(np.float32)
    expected = reference_fill(shaded, coverage, depth, normals)
    *got, _, filled = fill_pinholes(shaded.copy(), coverage.copy(), depth.copy(), normals.copy())
    assert filled == expected[-1] > 4
    for a, b in zip(got, expected[:-1], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
