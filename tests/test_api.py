"""The Python API as a notebook user meets it, adapters, and the turntable."""

import os
import subprocess
import sys

import numpy as np
import pytest

import surfel
from conftest import requires_gl
from models import SPOT
from surfel.adapters import from_numpy, from_trimesh, to_numpy, to_trimesh


@requires_gl
def test_render_returns_a_result_that_shows_itself_as_png():
    result = surfel.render(surfel.load(SPOT), method="deferred", size=(128, 128))
    png = result._repr_png_()
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    assert result.color.shape == (128, 128, 3) and 0.1 < result.alpha.mean() < 0.6


def test_numpy_round_trip():
    rng = np.random.default_rng(0)
    cloud = from_numpy(rng.normal(size=(50, 3)), colors=rng.integers(0, 256, (50, 3)).astype(np.uint8))
    arrays = to_numpy(cloud)
    assert np.array_equal(arrays["positions"], cloud.positions) and arrays["colors"].max() <= 1


def test_trimesh_round_trip_keeps_the_mesh():
    cloud = surfel.load(SPOT)
    back = from_trimesh(to_trimesh(cloud))
    assert back.is_mesh and len(back) == len(cloud)
    assert np.allclose(back.positions, cloud.positions)
    assert np.einsum("ij,ij->i", back.normals, cloud.normals).min() > 0.999


def test_open3d_adapter_is_optional():
    pytest.importorskip("open3d")
    cloud = surfel.load(SPOT)
    from surfel.adapters import from_open3d, to_open3d

    assert np.allclose(from_open3d(to_open3d(cloud)).positions, cloud.positions)


@requires_gl
def test_turntable_gif_has_the_frames(tmp_path):
    from PIL import Image

    from surfel.turntable import turntable

    out = tmp_path / "t.gif"
    turntable(surfel.load(SPOT), out, frames=12, size=(64, 64), progress=False)
    assert Image.open(out).n_frames == 12


def test_pyvista_adapter_is_optional():
    pytest.importorskip("pyvista")
    from surfel.adapters import from_pyvista, to_pyvista

    cloud = surfel.load(SPOT)
    back = from_pyvista(to_pyvista(cloud))
    assert back.is_mesh and np.allclose(back.positions, cloud.positions)


def test_derived_clouds_check_new_values_but_not_kept_ones(monkeypatch):
    """with_ and take check the values they bring (a NaN radius, a wrong shape, a NaN
    attribute are refused) and only the shapes of the arrays kept or picked from a valid
    cloud: no finite check runs over those again."""
    from surfel.errors import InputError

    rng = np.random.default_rng(2)
    n = 1_000
    cloud = surfel.PointCloud(rng.normal(size=(n, 3)), normals=np.tile([0.0, 0, 1], (n, 1)), radii=np.full(n, 0.1),
                              attributes={"phong_alpha": rng.random(n)})
    bad = np.full(n, 0.1)
    bad[7] = np.nan
    for changes in ({"radii": bad}, {"radii": -bad}, {"normals": np.ones((n, 2))},
                    {"attributes": {**cloud.attributes, "phong_beta": bad}}):
        with pytest.raises(InputError):
            cloud.with_(**changes)
    checked = []
    real = np.isfinite

    def counting(values, *args, **kwargs):
        checked.append(np.shape(values))
        return real(values, *args, **kwargs)

    monkeypatch.setattr(np, "isfinite", counting)
    assert np.array_equal(cloud.with_(radii=np.full(n, 0.2)).radii, np.full(n, 0.2, np.float32))
    assert checked == [(n,)]  # the new radii only
    checked.clear()
    taken = cloud.take(slice(10, 20))
    assert checked == [] and len(taken) == 10
    np.testing.assert_array_equal(taken.attributes["phong_alpha"], cloud.attributes["phong_alpha"][10:20])
    with pytest.raises(InputError):
        cloud.take(slice(0, 10)).with_(radii=np.zeros(10))


def test_colours_in_eight_bits_are_taken_as_0_to_255():
    """uint8 colours (trimesh's vertex colours, an image's pixels) are divided by 255; float
    colours outside [0, 1], and wider integers, are refused in one line that says both forms."""
    from surfel.errors import InputError

    eight = np.array([[0, 128, 255], [255, 0, 51]], np.uint8)
    cloud = surfel.PointCloud(np.eye(2, 3), colors=eight)
    np.testing.assert_allclose(cloud.colors, eight / 255.0, atol=1e-7)
    assert cloud.colors.dtype == np.float32
    for wrong in (eight.astype(np.float32), eight.astype(np.uint16)):
        with pytest.raises(InputError, match=r"colors must lie in \[0, 1\] \(or be uint8, 0 to 255\)"):
            surfel.PointCloud(np.eye(2, 3), colors=wrong)


def test_take_keeps_every_per_point_attribute():
    rng = np.random.default_rng(1)
    n = 20
    axes = np.zeros((n, 2, 3), np.float32)
    axes[:, 0, 0] = axes[:, 1, 1] = 0.1
    cloud = surfel.PointCloud(rng.normal(size=(n, 3)), normals=np.tile([0.0, 0, 1], (n, 1)), colors=rng.random((n, 3)),
                              radii=np.full(n, 0.1), axes=axes, attributes={"clip_lines": rng.random((n, 2, 3)),
                                                                       "phong_alpha": rng.random(n)},
                              faces=np.array([[0, 1, 2]]))
    index = np.array([5, 0, 19])
    taken = cloud.take(index)
    assert len(taken) == 3 and taken.faces is None
    np.testing.assert_array_equal(taken.positions, cloud.positions[index])
    np.testing.assert_array_equal(taken.colors, cloud.colors[index])
    np.testing.assert_array_equal(taken.attributes["clip_lines"], cloud.attributes["clip_lines"][index])
    np.testing.assert_array_equal(taken.attributes["phong_alpha"], cloud.attributes["phong_alpha"][index])


@pytest.mark.parametrize("index", [np.array([5, 0, 19, -1]), [3, 3, 7], np.uint32([2, 1]), slice(4, 9),
                                   np.arange(20) % 3 == 0, [True] * 10 + [False] * 10])
def test_take_picks_what_numpy_indexing_picks(index):
    """take gathers integer rows with np.take (faster than fancy indexing): the same rows as
    numpy's indexing for every kind of index it accepts."""
    rng = np.random.default_rng(2)
    cloud = surfel.PointCloud(rng.normal(size=(20, 3)), normals=np.tile([0.0, 0, 1], (20, 1)),
                              attributes={"clip_lines": rng.random((20, 2, 3)), "intensity": rng.random(20)})
    taken = cloud.take(index)
    np.testing.assert_array_equal(taken.positions, cloud.positions[index])
    np.testing.assert_array_equal(taken.normals, cloud.normals[index])
    np.testing.assert_array_equal(taken.attributes["clip_lines"], cloud.attributes["clip_lines"][index])
    np.testing.assert_array_equal(taken.attributes["intensity"], cloud.attributes["intensity"][index])


def test_adapters_come_with_the_package():
    """The README's `surfel.adapters` works after `import surfel` alone (a fresh interpreter:
    in this one another test may have imported the module already)."""
    code = ("import numpy as np, surfel\n"
            "back = surfel.adapters.from_numpy(**surfel.adapters.to_numpy(surfel.PointCloud(np.eye(3))))\n"
            "print(len(back))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stdout.strip() == "3", proc.stderr


def test_show_without_a_display_says_so_and_returns_the_image():
    """Outside a notebook on a machine without a display, `show` warns in one line and returns
    the render, instead of running an image viewer that cannot open."""
    code = ("import numpy as np, surfel\n"
            "r = surfel.show(surfel.PointCloud(np.random.default_rng(0).normal(size=(200, 3))), size=(32, 32))\n"
            "print(type(r).__name__, r.color.shape)")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert proc.returncode == 0 and proc.stdout.strip() == "RenderResult (32, 32, 3)", proc.stderr
    assert "no display" in proc.stderr and "xdg-open" not in proc.stderr


def test_api_misuse_is_one_clear_error(tmp_path):
    """A size that is no pair of whole numbers, a camera that is no Camera, and a save whose
    last file cannot be written: each refused by name, and the save writes none of its files."""
    from surfel.errors import SurfelError

    cloud = surfel.PointCloud(np.random.default_rng(0).normal(size=(300, 3)))
    for size in ("64x64", (64.5, 64), (64,)):
        with pytest.raises(SurfelError, match=r"image size must be two whole numbers \(width, height\)"):
            surfel.render(cloud, size=size)
    assert surfel.render(cloud, size=(np.int64(16), 16.0)).color.shape == (16, 16, 3)
    with pytest.raises(TypeError, match="camera must be a surfel Camera"):
        surfel.render(cloud, camera="front")
    result = surfel.render(cloud, size=(16, 16))
    with pytest.raises(SurfelError, match="no such directory"):
        result.save(tmp_path / "x.png", depth=tmp_path / "missing" / "d.npy")
    assert not (tmp_path / "x.png").exists()
