"""surfel export-html: the page in a real browser against surfel render, as a user meets it."""

import subprocess
import sys
import warnings

import numpy as np
import pytest

from browser import png_rgb, psnr
from conftest import requires_gl
from surfel import PointCloud
from surfel.camera import Camera
from surfel.colors import ASPRS_COLORS, colormap_table
from surfel.methods import DEFAULT_METHOD
from surfel.options import RenderOptions
from surfel.web import export_html
from surfel.web.pack import oct_decode, pack_cloud, tangent_frame


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "surfel.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=600)


def open_page(browser, path, size, capture=True):
    """The page at `size`, after its first full frame; every request it made is local."""
    page = browser.new_page()
    page.set_viewport_size({"width": size[0], "height": size[1]})
    requests, errors = [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(path.as_uri() + ("#capture" if capture else ""))
    page.wait_for_function("window.surfelStats && (surfelStats.ready || surfelStats.error)", timeout=180_000)
    assert page.evaluate("surfelStats.error") is None and not errors, (page.evaluate("surfelStats.error"), errors)
    assert all(url.startswith(("file:", "data:", "blob:")) for url in requests), requests
    return page


def next_frame(page, frames_before):
    page.wait_for_function(f"surfelStats.frames > {frames_before} && surfelStats.ready", timeout=120_000)


def canvas(page):
    return png_rgb(page.locator("canvas").screenshot())


CAMERAS = {
    "perspective": ["--eye", "1.6,1.2,3.6", "--target", "0.05,0.05,-0.1", "--up", "0,1,0", "--fov", "32",
                    "--size", "480x360", "--shading", "lambert"],
    "perspective deferred": ["--eye", "1.6,1.2,3.6", "--target", "0.05,0.05,-0.1", "--up", "0,1,0", "--fov", "32",
                             "--size", "480x360", "--shading", "phong", "--method", "deferred"],
    "close-up, quads": ["--eye", "0.5,0.4,1.1", "--target", "0.1,0.2,0.2", "--up", "0.1,1,0", "--fov", "45",
                        "--size", "320x320"],
    "orthographic gaussian": ["--view", "right", "--ortho", "2.2", "--size", "400x300", "--method", "gaussian",
                              "--shading", "normals"],
}


@requires_gl
@pytest.mark.parametrize("name", CAMERAS)
def test_page_matches_surfel_render(browser, tmp_path, name):
    """The #capture screenshot against surfel render with the same flags (judged at 30 dB)."""
    flags = CAMERAS[name]
    method = flags[flags.index("--method") + 1] if "--method" in flags else DEFAULT_METHOD
    size = tuple(int(v) for v in flags[flags.index("--size") + 1].split("x"))
    ref = run("render", "--demo", "-o", tmp_path / "ref.png", "--method", method, *flags)
    assert ref.returncode == 0, ref.stderr
    out = run("export-html", "--demo", "-o", tmp_path / "view.html", *flags)
    assert out.returncode == 0, out.stderr
    page = open_page(browser, tmp_path / "view.html", size)
    shot = png_rgb(page.screenshot())
    reference = png_rgb((tmp_path / "ref.png").read_bytes())
    assert shot.shape == reference.shape
    assert (reference.max(axis=2) > 0).mean() > 0.05  # the model is in view
    assert psnr(shot, reference) >= 40.0
    if method == "phong":  # lit by its normal fields: nearer phong's render than deferred's
        other = run("render", "--demo", "-o", tmp_path / "other.png", *flags, "--method", "deferred")
        assert other.returncode == 0, other.stderr
        assert psnr(shot, reference) > psnr(shot, png_rgb((tmp_path / "other.png").read_bytes())) + 3
    if name == "close-up, quads":
        assert page.evaluate("surfelStats.primitive") == "quads"
    page.close()


@requires_gl
def test_a_sheet_close_above_a_body_hides_it_in_the_page_too(browser, tmp_path):
    """The page caps z_t by the layers' thickness as surfel render does (its own column): the
    body 0.3 below the sheet stays hidden, so the page matches the render (uncapped, the sheet
    would show half blue)."""
    from scenes import sheet_over_body
    from surfel.io import write_ply

    cloud, _ = sheet_over_body(np.random.default_rng(5))
    write_ply(cloud, tmp_path / "layers.ply")
    flags = ["--eye", "0,-40,17", "--target", "0,-5,0", "--up", "0,0,1", "--fov", "40", "--size", "320x240",
             "--shading", "none"]
    ref = run("render", tmp_path / "layers.ply", "-o", tmp_path / "ref.png", *flags)
    assert ref.returncode == 0, ref.stderr
    out = run("export-html", tmp_path / "layers.ply", "-o", tmp_path / "view.html", *flags)
    assert out.returncode == 0, out.stderr
    page = open_page(browser, tmp_path / "view.html", (320, 240))
    shot = png_rgb(page.screenshot())
    reference = png_rgb((tmp_path / "ref.png").read_bytes())
    sheet = reference[..., 0] > 200
    assert sheet.mean() > 0.2 and (reference[sheet, 2] < 10).all()  # red, no body colour
    assert psnr(shot, reference) >= 35.0
    page.close()


@requires_gl
def test_dragging_zooming_and_switching_change_the_view(browser, tmp_path):
    proc = run("export-html", "--demo", "-o", tmp_path / "view.html", "--size", "400x320")
    assert proc.returncode == 0, proc.stderr
    page = open_page(browser, tmp_path / "view.html", (400, 360), capture=False)
    assert page.locator("#panel").is_visible() and "splats" in page.locator("#status").inner_text()
    before = canvas(page)
    frames = page.evaluate("surfelStats.frames")
    page.mouse.move(200, 160)
    page.mouse.down()
    for step in range(1, 6):
        page.mouse.move(200 + 20 * step, 160 + 4 * step)
    page.mouse.up()
    next_frame(page, frames)
    orbited = canvas(page)
    assert np.abs(orbited.astype(int) - before).mean() > 2  # the cow turned

    frames = page.evaluate("surfelStats.frames")
    covered = (orbited.max(axis=2) > 0).mean()
    page.mouse.move(200, 160)
    page.mouse.wheel(0, -400)  # zoom in
    next_frame(page, frames)
    assert (canvas(page).max(axis=2) > 0).mean() > covered + 0.05  # nearer: the cow fills more of the view

    assert not page.is_checked("#ewa")  # phong's own default: off
    changes = [("#method", "gaussian"), ("#color", "elevation"), ("#shading", "edl")]
    for selector, value in changes:
        frames = page.evaluate("surfelStats.frames")
        shown = canvas(page)
        page.select_option(selector, value)
        next_frame(page, frames)
        assert (np.abs(canvas(page).astype(int) - shown).max(axis=2) > 2).mean() > 0.02, selector
    assert page.evaluate("[surfelStats.method, surfelStats.color, surfelStats.shading]") == \
        ["gaussian", "elevation", "edl"]
    page.select_option("#method", "deferred")  # the EWA box follows the method's own default
    assert page.is_checked("#ewa")
    page.close()


def plane(n=120, spacing=0.01, height=None, classes=None):
    """A square of n x n points on z = 0 (+Z up, normals up), optionally raised by height(x, y)."""
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    z = np.zeros_like(x) if height is None else height(x, y)
    attributes = {} if classes is None else {"classification": classes(x, y).ravel().astype(np.float32)}
    return PointCloud(np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1), normals=np.tile([0, 0, 1.0], (n * n, 1)),
                      radii=np.full(n * n, spacing * 0.8), attributes=attributes, geospatial=True)


def top_camera(cloud, size=(240, 240), height=None):
    center = cloud.center
    return Camera.look_at(center + [0, 0, 3], center, (0, 1, 0), size=size,
                          ortho_height=height or 1.1 * (cloud.bounds[1] - cloud.bounds[0]).max())


@requires_gl
@pytest.mark.parametrize("supersample", [1, 3])
def test_categories_are_never_blended(browser, tmp_path, supersample):
    """Classification with --shading none: each pixel inside the plane shows one class's colour,
    along the borders between classes too, supersampled or not."""
    cloud = plane(classes=lambda x, y: np.where(x < 0.6, 2, np.where(y < 0.6, 6, 9)))
    export_html(cloud, top_camera(cloud), tmp_path / "c.html",
                options=RenderOptions(shading="none", color="classification", supersample=supersample))
    shot = open_page(browser, tmp_path / "c.html", (240, 240)).screenshot()
    inside = png_rgb(shot)[30:210, 30:210].reshape(-1, 3).astype(int)
    palette = np.round(np.array([ASPRS_COLORS[c] for c in (2, 6, 9)]) * 255)
    nearest = np.abs(inside[:, None, :] - palette[None]).max(axis=2).min(axis=1)
    assert (nearest <= 1).all(), np.unique(inside[nearest > 1], axis=0)[:5]
    assert len({tuple(c) for c in inside}) == 3  # all three classes show


@requires_gl
def test_elevation_colours_follow_height(browser, tmp_path):
    cloud = plane(height=lambda x, y: 0.5 * x + 0.1 * y)
    export_html(cloud, top_camera(cloud), tmp_path / "e.html",
                options=RenderOptions(shading="none", color="elevation", colormap="viridis", color_range=(0.0, 0.6)))
    image = png_rgb(open_page(browser, tmp_path / "e.html", (240, 240)).screenshot())[40:200, 40:200]
    lut = np.round(colormap_table("viridis") * 255).astype(int)
    index = np.abs(image.reshape(-1, 1, 3).astype(int) - lut[None]).sum(axis=2).argmin(axis=1).reshape(160, 160)
    column = index.mean(axis=0)
    assert (np.diff(column) >= 0).all() and column[-1] - column[0] > 100  # rises with x, across most of the map


@requires_gl
def test_eye_dome_lighting_darkens_beside_a_step(browser, tmp_path):
    """A plane with a raised box, seen from above with --shading edl: the plane in a ring just
    outside the box darkens, far from it keeps its albedo (white)."""
    def box(x, y):
        return np.where((np.abs(x - 0.6) < 0.2) & (np.abs(y - 0.6) < 0.2), 0.15, 0.0)

    cloud = plane(height=box)
    camera = Camera.look_at(cloud.center + [0, 0, 3], cloud.center, (0, 1, 0), size=(240, 240), fov=30)
    # deferred keeps the given radii as circles; phong fits ellipses over them, which carry the
    # box's top a pixel or two past its edge, over the ring measured here
    export_html(cloud, camera, tmp_path / "edl.html", method="deferred",
                options=RenderOptions(shading="edl", color="rgb"))
    gray = png_rgb(open_page(browser, tmp_path / "edl.html", (240, 240)).screenshot()).mean(axis=2)
    project, _ = camera.project(np.array([[0.6, 0.6, 0.15], [0.8, 0.6, 0.0], [0.1, 0.1, 0.0]]))
    (cx, cy), (edge_x, _), (far_x, far_y) = project
    ring = gray[int(cy) - 10:int(cy) + 10, int(edge_x) + 1:int(edge_x) + 3]
    far = gray[int(far_y) - 5:int(far_y) + 5, int(far_x) - 5:int(far_x) + 5]
    assert far.mean() >= 0.85 * 255
    assert ring.mean() <= 0.7 * far.mean()


@requires_gl
def test_a_million_point_page_draws_its_point_tree_and_reports_frame_time(browser, tmp_path):
    from surfel.bench import replicate
    from surfel.data import demo_cloud
    from surfel.rendering import default_camera

    cloud = replicate(demo_cloud(), 1_000_000)
    report = export_html(cloud, default_camera(cloud, (640, 640)), tmp_path / "m.html")
    assert report["point_tree"] > 1_000_000
    assert report["bytes"] < 40 * report["points"]  # quantized: about 25 bytes a node, base64
    page = open_page(browser, tmp_path / "m.html", (640, 700), capture=False)
    still = page.evaluate("({...surfelStats})")
    assert still["frameMs"] > 0 and still["primitive"] == "point sprites"
    assert 0 < still["drawn"] < still["points"]  # the vertex test keeps a cut of the tree
    assert f"{still['frameMs']:.1f} ms" in page.locator("#status").inner_text()
    page.mouse.move(320, 320)
    page.mouse.down()
    page.mouse.move(380, 330)
    page.wait_for_function("surfelStats.moving", timeout=60_000)
    moving = page.evaluate("({...surfelStats})")
    assert moving["drawn"] < still["drawn"]  # coarser while the camera moves
    page.mouse.up()
    next_frame(page, moving["frames"])
    page.close()


def test_quantized_splats_decode_to_the_cloud_they_came_from():
    """pack.py's columns, decoded with the page's formulas (splat_attributes.glsl), give back
    positions, normals and both splat axes, and clip lines that still cut the same side."""
    rng = np.random.default_rng(3)
    n = 2000
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    u_dir = np.cross(normals, rng.normal(size=(n, 3)))
    u_dir /= np.linalg.norm(u_dir, axis=1, keepdims=True)
    v_dir = np.cross(normals, u_dir) * rng.choice([-1.0, 1.0], size=(n, 1))
    axes = np.stack([u_dir * rng.uniform(0.01, 0.05, (n, 1)), v_dir * rng.uniform(0.01, 0.05, (n, 1))], axis=1)
    lines = np.tile(np.array([[0.6, 0.8, 0.3], [0.0, 0.0, 1.0]]), (n, 1, 1))
    cloud = PointCloud(rng.uniform(-3, 5, (n, 3)), normals=normals, axes=axes,
                       radii=np.linalg.norm(axes[:, 0], axis=1), attributes={"clip_lines": lines})
    layout, blob = pack_cloud(cloud, {})

    def column(name, dtype, width):
        c = layout["columns"][name]
        return np.frombuffer(blob, dtype, c["bytes"] // np.dtype(dtype).itemsize, c["offset"]).reshape(n, width)

    positions = layout["box_lo"] + column("position", "<u2", 3) / 65535 * np.array(layout["box_size"])
    assert np.abs(positions - (cloud.positions - cloud.local_origin)).max() <= 8 / 65535 * 0.5 + 1e-9
    decoded = oct_decode(column("normal", "<u2", 2))
    assert np.degrees(np.arccos(np.clip((decoded * normals).sum(axis=1), -1, 1))).max() < 0.01
    d1, d2 = tangent_frame(decoded)
    phi = 2 * np.pi * column("angle", "<u2", 1) / 65535
    radii = column("radii", "<f2", 2).astype(np.float64) * layout["length_unit"]
    u = radii[:, :1] * (np.cos(phi) * d1 + np.sin(phi) * d2)
    v = radii[:, 1:] * (np.cos(phi) * d2 - np.sin(phi) * d1)
    assert np.abs(u - axes[:, 0]).max() < 1e-4 and np.abs(np.abs((v * axes[:, 1]).sum(axis=1))
                                                          - (axes[:, 1] ** 2).sum(axis=1)).max() < 1e-6
    clip = column("clip", "<f2", 6).reshape(n, 2, 3).astype(np.float64)
    # the world point 0.7 axis_u + 0.5 axis_v, in the decoded splat's local coordinates, lies
    # where the original clip line put it (its v coefficient flips with the decoded axis_v)
    world = 0.7 * axes[:, 0] + 0.5 * axes[:, 1]
    local = np.stack([(world * u).sum(1) / (u * u).sum(1), (world * v).sum(1) / (v * v).sum(1)], axis=1)
    assert np.allclose((local * clip[:, 0, :2]).sum(axis=1), 0.7 * 0.6 + 0.5 * 0.8, atol=2e-3)
    assert np.allclose(clip[:, 1], [0.0, 0.0, 1.0])  # an inactive line stays inactive


def test_coincident_points_keep_their_splat_size():
    """A cloud whose box has no extent (one point, or all in one place) packs its semi-axes in
    the splat's own unit: finite half floats that decode to its radius, not infinities."""
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    axes = np.tile([[[0.5, 0.0, 0.0], [0.0, 0.25, 0.0]]], (3, 1, 1))
    cloud = PointCloud(np.full((3, 3), 7.0), normals=normals, axes=axes, radii=np.full(3, 0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow in the float16 cast warns
        layout, blob = pack_cloud(cloud, {})
    c = layout["columns"]["radii"]
    radii = np.frombuffer(blob, "<f2", c["bytes"] // 2, c["offset"]).reshape(3, 2).astype(np.float64)
    assert np.allclose(radii * layout["length_unit"], [[0.5, 0.25]] * 3, rtol=1e-3)


def test_bad_options_end_in_one_line_and_write_nothing(tmp_path):
    out = tmp_path / "view.html"
    bad = [(["--color", "nosuch"], "--color"), (["--colormap", "nosuch"], "--colormap"),
           (["--color-range", "1"], "--color-range"), (["--color-range", "3,1"], "--color-range"),
           (["--method", "mls"], "--method")]
    for args, word in bad:
        proc = run("export-html", "--demo", "-o", out, *args)
        assert proc.returncode == 2, (args, proc.stderr)
        assert word in proc.stderr.strip().splitlines()[-1], proc.stderr
        assert "Traceback" not in proc.stderr and not out.exists()


@requires_gl
def test_a_copc_file_becomes_a_page_of_its_uniform_cut(browser, tmp_path):
    from pathlib import Path

    copc = Path(__file__).parent / "data" / "simple_with_page.copc.laz"
    proc = run("export-html", copc, "-o", tmp_path / "c.html", "--size", "320x240", "--view", "top",
               "--color", "elevation", "--shading", "edl")
    assert proc.returncode == 0, proc.stderr
    page = open_page(browser, tmp_path / "c.html", (320, 240))
    assert page.evaluate("surfelStats.drawn") > 0 and page.evaluate("surfelStats.color") == "elevation"
    shot = png_rgb(page.screenshot())
    assert (shot.max(axis=2) > 0).mean() > 0.05
    page.close()


@requires_gl
@pytest.mark.parametrize("mode,shading", [("elevation", "edl"), ("classification", "none"), ("intensity", "lambert"),
                                          ("return-number", "none")])
def test_the_page_s_colour_modes_match_surfel_render(browser, tmp_path, mode, shading):
    """A real tile's colour modes in the page against surfel render --method deferred, same camera."""
    from pathlib import Path

    import surfel
    from surfel.request import CameraSpec

    tile = surfel.load(Path(__file__).parent / "data" / "autzen_trim.laz")
    lo = tile.bounds[0]
    tile = tile.take((tile.positions[:, 0] < lo[0] + 300) & (tile.positions[:, 1] > lo[1] + 150))
    camera = CameraSpec(size=(320, 240), view="iso").camera(tile)
    options = RenderOptions(color=mode, shading=shading)
    report = export_html(tile, camera, tmp_path / "m.html", method="deferred", options=options)
    assert report["color"] == mode.replace("-", "_") and report["shading"] == shading
    shot = png_rgb(open_page(browser, tmp_path / "m.html", (320, 240)).screenshot())
    reference = surfel.render(tile, camera, "deferred", options=options).rgba8()[..., :3]
    assert (reference.max(axis=2) > 0).mean() > 0.1
    assert psnr(shot, reference) >= 40.0
