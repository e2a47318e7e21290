"""The CPU backends of gaussian, deferred and phong (methods/splatting_cpu.py) against their GL
programs (splatting.glsl), and how `--backend auto` chooses between them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import surfel
from conftest import requires_gl
from scenes import sheet_on_body, sheet_over_body
from surfel.camera import frame
from surfel.io import load
from surfel.metrics import compare_results
from surfel.preprocess import prepare
from surfel.rendering import Renderer, choose_backend, is_software_renderer
from surfel.request import CameraSpec

pytestmark = requires_gl

DATA = Path(__file__).parent / "data"
METHODS = ("gaussian", "deferred", "phong")
MIN_PSNR = 40.0  # dB between the two backends' images
# A LiDAR tile's tree crowns: phong's curved splats of noisy normal fields, whose ray-surface
# roots are ill-conditioned there, differ at isolated pixels (0.3% by more than 5%).
MIN_PSNR_LIDAR = 38.0
SIZE = (192, 192)


def both(cloud, camera, method, **options):
    """The CPU and GL renders of one view, through one Renderer (as bench and the viewer do)."""
    renderer = Renderer()
    return (renderer.render(cloud, camera, method, backend="cpu", **options),
            renderer.render(cloud, camera, method, backend="gl", **options))


def assert_agree(cpu, gl, least=MIN_PSNR, covered=0.05):
    """The same picture: PSNR, and the same pixels covered (alpha within a few levels)."""
    metrics = compare_results(cpu, gl)
    assert metrics["psnr"] >= least, metrics
    assert gl.alpha.sum() > covered * gl.alpha.size  # the model is there
    assert np.abs(cpu.alpha - gl.alpha).mean() < 0.004
    assert ((cpu.alpha > 0) != (gl.alpha > 0)).mean() < 0.002


@pytest.fixture(scope="module")
def autzen():
    """A corner of the Autzen tile (RGB, intensity, classes 1 and 2), as test_colors uses it."""
    cloud = load(DATA / "autzen_trim.laz")
    lo = cloud.bounds[0]
    return cloud.take((cloud.positions[:, 0] < lo[0] + 300) & (cloud.positions[:, 1] > lo[1] + 150))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("view,shading", [("front", "lambert"), ("right", "phong")])
def test_cpu_matches_gl_on_dense_spot(dense_spot, method, view, shading):
    camera = frame(dense_spot.center, dense_spot.bounding_radius, view=view, size=SIZE)
    assert_agree(*both(dense_spot, camera, method, shading=shading))


@pytest.mark.parametrize("method", METHODS)
def test_the_far_side_of_a_closed_surface_is_passed_by_and_the_picture_kept(method):
    """A tile draws the splats facing the camera first and passes by those behind them that
    could change no pixel (splatting_kernels._hidden): on a sphere seen from outside, more than
    half of the far half, whatever the method, and the picture stays the GL program's, which
    draws every splat."""
    from models import unit_sphere

    sphere = unit_sphere()
    for view in ("front", "iso"):
        camera = frame(sphere.center, sphere.bounding_radius, view=view, size=SIZE)
        cpu, gl = both(sphere, camera, method, shading="lambert")
        assert cpu.stats["hidden_in_tiles"] > 0.25 * len(sphere)  # of about half facing away
        assert_agree(cpu, gl)


def test_a_splat_is_hidden_only_where_it_can_change_no_pixel():
    """splatting_kernels._hidden on a 2x2 box: every pixel in front of the splat's nearest
    depth, with a coverage of 1, or of at least a half with its four neighbours' too (the
    pixel is whole whatever the splat adds); never at the tile's edge with less than 1."""
    from surfel.methods.splatting_kernels import _hidden
    from surfel.methods.splatting_tiles import STRIDE

    def hidden(x, y, nearest=2.0, changes=()):
        zb, cov = np.ones(STRIDE * STRIDE, np.float32), np.ones(STRIDE * STRIDE, np.float32)
        for (px, py), depth, coverage in changes:
            zb[py * STRIDE + px], cov[py * STRIDE + px] = depth, coverage
        box = np.array([[x], [x + 1], [y], [y + 1]], np.int32)
        return _hidden(box, 0, 0, 0, 32, 32, np.float32(nearest), zb, cov)

    assert hidden(10, 20)
    assert not hidden(10, 20, 1.0)  # the splat's fragments may reach the visible depth
    assert not hidden(10, 20, changes=[((11, 21), 2.0, 1.0)])
    assert hidden(10, 20, changes=[((11, 21), 1.0, 0.7)])  # surrounded: whole whatever it adds
    assert not hidden(10, 20, changes=[((11, 21), 1.0, 0.7), ((12, 21), 1.0, 0.4)])
    assert not hidden(10, 20, changes=[((10, 20), 1.0, 0.4)])  # it could make the pixel covered
    assert hidden(30, 20) and not hidden(30, 20, changes=[((31, 20), 1.0, 0.9)])  # a neighbour in another tile
    assert hidden(30, 20, changes=[((31, 20), 1.0, 1.0), ((30, 21), 1.0, 0.9)])


@pytest.mark.parametrize("method", METHODS)
def test_large_splats_match_gl(method):
    """Spot's 2,930 vertices at 192x192: boxes of 4-5 samples across (median; 8-10 at phong's
    2x2 samples a pixel), whose samples beyond each top-left 2x2 make 2,351-4,252 further 2x2
    blocks in the busiest tile, drawn in rounds of SPLIT_BLOCKS (splatting_tiles.visible_splats):
    more than one round in nearly every tile."""
    from surfel.methods.splatting_tiles import SPLIT_BLOCKS

    assert SPLIT_BLOCKS < 2351
    mesh = load(DATA / "spot.obj")
    cloud = mesh.take(np.arange(len(mesh)))
    for view in ("front", "right"):
        camera = frame(cloud.center, cloud.bounding_radius, view=view, size=SIZE)
        assert_agree(*both(cloud, camera, method, shading="lambert"))


@pytest.mark.parametrize("method", METHODS)
def test_rows_the_same_for_every_splat_are_written_once_and_draw_the_same(dense_spot, method):
    """Packed rows that every splat shares (here green and blue, and the layers' thickness)
    are written into each thread's table once instead of being staged for every tile
    (splatting_cpu.CpuSplatBuffers): the picture is the GL program's, in those colours."""
    red = np.random.default_rng(2).random(len(dense_spot))
    colors = np.column_stack([red, np.full_like(red, 0.5), np.full_like(red, 0.9)]).astype(np.float32)
    cloud = dense_spot.with_(colors=colors)
    camera = frame(cloud.center, cloud.bounding_radius, view="front", size=SIZE)
    cpu, gl = both(cloud, camera, method, shading="none")
    assert_agree(cpu, gl)
    inside = cpu.alpha > 0.99
    np.testing.assert_allclose(cpu.color[inside][:, 1:], np.broadcast_to((0.5, 0.9), (inside.sum(), 2)), atol=0.01)


@pytest.mark.parametrize("method", ["deferred", "phong"])
def test_clip_lines_and_normal_fields_match_gl(turned_part, method):
    """A CAD part: splats cut at its creases, and phong's curved splats with normal fields."""
    from surfel.preprocess import complete

    cloud = complete(turned_part.with_(faces=None), normal_field=True)[0]
    assert (cloud.attributes["clip_lines"][:, 0, 2] < 1).mean() > 0.1
    for view in ("front", "right"):
        camera = frame(cloud.center, cloud.bounding_radius, view=view, size=SIZE)
        assert_agree(*both(cloud, camera, method, shading="lambert"))


@pytest.mark.parametrize("method", METHODS)
def test_orthographic_supersampled_and_culled_match_gl(dense_spot, method):
    camera = frame(dense_spot.center, dense_spot.bounding_radius, view="right", size=(128, 128),
                   ortho_height=2.2 * dense_spot.bounding_radius)
    cpu, gl = both(dense_spot, camera, method, shading="lambert", supersample=2, backface_culling=True)
    assert cpu.color.shape == (128, 128, 3)
    assert_agree(cpu, gl)


@pytest.mark.parametrize("method", METHODS)
def test_screen_facing_splats_match_gl(method):
    """Splats without orientation (preprocess.drawn_normals) face the camera on both backends."""
    from test_lidar import facing_cloud

    cloud = facing_cloud()
    for view in ("front", "top"):
        camera = frame(cloud.center, cloud.bounding_radius, view=view, size=(128, 128))  # perspective
        assert_agree(*both(cloud, camera, method, shading="lambert"), covered=0.01)  # eight small disks


def test_a_first_frame_with_every_splat_off_screen_is_empty(dense_spot):
    """A camera path can start with the cloud out of view: that frame leaves every tile empty,
    and the next, looking at the cloud, draws it as a fresh renderer would (the per-thread
    tables are made on the first frame whatever it holds)."""
    renderer = Renderer()
    camera = frame(dense_spot.center, dense_spot.bounding_radius, size=SIZE)
    away = frame(dense_spot.center + 10 * dense_spot.bounding_radius, dense_spot.bounding_radius, size=SIZE)
    for method in METHODS:
        empty = renderer.render(dense_spot, away, method, backend="cpu", shading="lambert")
        assert empty.alpha.max() == 0.0
        seen = renderer.render(dense_spot, camera, method, backend="cpu", shading="lambert")
        assert compare_results(seen, Renderer().render(dense_spot, camera, method, backend="cpu",
                                                       shading="lambert"))["psnr"] == float("inf")


@pytest.mark.parametrize("method", ["deferred", "phong"])
def test_an_edge_on_splat_with_the_low_pass_leaves_finite_pixels(method):
    """A flat cut-out's splat seen almost exactly edge-on (a cartoon figure's vertices, the eye
    in its plane) reaches two pixels only through the EWA low-pass, with weights of ~1e-20.
    The normal sums there square to subnormals, whose fastmath reciprocal square root is
    infinite: those pixels came out NaN (splatting_kernels._normalize)."""
    normals = np.array([[0.0, 0.0, 1.0]])
    axes = np.array([[[1.1249783, -9.688645, 0.0], [7.1429625, 0.82939124, 0.0]]])
    cloud = surfel.PointCloud(np.array([[167.605051, 374.166324, 0.0]]), normals=normals,
                              radii=np.linalg.norm(axes, axis=2).max(1), axes=axes)
    camera = frame(np.array([174.5, 201.5, 0.0]), 266.60832695172894, azimuth=270.0, elevation=-20.0,
                   size=(512, 512))
    result = Renderer().render(cloud, camera, method, backend="cpu", shading="lambert", ewa_filter=True,
                               supersample=1)
    assert np.isfinite(result.color).all() and np.isfinite(result.alpha).all()
    assert result.alpha.max() < 0.5  # edge-on: no pixel covered


def test_level_of_detail_matches_gl(dense_spot):
    """--lod-error: the CPU draws the cut the Renderer selects, GL the one its vertex stage keeps."""
    camera = frame(dense_spot.center, dense_spot.bounding_radius, size=SIZE)
    cpu, gl = both(dense_spot, camera, "deferred", shading="lambert", lod_error=1.0)
    assert cpu.stats["splats"] == gl.stats["splats"] < len(dense_spot)
    assert_agree(cpu, gl)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("color,shading", [("elevation", "lambert"), ("intensity", "phong"),
                                           ("classification", "lambert"), ("rgb", "edl")])
def test_colour_modes_and_eye_dome_lighting_match_gl(autzen, method, color, shading):
    """Continuous attributes splatted like colour and mapped per pixel (per splat for
    gaussian), categories the heaviest splat's, eye-dome lighting on the samples."""
    camera = CameraSpec(size=(160, 160), view="iso").camera(autzen)
    cpu, gl = both(autzen, camera, method, color=color, shading=shading)
    assert_agree(cpu, gl, MIN_PSNR_LIDAR)
    assert cpu.stats["color"] == color and cpu.stats["backend"] == "cpu"


def test_categories_are_never_blended_on_the_cpu():
    """Two interleaved classes, a palette entry each: every covered pixel shows one of the two
    entries exactly, supersampled or not, and both show, in the same places as on the GPU."""
    from surfel.cloud import PointCloud
    from surfel.colors import palette

    g = np.arange(-1, 1, 0.02)
    x, y = np.meshgrid(g, g)
    positions = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    classes = ((np.floor(x * 4) + np.floor(y * 4)) % 2).astype(np.uint8).ravel() + 2  # a checkerboard
    cloud = PointCloud(positions, normals=np.tile([0.0, 0.0, 1.0], (len(positions), 1)),
                       attributes={"classification": classes})
    entries = np.round(palette("classification", np.array([2, 3])) * 255).astype(int)
    camera = frame(cloud.center, cloud.bounding_radius, view="front", size=(96, 96))
    for method in METHODS:
        for supersample in (None, 3):
            cpu, gl = both(cloud, camera, method, color="classification", shading="none", supersample=supersample)
            rgba = cpu.rgba8().astype(int)
            full = rgba[..., 3] == 255
            assert full.mean() > 0.3
            distance = np.abs(rgba[full][:, None, :3] - entries[None]).max(axis=2)
            assert (distance.min(axis=1) <= 1).all(), (method, supersample)
            shown = distance.argmin(axis=1)
            assert 0.3 < shown.mean() < 0.7
            gl_shown = np.abs(gl.rgba8().astype(int)[full][:, None, :3] - entries[None]).max(axis=2).argmin(axis=1)
            assert (shown == gl_shown).mean() > 0.99


def test_auto_picks_the_cpu_over_a_software_rasterizer_and_reports_it(dense_spot):
    from surfel.gl.context import renderer_string

    software = is_software_renderer(renderer_string())
    backend, why = choose_backend("deferred", None)
    assert backend == ("cpu" if software else "gl") and why.startswith("auto")
    assert choose_backend("points", None)[0] == "gl"  # no CPU backend
    assert choose_backend("deferred", "gl") == ("gl", "asked")
    assert choose_backend("deferred", None, dump_passes=True)[0] == "gl"  # only GL writes its passes
    assert is_software_renderer("llvmpipe (LLVM 15.0.6, 256 bits)")
    assert not is_software_renderer("NVIDIA GeForce RTX 4090/PCIe/SSE2")
    camera = frame(dense_spot.center, dense_spot.bounding_radius, size=(64, 64))
    stats = surfel.render(dense_spot, camera, "phong", backend="auto").stats
    assert stats["backend"] == backend and stats["backend_choice"] == why


def test_backend_options_on_the_command_line(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "surfel.cli", "render", "--demo", "--size", "32x32", *args],
                              capture_output=True, text=True, timeout=600)

    out = tmp_path / "a.png"
    done = run("-o", out, "--backend", "auto", "--method", "gaussian")
    assert done.returncode == 0 and out.exists(), done.stderr
    bad = run("-o", tmp_path / "b.png", "--backend", "cpu", "--method", "deferred", "--dump-passes", tmp_path)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--dump-passes" in bad.stderr
    assert "cpu backend" in bad.stderr and not (tmp_path / "b.png").exists()
    bad = run("-o", tmp_path / "c.png", "--backend", "cpu", "--method", "points")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "no 'cpu' backend" in bad.stderr
    assert "Traceback" not in bad.stderr


def stacked_sheets(sheets: int = 10, side: int = 80, seed: int = 0):
    """Parallel square sheets one behind the other, each shifted sideways so that a strip of
    it shows: nine tenths of the splats hidden wholly, the rest partly, at every edge."""
    from surfel.cloud import PointCloud

    rng = np.random.default_rng(seed)
    g = (np.arange(side) + 0.5) / side * 2 - 1
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    palette = rng.uniform(0.1, 0.9, (sheets, 3))
    palette[0] = (0.9, 0.2, 0.1)
    positions, colors = [], []
    for k in range(sheets):
        jitter = rng.uniform(-0.3, 0.3, (len(x), 2)) * (2 / side)
        positions.append(np.c_[x + jitter[:, 0] + 0.12 * k, y + jitter[:, 1], np.full(len(x), -0.1 * k)])
        colors.append(np.tile(palette[k], (len(x), 1)))
    n = sheets * len(x)
    radius = np.full(n, 2.4 / side, np.float32)  # 1.2 spacings: no gaps, whatever the jitter
    axes = np.zeros((n, 2, 3), np.float32)
    axes[:, 0, 0] = axes[:, 1, 1] = radius
    return PointCloud(np.concatenate(positions), normals=np.tile([0, 0, 1.0], (n, 1)),
                      colors=np.concatenate(colors), radii=radius, axes=axes)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("ortho", [False, True])
def test_occlusion_culling_keeps_the_picture_of_stacked_sheets(method, ortho):
    """The GL attribute pass culls splats behind the visible surface by an early depth test
    (splatting.glsl nearest_depth): on a stack of sheets its picture is still the CPU
    backend's, which culls nothing, and the front sheet's colour fills its part."""
    from surfel.camera import Camera

    cloud = stacked_sheets()
    camera = Camera.look_at([0.4, 0.3, 4.0], [0.4, 0.0, -0.5], fov=40, size=SIZE,
                            ortho_height=2.8 if ortho else None).fit_clip_planes(cloud.center, cloud.bounding_radius)
    cpu, gl = both(cloud, camera, method, shading="lambert")
    assert_agree(cpu, gl)
    front = gl.color[80:112, 40:72]  # inside the front sheet, away from its edges
    assert (front[..., 0] > 3 * front[..., 1]).all()


@pytest.mark.parametrize("method", METHODS)
def test_a_sheet_on_a_body_leaves_no_holes_beside_its_rim(method):
    """A thin sheet lying on a body (ogre's belt): the body's splats beside the sheet's dense rim
    keep the size of their cells (preprocess/outlier_cap.py), so the body there has
    no holes, on either backend (the cap over all neighbours left 17% of it uncovered)."""
    from surfel.camera import Camera
    from surfel.cloud import PointCloud

    rng = np.random.default_rng(11)
    points, normals, body = sheet_on_body(rng)
    cloud = PointCloud(points, normals=normals)
    camera = Camera.look_at([0, -8, 30], [0, -1, 0], fov=30, size=SIZE).fit_clip_planes([0, 0, 0], 17)
    cpu, gl = both(cloud, camera, method, shading="lambert")
    assert_agree(cpu, gl)
    # from y = 0.6: nearer the rim the body has a crack (the dense rim's points, turned from the
    # body and lying on it, end the body's cells half-way to them), whose anti-aliased edge
    # reaches y = 0.5 (alpha 0.45 there at 2x2 samples, phong's default)
    beside = np.c_[rng.uniform(-6, 6, 20_000), rng.uniform(0.6, 3.0, 20_000), np.zeros(20_000)]
    column, row = np.floor(camera.project(beside)[0]).astype(int).T
    for result in (cpu, gl):
        assert (result.alpha[row, column] >= 0.5).all()


def _sheet_pixels(rng, camera, count=5_000):
    """Pixels (rows, columns) of the sheet of `scenes.sheet_over_body` well inside its edges."""
    inside = np.c_[rng.uniform(-15, 15, count), rng.uniform(-15, -2, count), np.full(count, 0.3)]
    column, row = np.floor(camera.project(inside)[0]).astype(int).T
    seen = (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height)
    return row[seen], column[seen]


@pytest.mark.parametrize("method", METHODS)
def test_a_sheet_close_above_a_body_hides_it(method):
    """A sheet 0.3 above a body, closer than their splats' radius (0.9), seen at 30 degrees:
    z_t capped by the layers' thickness (preprocess/thickness.py) keeps the body's colour out
    of the sheet on both backends; uncapped, the two blend about half and half."""
    rng = np.random.default_rng(5)
    cloud, _ = sheet_over_body(rng)
    camera = frame(cloud.center, 0.5 * cloud.bounding_radius, azimuth=0.0, elevation=30.0, size=SIZE)
    cpu, gl = both(cloud, camera, method, shading="none")
    assert_agree(cpu, gl)
    rows, columns = _sheet_pixels(rng, camera)
    assert len(rows) > 1_000
    for result in (cpu, gl):
        assert (result.color[rows, columns, 2] > 0.05).mean() < 0.005
    uncapped = prepare(cloud, elliptical=method == "phong", normal_field=True)[0]  # all a method needs
    uncapped = uncapped.with_(attributes={k: v for k, v in uncapped.attributes.items() if k != "thickness"})
    for backend in ("cpu", "gl"):
        result = Renderer().render(uncapped, camera, method, backend=backend, shading="none")
        assert result.color[rows, columns, 2].mean() > 0.3


@pytest.mark.parametrize(("method", "backend"), [("ewa", "cpu"), ("ewa", "gl"), ("object-space", "gl")])
def test_the_other_splat_methods_keep_a_close_sheet_in_front(method, backend):
    """The same cap in EWA splatting's threshold (its own depth range included) and in the
    object-space visibility pass: the body shows through the sheet at most faintly, at the
    low-pass fringes."""
    rng = np.random.default_rng(5)
    cloud, _ = sheet_over_body(rng)
    camera = frame(cloud.center, 0.5 * cloud.bounding_radius, azimuth=0.0, elevation=30.0, size=SIZE)
    result = Renderer().render(cloud, camera, method, backend=backend, shading="none")
    rows, columns = _sheet_pixels(rng, camera)
    assert result.color[rows, columns, 2].mean() < 0.05  # uncapped: 0.48


def _packed_float_ops(kernel, *args) -> int:
    """Packed (SIMD) float32 arithmetic instructions in a fresh, uncached compilation of a
    kernel for these arguments' types (cached code cannot be inspected)."""
    import re

    import numba

    fresh = numba.njit(fastmath=True, error_model="numpy")(kernel.py_func)
    fresh(*args)
    assembly = fresh.inspect_asm(fresh.signatures[0])
    return len(re.findall(r"\bv?(?:mul|add|sub|fmadd\d+|fnmadd\d+|fmsub\d+|div|sqrt)ps\b", assembly))


def test_the_hot_loops_compile_to_simd():
    """The per-block loops of the CPU splatting kernels are written for LLVM's loop vectorizer: a
    tuple indexed by a loop variable (a switch), a short loop inside them, a call, or stores
    into an array it cannot tell apart from the loads keep them scalar, at about half the
    speed. On every x86-64 the vector code uses packed float instructions."""
    from surfel.methods import splatting_bins as bins
    from surfel.methods import splatting_tiles as t

    count = t.BLOCK
    table = np.zeros(t.table_size(count), np.float32)
    boxes = np.zeros(4 * count, np.int32)
    scratch = [np.zeros(t.TEMP_ROWS * t.BLOCK, np.float32), np.zeros(t.table_size(count, t.KEPT_ROWS), np.float32),
               np.zeros(t.STRIDE ** 2, np.float32), np.zeros(t.STRIDE ** 2, np.float32)]
    params = (np.float32(1.0), np.float32(0.0), np.float32(32.0))
    extras = np.zeros((t.EXTRAS, count), np.float32)
    assert _packed_float_ops(t.visibility_tile, table, boxes, count, 0, 0, params, extras, extras, None,
                             *scratch) >= 32
    packed = np.zeros((t.PACKED, count), np.float32)
    camera = tuple(np.float32(v) for v in (1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, -5, 500, 500, 256, 256, 0, 0.1, 100))
    assert _packed_float_ops(bins.bound_block, packed, extras, camera, np.float32(1.0), np.float32(1.0), False,
                             np.float32(32.0), 512, 512, np.zeros(4 * bins.BOUND_BLOCK, np.int32),
                             np.zeros(count, np.float32), 0, count) >= 16


@pytest.mark.parametrize("threads", [1, 2, 3, 8])
def test_tiles_are_dealt_to_threads_in_equal_shares_of_work(threads):
    """numba splits a parallel loop into equal contiguous ranges, one a thread: the dealt
    order visits every tile once, pads with -1 to whole ranges, and gives each range work
    within one tile's cost of every other's (a screen-ordered split of this skewed screen
    gives one thread nearly all of it)."""
    from surfel.methods.ewa import TILE_PIXEL_COST, balanced_tile_order

    rng = np.random.default_rng(3)
    splats = np.zeros(32 * 32, np.int64)
    splats[:300] = rng.integers(0, 20000, 300)  # the object fills the top of the screen
    order = balanced_tile_order(splats, threads)
    assert len(order) % threads == 0
    assert np.array_equal(np.sort(order[order >= 0]), np.arange(len(splats)))
    cost = np.where(order >= 0, splats[np.maximum(order, 0)] + TILE_PIXEL_COST, 0)
    shares = cost.reshape(threads, -1).sum(axis=1)
    assert shares.max() - shares.min() <= splats.max() + TILE_PIXEL_COST
    if threads == 2:
        assert shares.max() / shares.sum() < 0.51
