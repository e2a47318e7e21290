"""Colour by attribute, eye-dome lighting, readable defaults and extent framing (issue 14's
appearance half), on real LiDAR tiles (tests/data: autzen_trim.laz, classified.laz) and
analytic scenes, through every method and the command line."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from scipy.stats import spearmanr

import surfel
from conftest import requires_gl
from surfel.camera import Camera, frame
from surfel.cloud import PointCloud
from surfel.colors import ASPRS_COLORS, NEUTRAL, colormap_table, palette, resolve
from surfel.edl import eye_dome_lighting
from surfel.errors import SurfelError
from surfel.io import load, write_ply
from surfel.options import RenderOptions
from surfel.request import CameraSpec
from surfel.result import RenderResult

DATA = Path(__file__).parent / "data"
SPLAT_METHODS = [("points", None), ("gaussian", "gl"), ("deferred", "gl"), ("phong", "gl"), ("object-space", None),
                 ("ewa", "gl"), ("ewa", "cpu"), ("gaussian", "cpu"), ("deferred", "cpu"), ("phong", "cpu")]
EVERY_METHOD = SPLAT_METHODS + [("mls-gpu", None), ("mls", None)]


def run(*args):
    return subprocess.run([sys.executable, "-m", "surfel.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def classified():
    """A real tile with six ASPRS classes (ground, three vegetation heights, buildings, noise)."""
    return load(DATA / "classified.laz")


@pytest.fixture(scope="module")
def autzen():
    """A corner of the Autzen tile (RGB, classes 1 and 2, up to four returns, trees over grass)."""
    cloud = load(DATA / "autzen_trim.laz")
    lo = cloud.bounds[0]
    return cloud.take((cloud.positions[:, 0] < lo[0] + 300) & (cloud.positions[:, 1] > lo[1] + 150))


def top_view(cloud, size=(200, 200)):
    return CameraSpec(size=size, view="top", ortho="auto").camera(cloud)


def foreign_fraction(rgba, colors) -> float:
    """The fraction of fully covered pixels whose colour is none of `colors` (0..1 floats)."""
    full = rgba[..., 3] == 255
    table = np.round(np.asarray(colors) * 255).astype(int)
    distance = np.abs(rgba[full][:, None, :3].astype(int) - table[None]).max(axis=2).min(axis=1)
    return float((distance > 1).mean())


@requires_gl
@pytest.mark.parametrize("method,backend", EVERY_METHOD)
def test_categories_are_never_blended(classified, method, backend):
    """--color classification --shading none: every fully covered pixel shows one class's
    colour, at the borders between classes too, supersampled or not."""
    camera = CameraSpec(size=(160, 160), view="iso").camera(classified)
    codes = np.unique(classified.attributes["classification"])
    for supersample in (None, 2) if method in ("deferred", "ewa") else (None,):
        result = surfel.render(classified, camera, method, backend=backend, color="classification",
                               shading="none", supersample=supersample)
        rgba = result.rgba8()
        assert (rgba[..., 3] == 255).sum() > 1000  # splats bounded by the sampling: the canopy's are dots
        assert foreign_fraction(rgba, palette("classification", codes)) == 0.0, (method, supersample)
        full = rgba[rgba[..., 3] == 255][:, :3]
        assert len(np.unique(full, axis=0)) >= 4  # ground, vegetation and buildings all show
        assert result.stats["categories"] == codes.tolist()


@requires_gl
def test_a_mesh_shows_its_vertices_categories_unblended():
    from surfel.data import demo_cloud

    spot = demo_cloud()
    part = (spot.positions[:, 1] > np.median(spot.positions[:, 1])).astype(np.uint8) + 3 * (spot.positions[:, 0] > 0)
    spot = spot.with_(attributes={**spot.attributes, "part": part})
    result = surfel.render(spot, frame(spot.center, spot.bounding_radius, size=(160, 160)), "mesh", color="part",
                           shading="none")
    assert result.stats["color"] == "part" and result.stats["categories"] == [0, 1, 3, 4]
    assert foreign_fraction(result.rgba8(), palette("part", np.array([0, 1, 3, 4]))) == 0.0


@requires_gl
@pytest.mark.parametrize("method,backend", [("deferred", None), ("points", None), ("ewa", "cpu"), ("mls-gpu", None)])
def test_elevation_read_back_through_the_colour_map_follows_the_surface(method, backend):
    """--color elevation --colormap viridis --shading none, top view of the whole tile, as judged:
    the elevation read back through the map ranks like the surface's, taken from the depth
    buffer (judged >= 0.95)."""
    tile = load(DATA / "autzen_trim.laz")
    camera = top_view(tile, (256, 256))
    result = surfel.render(tile, camera, method, backend=backend, color="elevation", colormap="viridis",
                           shading="none")
    lo, hi = result.stats["color_range"]
    z = tile.positions[:, 2]
    assert (lo, hi) == pytest.approx(tuple(np.percentile(z, [2, 98])))  # robust percentiles by default
    rgba = result.rgba8().astype(int)
    full = rgba[..., 3] == 255
    lut = np.round(colormap_table("viridis") * 255).astype(int)
    read_back = np.abs(rgba[full][:, None, :3] - lut[None]).sum(axis=2).argmin(axis=1)
    surface = camera.eye[2] - result.depth[full]  # looking straight down the +Z axis
    assert full.mean() > 0.15  # the tile fills half the image; EWA leaves soft edges
    assert spearmanr(read_back, surface).statistic >= 0.95


@requires_gl
@pytest.mark.parametrize("mode", ["elevation", "intensity", "classification"])
def test_the_cpu_and_gl_rasterizers_agree_in_every_colour_mode(autzen, mode):
    from surfel.metrics import compare_results

    camera = CameraSpec(size=(160, 160), view="iso").camera(autzen)
    cpu = surfel.render(autzen, camera, "ewa", backend="cpu", color=mode, shading="lambert")
    gl = surfel.render(autzen, camera, "ewa", backend="gl", color=mode, shading="lambert")
    assert compare_results(cpu, gl)["psnr"] >= 35.0
    assert cpu.stats["color"] == gl.stats["color"] == mode


def test_continuous_values_map_per_pixel_with_not_a_number_neutral():
    """Encoded (t, valid) colours decode to exact colour-map entries, and to NEUTRAL where no
    value was a number; blended half and half, halfway between."""
    values = np.array([0.0, 0.5, 1.0, np.nan])
    cloud = PointCloud(np.c_[np.arange(4.0), np.zeros((4, 2))], attributes={"h": values})
    coloring = resolve(cloud, "h", "viridis", (0.0, 1.0))
    encoded = coloring.encode(cloud)
    decoded = coloring.decode(encoded)
    lut = colormap_table("viridis")
    assert np.array_equal(decoded[:3], lut[[0, 128, 255]]) and np.allclose(decoded[3], NEUTRAL)
    half = coloring.decode((encoded[2] + encoded[3]) / 2)
    assert np.allclose(half, (np.asarray(NEUTRAL) + lut[255]) / 2, atol=1e-6)


def test_supersampled_pixels_take_one_category():
    """The box filter of categorical samples picks the category covering most of each pixel."""
    shaded = np.zeros((2, 2, 3), np.float32)
    shaded[0, 0] = shaded[0, 1] = shaded[1, 0] = (1, 0, 0)
    shaded[1, 1] = (0, 0, 1)
    indices = np.array([[0, 0], [0, 1]], np.int32)
    args = (shaded, np.ones((2, 2), np.float32), np.ones((2, 2), np.float32), np.zeros((2, 2, 3), np.float32))
    mixed = RenderResult.from_samples(*args, supersample=2, options=RenderOptions(), stats={})
    picked = RenderResult.from_samples(*args, supersample=2, options=RenderOptions(), stats={}, indices=indices)
    assert np.allclose(mixed.color[0, 0], (0.75, 0, 0.25)) and np.allclose(picked.color[0, 0], (1, 0, 0))


# ---- eye-dome lighting -------------------------------------------------------------------------------------


def plane_with_box(path, spacing=0.05):
    """A 10 x 10 plane with a 2 x 2 box 1 unit high on it, sampled every `spacing`, as PLY."""
    g = np.arange(0, 10 + spacing / 2, spacing)
    x, y = np.meshgrid(g, g)
    on_box = (np.abs(x - 5) <= 1) & (np.abs(y - 5) <= 1)
    points = [np.c_[x.ravel(), y.ravel(), np.where(on_box, 1.0, 0.0).ravel()]]
    side = np.arange(-1, 1 + spacing / 2, spacing)
    for height in np.arange(spacing, 1, spacing):
        for a, b in ((side, np.full_like(side, -1)), (side, np.full_like(side, 1))):
            points += [np.c_[5 + a, 5 + b, np.full_like(a, height)], np.c_[5 + b, 5 + a, np.full_like(a, height)]]
    write_ply(PointCloud(np.concatenate(points)), path)
    return path


@requires_gl
@pytest.mark.parametrize("flags", [["--method", "deferred"], ["--method", "deferred", "--supersample", "2"],
                                   ["--method", "points"], ["--method", "ewa", "--backend", "cpu"]])
def test_eye_dome_lighting_darkens_rings_around_a_raised_box(tmp_path, flags):
    """--shading edl, a plane with a raised box seen from above: the plane 1-2 and 3-5 pixels
    outside the box at most 0.7 times as bright as far from it, which stays at 85% or more."""
    cloud = plane_with_box(tmp_path / "box.ply")
    proc = run("render", cloud, "-o", tmp_path / "edl.png", "--depth", tmp_path / "d.npy", "--eye", "5,5,30",
               "--target", "5,5,0", "--up", "0,1,0", "--size", "300x300", "--shading", "edl", "--stats",
               tmp_path / "s.json", *flags)
    assert proc.returncode == 0, proc.stderr
    from PIL import Image

    gray = np.asarray(Image.open(tmp_path / "edl.png").convert("RGB")).astype(float).mean(axis=2) / 255
    depth = np.load(tmp_path / "d.npy")
    box = depth < 29.5  # the box's top, a unit nearer than the plane at 30
    outside = ndimage.distance_transform_edt(~box)
    plane = np.isfinite(depth) & (depth > 29.5)
    far = gray[plane & (outside > 40)].mean()
    assert far >= 0.85
    for lo, hi in ((1, 2), (3, 5)):
        ring = plane & (outside >= lo) & (outside <= hi)
        assert gray[ring].mean() <= 0.7 * far, (lo, hi)
    stats = json.loads((tmp_path / "s.json").read_text())
    assert stats["shading"] == "edl" and stats["edl"] == {"strength": 1.0, "radius": 1.4}


@requires_gl
def test_the_glsl_twin_of_eye_dome_lighting_matches_the_reference():
    """gl/edl.glsl (the page's) against surfel.edl on a depth image with steps, slopes and holes."""
    from surfel.gl.context import get_context
    from surfel.gl.program import expand_includes

    ctx = get_context()
    h, w = 96, 128
    y, x = np.mgrid[0:h, 0:w]
    depth = (20 + 0.02 * x + 0.01 * y).astype(np.float32)
    depth[30:60, 40:80] -= 3  # a raised block
    depth[70:, 100:] = np.inf  # nothing drawn
    source = expand_includes(Path(surfel.__file__).parent / "gl" / "edl.glsl")
    program = ctx.program(vertex_shader="#version 430 core\nvoid main() { vec2 p = vec2((gl_VertexID << 1) & 2, "
                                        "gl_VertexID & 2); gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0); }",
                          fragment_shader="#version 430 core\n" + source + """
uniform sampler2D u_depth;
uniform float u_radius, u_strength;
out vec4 out_term;
void main() { out_term = vec4(edl_term(u_depth, ivec2(gl_FragCoord.xy), u_radius, u_strength)); }""")
    texture = ctx.texture((w, h), 1, np.where(np.isfinite(depth), depth, 0)[::-1].copy().tobytes(), dtype="f4")
    target = ctx.texture((w, h), 1, dtype="f4")
    fbo = ctx.framebuffer(color_attachments=[target])
    fbo.use()
    texture.use(0)
    program["u_depth"].value, program["u_radius"].value, program["u_strength"].value = 0, 1.4, 1.0
    vao = ctx.vertex_array(program, [])
    vao.render(ctx.TRIANGLES, vertices=3)
    gpu = np.frombuffer(target.read(), np.float32).reshape(h, w)[::-1]
    for obj in (vao, fbo, target, texture, program):
        obj.release()
    cpu = eye_dome_lighting(depth, 1.4, 1.0)
    assert np.abs(gpu - cpu).max() < 2e-3
    assert cpu[28, 60] < 0.2 and cpu[10, 10] > 0.99  # dark just outside the block, the slope untouched


# ---- filters ------------------------------------------------------------------------------------------------


@requires_gl
def test_classes_filter_draws_a_continuous_bare_earth(autzen):
    """--classes 2 draws the ground alone, and its splats are sized for it: the ground's
    footprint is covered without holes where trees stood."""
    camera = top_view(autzen, (256, 256))
    ground = autzen.attributes["classification"] == 2
    result = surfel.render(autzen, camera, classes=(2,), color="classification", shading="none")
    assert result.stats["selected"] == int(ground.sum()) and result.stats["categories"] == [2]
    pixels, _ = camera.project(autzen.positions[ground])
    footprint = np.zeros((256, 256), bool)
    inside = (pixels >= 0).all(axis=1) & (pixels[:, 0] < 256) & (pixels[:, 1] < 256)
    footprint[pixels[inside, 1].astype(int), pixels[inside, 0].astype(int)] = True
    footprint = ndimage.binary_closing(footprint, iterations=3) & ndimage.binary_erosion(
        ndimage.binary_fill_holes(ndimage.binary_closing(footprint, iterations=3)), iterations=2)
    assert footprint.sum() > 10000
    assert (result.alpha[footprint] == 0).mean() <= 0.01
    assert foreign_fraction(result.rgba8(), [ASPRS_COLORS[2]]) == 0.0


@requires_gl
def test_returns_filter_keeps_first_and_last_returns(autzen):
    a = autzen.attributes
    camera = top_view(autzen, (64, 64))
    first = surfel.render(autzen, camera, "points", returns=("first",)).stats["selected"]
    last = surfel.render(autzen, camera, "points", returns=("last",)).stats["selected"]
    second = surfel.render(autzen, camera, "points", returns=("2",), classes=(1,)).stats["selected"]
    assert first == int((a["return_number"] == 1).sum())
    assert last == int((a["return_number"] == a["number_of_returns"]).sum())
    assert second == int(((a["return_number"] == 2) & (a["classification"] == 1)).sum())


def test_bad_colour_options_end_in_one_line_and_write_nothing(tmp_path):
    out = tmp_path / "x.png"
    tile = DATA / "simple.las"
    plain = tmp_path / "plain.ply"
    write_ply(PointCloud(np.random.default_rng(0).normal(size=(50, 3))), plain)
    cases = [((tile, "--color", "nosuch"), "--color: "), ((tile, "--colormap", "nosuch"), "--colormap"),
             ((tile, "--color-range", "3,1"), "--color-range"), ((tile, "--color-range", "1"), "--color-range"),
             ((tile, "--returns", "middle"), "--returns"), ((tile, "--classes", "a,b"), "--classes"),
             ((tile, "--classes", "300"), "--classes"), ((tile, "--classes", "9"), "no point"),
             ((plain, "--classes", "2"), "no classification"), ((tile, "--edl-radius", "0"), "--edl-radius"),
             ((tile, "--shading", "glow"), "--shading")]
    for args, message in cases:
        proc = run("render", *args, "-o", out, "--size", "32x32")
        assert proc.returncode == 2, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (args, proc.stderr)
        assert not out.exists()


# ---- readable defaults and framing ---------------------------------------------------------------------------


@requires_gl
def test_defaults_follow_the_data_and_are_reported(tmp_path, autzen):
    camera = top_view(autzen, (64, 64))
    assert {k: surfel.render(autzen, camera).stats[k] for k in ("shading", "color")} == \
        {"shading": "edl", "color": "rgb"}  # a raw tile with RGB: its colours, eye-dome lighting
    bare = autzen.with_(colors=None)
    stats = surfel.render(bare, camera).stats
    assert stats["shading"] == "edl" and stats["color"] == "elevation" and len(stats["color_range"]) == 2
    with_normals = autzen.with_(normals=np.tile([0.0, 0.0, 1.0], (len(autzen), 1)))
    assert surfel.render(with_normals, camera).stats["shading"] == "phong"  # surfaces keep surface shading
    # the tile with the normals surfel estimated for it (as `surfel prepare` writes them) is the same raw tile
    from surfel.preprocess import complete

    prepared, _ = complete(autzen)
    assert prepared.normals is not None and surfel.render(prepared, camera).stats["shading"] == "edl"
    help_text = " ".join(run("render", "--help").stdout.split())
    assert "edl for geospatial clouds without normals of their own, else phong" in help_text
    assert "else elevation for geospatial clouds" in help_text and "2nd to 98th percentile" in help_text


def long_tile(length=100.0, width=20.0, n=20000):
    rng = np.random.default_rng(1)
    xy = rng.uniform([0, 0], [length, width], (n, 2))
    return PointCloud(np.c_[xy + [5e5, 4e6], 0.3 * np.sin(xy[:, 0] / 7)], geospatial=True)


def covered_box(alpha):
    rows, cols = np.nonzero(alpha > 0)
    return rows.min(), rows.max(), cols.min(), cols.max()


@requires_gl
@pytest.mark.parametrize("ortho", [None, "auto"])
def test_a_long_tile_seen_from_the_top_fills_the_width(ortho):
    tile = long_tile()
    camera = CameraSpec(size=(400, 300), view="top", ortho=ortho).camera(tile)
    lo, hi = tile.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pixels, _ = camera.project(corners)
    assert pixels[:, 0].min() == pytest.approx(20, abs=1e-6) and pixels[:, 0].max() == pytest.approx(380, abs=1e-6)
    result = surfel.render(tile, camera, "points", color="rgb")
    top, bottom, left, right = covered_box(result.alpha)
    assert 0.9 <= (right - left + 1) / 400 <= 0.93  # 5% margin each side (and the splats' radii)
    assert (bottom - top + 1) / 300 < 0.3
    if ortho == "auto":
        length = tile.bounds[1][0] - tile.bounds[0][0]
        assert camera.ortho_height == pytest.approx(length / 0.9 * 300 / 400, rel=1e-9)


def test_iso_views_frame_the_projected_extent_and_explicit_cameras_stay():
    tile = long_tile()
    camera = frame(tile.center, tile.bounding_radius, view="iso", geospatial=True, size=(300, 300),
                   bounds=tile.bounds)
    lo, hi = tile.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pixels, _ = camera.project(corners)
    margin = np.minimum(pixels, 300 - pixels).min()
    assert margin == pytest.approx(0.05 * 300, abs=0.5)  # the box touches the 5% margin
    explicit = CameraSpec(size=(300, 300), eye=(5e5, 4e6, 500.0), target=(5e5 + 50, 4e6 + 10, 0.0)).camera(tile)
    same = Camera.look_at((5e5, 4e6, 500.0), (5e5 + 50, 4e6 + 10, 0.0), (0, 0, 1), size=(300, 300))
    assert np.allclose(explicit.world_to_eye, same.world_to_eye)
    wide = dict(view="top", geospatial=True, size=(800, 200))  # a wide image: the sphere would fill its height
    top = frame(tile.center, tile.bounding_radius, bounds=tile.bounds, **wide)
    sphere = frame(tile.center, tile.bounding_radius, **wide)
    assert np.linalg.norm(sphere.eye - tile.center) > 2.5 * np.linalg.norm(top.eye - tile.center)


# ---- attributes that are not numbers, the viewer's keys -------------------------------------------------------


@requires_gl
def test_a_las_field_holding_nan_reads_and_shows_neutral(tmp_path):
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="height_above_ground", type=np.float32))
    header.scales = [0.01] * 3
    g = np.arange(0, 10, 0.1)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, np.zeros_like(x)
    las.height_above_ground = np.where(x < 5, np.nan, y).astype(np.float32)
    las.write(tmp_path / "nan.las")
    info = run("info", tmp_path / "nan.las")
    assert info.returncode == 0 and "5000 not finite" in info.stdout
    proc = run("render", tmp_path / "nan.las", "-o", tmp_path / "n.png", "--color", "height_above_ground",
               "--shading", "none", "--view", "top", "--ortho", "auto", "--size", "200x200", "--method", "points")
    assert proc.returncode == 0, proc.stderr
    from PIL import Image

    rgb = np.asarray(Image.open(tmp_path / "n.png").convert("RGB")).astype(int)
    left, right = rgb[60:140, 30:90], rgb[60:140, 110:170]  # x < 5 (no value) and x > 5
    assert np.abs(left - np.round(np.asarray(NEUTRAL) * 255)).max() <= 1
    assert np.abs(right - np.round(np.asarray(NEUTRAL) * 255)).max(axis=2).min() > 20


@requires_gl
def test_the_viewer_cycles_colour_modes_toggles_edl_and_opens_a_tile_obliquely(autzen):
    from surfel.viewer import OBLIQUE_ELEVATION, ViewState, color_status

    state = ViewState(autzen, "deferred")
    assert state.shading == "edl" and state.color == "rgb" and state.elevation == OBLIQUE_ELEVATION
    camera = state.camera((200, 150))
    lo, hi = autzen.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pixels, depth = camera.project(corners)
    assert (depth > 0).all() and pixels.min() >= -1e-6 and (pixels <= [200, 150]).all()  # the whole tile
    margins = np.r_[pixels.min(axis=0), [200, 150] - pixels.max(axis=0)] / [200, 150, 200, 150]
    assert margins.min() == pytest.approx(0.05, abs=1e-6)  # filling the view
    assert np.degrees(np.arcsin(-camera.forward[2])) == pytest.approx(OBLIQUE_ELEVATION)
    result, _ = state.render((200, 150))
    assert state.colors[:2] == ["rgb", "elevation"] and "classification" in state.colors
    state.key("c")
    result, _ = state.render((200, 150))
    assert state.color == "elevation" and "elevation viridis" in color_status(result.stats)
    lo, hi = result.stats["color_range"]
    assert f"{lo:.4g}..{hi:.4g}" in color_status(result.stats)
    state.key("l")
    assert state.shading == "phong" and state.render((64, 64))[0].stats["shading"] == "phong"
    state.key("l")
    assert state.shading == "edl"
    with pytest.raises(SurfelError, match="no attribute"):
        resolve(autzen, "nosuch")
