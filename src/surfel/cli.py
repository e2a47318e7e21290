"""The `surfel` command line. Every user-fixable error is one line on stderr and exit status 2."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from .errors import SurfelError

CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}


def _floats(text: str | None, count: int, name: str):
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise click.BadParameter(f"{name} needs {count} comma-separated numbers, got {text!r}") from None
    if len(values) != count or not all(np.isfinite(values)):
        raise click.BadParameter(f"{name} needs {count} comma-separated finite numbers, got {text!r}")
    return values


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"size must look like 512x512, got {text!r}") from None
    if w <= 0 or h <= 0 or w * h > 16384 * 16384:
        raise click.BadParameter(f"size {text!r} is out of range")
    return w, h


def camera_options(f):
    """The camera flags of CONVENTIONS.md."""
    from .camera import VIEWS

    for option in reversed([
        click.option("--size", default="1024x1024", show_default=True, help="Image size WxH in pixels."),
        click.option("--view", type=click.Choice(VIEWS), default=None, help="Auto-framing direction (default front)."),
        click.option("--azimuth", type=float, default=None,
                     help="Degrees from the front view towards the right, about the up axis."),
        click.option("--elevation", type=float, default=None, help="Degrees above the horizon."),
        click.option("--eye", default=None, help="Camera position X,Y,Z in file coordinates."),
        click.option("--target", default=None, help="Look-at point X,Y,Z (default: bounding-box centre)."),
        click.option("--up", default=None, help="Up vector (default 0,0,1 for LAS/LAZ, 0,1,0 otherwise)."),
        click.option("--fov", type=float, default=30.0, show_default=True, help="Vertical field of view in degrees."),
        click.option("--ortho", type=float, default=None, metavar="HEIGHT",
                     help="Orthographic camera showing HEIGHT world units vertically."),
        click.option("--opencv", type=click.Path(dir_okay=False), default=None,
                     help='Pinhole camera from a JSON file {"K": 3x3, "R": 3x3, "t": 3} (OpenCV world-to-camera).'),
        click.option("--zoom", type=float, default=1.0, show_default=True,
                     help="Move the auto-framed camera this many times farther."),
    ]):
        f = option(f)
    return f


def render_options(f):
    from .shading import MODELS

    for option in reversed([
        click.option("--shading", type=click.Choice(MODELS), default="phong", show_default=True),
        click.option("--background", default="0,0,0", show_default=True, help="Background R,G,B in [0, 1]."),
        click.option("--backend", type=click.Choice(["gl", "cpu"]), default=None,
                     help="Default: gl, else cpu where the method has one."),
        click.option("--supersample", type=click.IntRange(1, 8), default=None,
                     help="Samples per pixel side (method default)."),
        click.option("--radius-scale", type=float, default=1.0, show_default=True, help="Multiply every splat radius."),
        click.option("--depth-offset", type=float, default=None,
                     help="Visibility offset z_t as a fraction of the splat radius."),
        click.option("--backface-culling/--no-backface-culling", default=False, show_default=True),
        click.option("--ewa-filter/--no-ewa-filter", default=None,
                     help="Screen-space EWA filter approximation (default on for deferred)."),
        click.option("--lowpass-radius", type=float, default=1.0, show_default=True,
                     help="Screen-space low-pass radius in pixels."),
        click.option("--lod-error", type=float, default=None, metavar="PX",
                     help="Level of detail: allowed projected error in pixels."),
        click.option("--point-budget", type=click.IntRange(1), default=None, metavar="N",
                     help="Most points drawn from a .lod hierarchy (its LOD error is raised to fit)."),
        click.option("--dump-passes", type=click.Path(file_okay=False), default=None,
                     help="Write the intermediate passes here as images."),
        click.option("--per-pixel-normalization/--per-surfel-normalization", default=True, show_default=True,
                     help="object-space: divide by the accumulated weight per pixel (Botsch & Kobbelt 2003), "
                          "or Ren et al.'s precomputed per-surfel weights."),
        click.option("--shadows", is_flag=True, help="Ray-traced shadows (mls)."),
        click.option("--reflect", is_flag=True, help="One mirror bounce (mls)."),
    ]):
        f = option(f)
    return f


def make_options(kw):
    from .options import RenderOptions

    background = _floats(kw["background"], 3, "--background")
    if min(background) < 0 or max(background) > 1:
        raise click.BadParameter("--background values must lie in [0, 1]")
    params = {k: True for k in ("shadows", "reflect") if kw.get(k)}
    params["normalization"] = "per-pixel" if kw.get("per_pixel_normalization", True) else "per-surfel"
    return RenderOptions(shading=kw["shading"], background=tuple(background), supersample=kw["supersample"],
                         radius_scale=kw["radius_scale"], depth_offset=kw["depth_offset"],
                         backface_culling=kw["backface_culling"], ewa_filter=kw["ewa_filter"],
                         lowpass_radius=kw["lowpass_radius"], lod_error=kw["lod_error"],
                         point_budget=kw.get("point_budget"),
                         dump_passes=kw["dump_passes"], params=params)


def make_camera(cloud, kw):
    from .camera import Camera, frame

    size = _size(kw["size"])
    if kw.get("opencv"):
        path = kw["opencv"]
        try:
            spec = json.loads(Path(path).read_text())
            cam = Camera.from_opencv(np.array(spec["K"], float), np.array(spec["R"], float),
                                     np.array(spec["t"], float), size)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SurfelError(f"{path}: not an OpenCV camera JSON with K, R, t ({type(exc).__name__}: {exc})") from None
        return cam.fit_clip_planes(cloud.center, cloud.bounding_radius)
    return frame(cloud.center, cloud.bounding_radius, view=kw["view"], azimuth=kw["azimuth"],
                 elevation=kw["elevation"], up=_floats(kw["up"], 3, "--up"), geospatial=cloud.geospatial,
                 fov=kw["fov"], size=size, eye=_floats(kw["eye"], 3, "--eye"),
                 target=_floats(kw["target"], 3, "--target"), ortho_height=kw["ortho"], zoom=kw["zoom"])


def load_input(path):
    from .io import load

    return load(path)


def open_input(path):
    """A lazy LOD source (a .lod directory, a COPC file) if PATH is one, else the loaded cloud."""
    from .lod.source import open_source

    return open_source(path) or load_input(path)


class SurfelGroup(click.Group):
    """Turns SurfelErrors into one line on stderr and exit status 2, never a traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except SurfelError as exc:
            click.echo(f"surfel: error: {exc}", err=True)
            ctx.exit(2)
        except MemoryError:
            click.echo("surfel: error: out of memory", err=True)
            ctx.exit(2)


@click.group(cls=SurfelGroup, context_settings=CONTEXT)
@click.version_option(package_name="surfel")
def main():
    """surfel: render point clouds as continuous, hole-free, anti-aliased surfaces.

    \b
    Examples:
      surfel render --demo -o demo.png
      surfel render scan.ply -o scan.png --method deferred --view iso
      surfel compare bunny.obj --method deferred --size 512x512 --shading lambert
      surfel bench --methods points,deferred --points 1000000 --size 1024x1024
    """


@main.command(context_settings=CONTEXT)
@click.argument("input", required=False, type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="PNG to write.")
@click.option("--method", "-m", default="deferred", show_default=True, help="Rendering method (see `surfel methods`).")
@click.option("--demo", is_flag=True, help="Render the bundled demo model (Spot, CC0) instead of INPUT.")
@click.option("--depth", type=click.Path(dir_okay=False), default=None, help="Write eye depth (H x W float32 .npy).")
@click.option("--normals", type=click.Path(dir_okay=False), default=None,
              help="Write eye normals (H x W x 3 float32 .npy).")
@click.option("--stats", type=click.Path(dir_okay=False), default=None, help="Write render statistics (.json).")
@camera_options
@render_options
def render(input, output, method, demo, depth, normals, stats, **kw):
    """Render INPUT (PLY, OBJ, LAS/LAZ, XYZ/PTS/TXT, NPZ, a .lod hierarchy, COPC) to a PNG.

    A .lod directory (`surfel lod build -o NAME.lod`) or a COPC file (NAME.copc.laz) is read
    lazily: only the nodes the view selects at --lod-error (default 1 pixel) are loaded, at
    most --point-budget.

    \b
    Example:
      surfel render bunny.obj -o bunny.png --method deferred --size 512x512
      surfel render big.lod -o far.png --lod-error 1 --point-budget 5000000
    """
    from .rendering import render as do_render

    if demo == (input is not None):
        raise click.UsageError("give an INPUT file or --demo (not both)")
    if demo:
        from .data import demo_cloud

        cloud = demo_cloud()
    else:
        cloud = open_input(input)
    result = do_render(cloud, make_camera(cloud, kw), method, backend=kw["backend"], options=make_options(kw))
    result.save(output, depth=depth, normals=normals, stats=stats)
    click.echo(f"{output}: {result.width}x{result.height} {method}@{result.stats['backend']} "
               f"{result.stats['splats']} splats in {result.stats['ms']:.0f} ms", err=True)


@main.command("export-html", context_settings=CONTEXT)
@click.argument("input", required=False, type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="HTML page to write.")
@click.option("--method", "-m", type=click.Choice(["deferred", "gaussian"]), default="deferred", show_default=True)
@click.option("--demo", is_flag=True, help="Export the bundled demo model instead of INPUT.")
@click.option("--shading", type=click.Choice(["lambert", "phong", "none", "normals", "depth", "edl"]), default="phong",
              show_default=True)
@click.option("--color", default=None, help="rgb, elevation or an attribute's name (default rgb).")
@click.option("--colormap", default="viridis", show_default=True, help="Colour map (matplotlib's names).")
@click.option("--color-range", default=None, metavar="LO,HI", help="Colour-map range (default: 2nd-98th percentile).")
@click.option("--edl-strength", type=click.FloatRange(0), default=1.0, show_default=True)
@click.option("--edl-radius", type=click.FloatRange(0.5, 32), default=1.4, show_default=True, help="Pixels.")
@click.option("--background", default="0,0,0", show_default=True, help="Background R,G,B in [0, 1].")
@click.option("--supersample", type=click.IntRange(1, 4), default=None, help="Samples per pixel side (default 1).")
@click.option("--radius-scale", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True)
@click.option("--depth-offset", type=float, default=None, help="Visibility offset z_t as a fraction of the radius.")
@click.option("--backface-culling/--no-backface-culling", default=False, show_default=True)
@click.option("--ewa-filter/--no-ewa-filter", default=None, help="Screen-space EWA filter (default on for deferred).")
@click.option("--lowpass-radius", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True)
@click.option("--lod-error", type=click.FloatRange(min=0, min_open=True), default=None, metavar="PX",
              help="Start at this LOD error (builds a point tree whatever the size).")
@click.option("--point-budget", type=click.IntRange(1), default=300_000, show_default=True, metavar="N",
              help="Above N points the page draws a sequential point tree.")
@camera_options
def export_html(input, output, method, demo, shading, color, colormap, color_range, edl_strength, edl_radius,
                background, point_budget, **kw):
    """Write one self-contained HTML page that splats INPUT in the browser (WebGL2, offline).

    It opens at the camera of these flags (as `surfel render`), orbits, pans and zooms with
    the mouse, switches method, colour and shading; INPUT#capture shows the canvas alone.

    \b
    Example:
      surfel export-html bunny.obj -o bunny.html --method deferred --size 800x600
      surfel export-html scan.laz -o scan.html --color elevation --shading edl --view iso
    """
    from .options import RenderOptions
    from .web import export_html as do_export

    if demo == (input is not None):
        raise click.UsageError("give an INPUT file or --demo (not both)")
    if demo:
        from .data import demo_cloud

        cloud = demo_cloud()
    else:
        cloud = open_input(input)
    rgb = _floats(background, 3, "--background")
    if min(rgb) < 0 or max(rgb) > 1:
        raise click.BadParameter("--background values must lie in [0, 1]")
    options = RenderOptions(shading=shading, background=tuple(rgb), supersample=kw["supersample"],
                            radius_scale=kw["radius_scale"], depth_offset=kw["depth_offset"],
                            backface_culling=kw["backface_culling"], ewa_filter=kw["ewa_filter"],
                            lowpass_radius=kw["lowpass_radius"], lod_error=kw["lod_error"])
    report = do_export(cloud, make_camera(cloud, kw), output, method=method, options=options, color=color,
                       colormap=colormap, color_range=_floats(color_range, 2, "--color-range"),
                       edl_strength=edl_strength, edl_radius=edl_radius, point_budget=point_budget,
                       up=_floats(kw["up"], 3, "--up"))
    click.echo(f"{output}: {report['points']} points, {report['bytes'] / 1e6:.1f} MB", err=True)


@main.command(context_settings=CONTEXT)
def methods():
    """List the rendering methods and their backends.

    \b
    Example:
      surfel methods
    """
    from .methods import METHODS

    for m in METHODS.values():
        click.echo(f"{m.name:14s} {','.join(m.backends):8s} {m.summary}")


@main.command(context_settings=CONTEXT)
@click.argument("input", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def info(input, as_json):
    """Counts, bounds, attributes, what would be estimated, and the OpenGL renderer.

    \b
    Example:
      surfel info scan.laz
    """
    from .gl.context import gl_available, renderer_string
    from .lod.source import open_source

    source = open_source(input)
    if source is not None:  # described from its metadata, without loading its points
        lo, hi = source.bounds
        report = {"file": str(input), "kind": type(source).__name__, "points": source.total_points,
                  "bounds_min": lo.tolist(), "bounds_max": hi.tolist(), "geospatial": source.geospatial,
                  **(source.describe() if hasattr(source, "describe") else {}),
                  "opengl": renderer_string() if gl_available() else None}
    else:
        cloud = load_input(input)
        lo, hi = cloud.bounds
        estimate = [name for name in ("normals", "radii", "axes") if getattr(cloud, name) is None]
        report = {
            "file": str(input), "points": len(cloud), "faces": 0 if cloud.faces is None else len(cloud.faces),
            "bounds_min": lo.tolist(), "bounds_max": hi.tolist(), "local_origin": cloud.local_origin.tolist(),
            "attributes": cloud.attribute_names(), "would_estimate": estimate, "geospatial": cloud.geospatial,
            "opengl": renderer_string() if gl_available() else None,
        }
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    for key, value in report.items():
        click.echo(f"{key:15s} {value if value is not None else 'unavailable (use --backend cpu)'}")


@main.command(context_settings=CONTEXT)
@click.argument("mesh", type=click.Path(dir_okay=False))
@click.option("--method", "-m", default="deferred", show_default=True)
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Side-by-side PNG: mesh, method, error x4 (default compare-METHOD.png).")
@click.option("--json", "as_json", is_flag=True, help="Print the metrics as JSON.")
@click.option("--every", type=click.IntRange(1), default=1, show_default=True, metavar="N",
              help="Splat every Nth vertex only (normals kept, splat sizes estimated): sparse sampling.")
@camera_options
@render_options
def compare(mesh, method, output, as_json, every, **kw):
    """Render MESH's ground truth and METHOD on its vertices; print PSNR, holes and spill.

    \b
    Examples:
      surfel compare bunny.obj --method deferred --size 512x512 --shading lambert --json
      surfel compare bunny.obj --method phong --every 4 --size 512x512 --shading lambert
    """
    from .metrics import compare_results
    from .rendering import render as do_render

    cloud = load_input(mesh)
    if not cloud.is_mesh:
        raise SurfelError(f"{mesh}: compare needs a mesh (faces) as ground truth")
    camera = make_camera(cloud, kw)
    kw = {**kw, "background": "0,0,0"}  # the metrics are defined over black
    options = make_options(kw)
    reference = do_render(cloud, camera, "mesh", options=make_options({**kw, "supersample": None}))
    vertices = cloud.take(np.arange(0, len(cloud), every))  # every = 1: all of them, without the faces
    result = do_render(vertices, camera, method, backend=kw["backend"], options=options)
    metrics = {"method": method, "backend": result.stats["backend"], **compare_results(reference, result),
               "ms": result.stats["ms"], "splats": result.stats["splats"]}
    output = output or f"compare-{method}.png"
    _side_by_side(reference, result, output)
    if as_json:
        click.echo(json.dumps(metrics, indent=2))
    else:
        click.echo(f"{method}@{metrics['backend']}: PSNR {metrics['psnr']:.2f} dB, interior PSNR "
                   f"{metrics['interior_psnr']:.2f} dB, holes {100 * metrics['holes']:.3f}%, "
                   f"spill {100 * metrics['spill']:.3f}%  ({output})")


def _side_by_side(reference, result, path):
    from PIL import Image

    from .files import write_atomically

    error = np.abs(reference.color - result.color).mean(axis=-1, keepdims=True)
    error = np.repeat(np.clip(4 * error, 0, 1), 3, axis=-1)
    strip = np.concatenate([reference.color, result.color, error], axis=1)
    import io

    buf = io.BytesIO()
    Image.fromarray(np.round(strip * 255).astype(np.uint8)).save(buf, format="PNG")
    write_atomically(path, buf.getvalue())


@main.command(context_settings=CONTEXT)
@click.argument("input", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="PLY to write.")
@click.option("-k", "--neighbors", type=click.IntRange(4, 256), default=16, show_default=True,
              help="Neighbours for normal estimation.")
@click.option("--viewpoint", default=None, help="Sensor position X,Y,Z to orient normals towards.")
@click.option("--elliptical", is_flag=True, help="Fit elliptical splats to the neighbourhood (for phong).")
@click.option("--normal-field", is_flag=True, help="Fit Phong splatting's linear normal fields.")
@click.option("--sharp-features/--no-sharp-features", default=True, show_default=True,
              help="Cut splats at creases with clip lines (stored as clip_lines).")
def prepare(input, output, neighbors, viewpoint, elliptical, normal_field, sharp_features):
    """Estimate normals, splat radii and tangent frames; write a PLY.

    \b
    Example:
      surfel prepare scan.xyz -o scan.ply --viewpoint 0,0,10
    """
    from .io import write_ply
    from .preprocess import prepare as do_prepare

    cloud = load_input(input)
    view = _floats(viewpoint, 3, "--viewpoint")
    prepared, report = do_prepare(cloud.with_(radii=None, axes=None) if elliptical else cloud, k_normals=neighbors,
                                  viewpoint=None if view is None else np.array(view),
                                  elliptical=elliptical, normal_field=normal_field, sharp_features=sharp_features)
    write_ply(prepared, output)
    click.echo(f"{output}: {len(prepared)} points; " + ", ".join(f"{k}: {v}" for k, v in report.items()), err=True)


@main.command(context_settings=CONTEXT)
@click.argument("input", required=False, type=click.Path(dir_okay=False))
@click.option("--demo", is_flag=True, help="View the bundled demo model.")
@click.option("--method", "-m", default="deferred", show_default=True)
@click.option("--shading", type=click.Choice(["lambert", "phong", "none", "normals", "depth"]), default="phong",
              show_default=True)
@click.option("--size", default="800x800", show_default=True, help="Window size WxH.")
@click.option("--screenshot", type=click.Path(dir_okay=False), default=None,
              help="Draw one frame in the window, save it as PNG and exit (for scripts and tests).")
def view(input, demo, method, shading, size, screenshot):
    """Open INPUT in an interactive window (needs the view extra: pip install 'surfel[view]').

    \b
    Mouse: left drag orbits, right drag pans, wheel zooms. Keys: 1-9 method, e EWA filter,
    + - LOD error, s shading, b back-face culling, r reset, h help, q quit.
    Example:
      surfel view bunny.obj --method phong
      xvfb-run surfel view bunny.obj --screenshot shot.png
    """
    from .methods import get_method
    from .viewer import view as open_view

    if demo == (input is not None):
        raise click.UsageError("give an INPUT file or --demo (not both)")
    get_method(method)
    if demo:
        from .data import demo_cloud

        cloud = demo_cloud()
    else:
        cloud = load_input(input)
    open_view(cloud, method=method, shading=shading, size=_size(size), screenshot=screenshot)


@main.command(context_settings=CONTEXT)
@click.argument("input", type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Animation to write (.gif, or .mp4 with the video extra).")
@click.option("--frames", type=click.IntRange(1, 3600), default=36, show_default=True)
@click.option("--method", "-m", default="deferred", show_default=True)
@click.option("--size", default="512x512", show_default=True)
@click.option("--elevation", type=float, default=15.0, show_default=True, help="Degrees above the horizon.")
@click.option("--fps", type=float, default=12.0, show_default=True)
@click.option("--shading", type=click.Choice(["lambert", "phong", "none", "normals", "depth"]), default="phong",
              show_default=True)
def turntable(input, output, frames, method, size, elevation, fps, shading):
    """Render an orbit around INPUT to an animated GIF or MP4 (a .lod hierarchy or a COPC file
    is read lazily, each frame at 1 pixel of error).

    \b
    Example:
      surfel turntable bunny.obj -o bunny.gif --frames 24 --method phong
    """
    from .turntable import turntable as do_turntable

    cloud = open_input(input)
    do_turntable(cloud, output, frames=frames, method=method, size=_size(size), elevation=elevation, fps=fps,
                 shading=shading)
    click.echo(f"{output}: {frames} frames of {method}", err=True)


@main.group(context_settings=CONTEXT)
def lod():
    """Level of detail: sequential point trees (Dachsbacher et al. 2003)."""


@lod.command("build", context_settings=CONTEXT)
@click.argument("input", type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(),
              help="Hierarchy to write: NAME.lod.npz (one file, in memory), NAME.lod (a directory, out of core) "
                   "or NAME.copc.laz (COPC: opens in PDAL, QGIS, Potree; normals and radii as extra bytes).")
@click.option("--stats", type=click.Path(dir_okay=False), default=None, help="Write build statistics (.json).")
@click.option("--memory", default="4GB", show_default=True,
              help="Out of core: peak memory budget (e.g. 512MB, 4GB); bounds the partition size.")
@click.option("--resume", is_flag=True, help="Out of core: continue an interrupted build (NAME.lod.partial).")
def lod_build(input, output, stats, memory, resume):
    """Build the point-tree hierarchy of INPUT; render the result with --lod-error PX.

    INPUT may be a directory of tiles, read as one cloud. With -o NAME.lod (or an existing
    directory) the build is out of core: the input is streamed and partitioned, peak memory
    stays within --memory whatever its size, and renders read NAME.lod lazily.

    \b
    Example:
      surfel lod build scan.laz -o scan.lod.npz --stats build.json
      surfel render scan.lod.npz -o far.png --lod-error 1 --zoom 4
      surfel lod build huge.ply -o huge.lod --memory 4GB
      surfel render huge.lod -o far.png --lod-error 1 --point-budget 5000000
      surfel lod build scan.laz -o scan.copc.laz
    """
    import os

    if output.lower().endswith(".copc.laz"):
        if resume:
            raise click.UsageError("--resume applies to out-of-core builds (-o NAME.lod)")
        from .lod.copc_write import build_command as build_copc

        result = build_copc(input, output, stats)
        click.echo(f"{output}: {result['points']} points, {result['nodes']} COPC nodes (depth {result['depth']}), "
                   f"{result['bytes'] / 1e6:.1f} MB in {result['ms']:.0f} ms", err=True)
        return

    if output.rstrip("/").endswith(".lod") or os.path.isdir(output):
        from .lod.outofcore import build_outofcore, parse_size

        result = build_outofcore(input, output.rstrip("/"), memory=parse_size(memory), resume=resume,
                                 stats_path=stats)
        click.echo(f"{output}: {result['points']} points, {result['nodes']} nodes in {result['partitions']} "
                   f"partitions, {result['ms'] / 1000:.0f} s ({result['points_per_s'] / 1e6:.2f} M points/s)",
                   err=True)
        return
    if resume:
        raise click.UsageError("--resume applies to out-of-core builds (-o NAME.lod)")
    from .lod import build_command

    result = build_command(input, output, stats)
    click.echo(f"{output}: {result['points']} points, {result['nodes']} nodes in {result['ms']:.0f} ms "
               f"({result['points_per_s'] / 1e6:.2f} M points/s)", err=True)


@main.command(context_settings=CONTEXT)
@click.option("--input", "input_path", type=click.Path(dir_okay=False), default=None,
              help="Model to replicate (default: the demo model).")
@click.option("--points", type=click.IntRange(1), default=None,
              help="Replicate (or subsample) and jitter the input to N points "
                   "[default: the input as it is; 1,000,000 for the demo model].")
@click.option("--size", default="1024x1024", show_default=True)
@click.option("--methods", default="points,gaussian,deferred", show_default=True,
              help="Comma-separated, each NAME or NAME@BACKEND.")
@click.option("--frames", type=click.IntRange(1), default=5, show_default=True,
              help="Timed frames per method (after one warm-up).")
@click.option("--lod-error", type=float, default=None, metavar="PX", help="Add a row per method with this LOD error.")
@click.option("--zoom", type=float, default=1.0, show_default=True,
              help="Camera this many times farther than the default framing.")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list of rows.")
def bench(input_path, points, size, methods, frames, lod_error, zoom, as_json):
    """Median ms per frame and million splats per second of each method, in one process.

    \b
    Example:
      surfel bench --methods points@gl,deferred,ewa@cpu --points 1000000 --size 1024x1024 --json
    """
    from .bench import run

    if input_path:
        cloud = load_input(input_path)
    else:
        from .data import demo_cloud

        cloud = demo_cloud()
        points = points or 1_000_000
    rows = run(cloud, [m.strip() for m in methods.split(",") if m.strip()], points=points, size=_size(size),
               frames=frames, lod_error=lod_error, zoom=zoom)
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    click.echo(f"{rows[0]['points']} points, {size}, renderer: {rows[0]['renderer']}")
    for row in rows:
        lod = f" lod {row['lod']}px" if "lod" in row else ""
        click.echo(f"{row['method'] + '@' + row['backend'] + lod:24s} {row['ms']:9.1f} ms  "
                   f"{row['msplats_per_s']:7.2f} Msplats/s  ({row['splats']} splats)")


@main.command(context_settings=CONTEXT)
@click.argument("jobs", required=False, type=click.Path())
@click.option("--turntable", type=click.IntRange(1, 3600), default=None, metavar="N",
              help="Render N orbit frames of the input JOBS (or --demo): the cameras of `surfel turntable`.")
@click.option("-o", "--output", default=None,
              help="With --turntable: PNG name, {frame} numbered (e.g. f-{frame:03d}.png).")
@click.option("--method", "-m", default=None, help="Rendering method of every job that names none (default deferred).")
@click.option("--demo", is_flag=True, help="With --turntable: the bundled demo model.")
@click.option("--depth", default=None, help="With --turntable: depth .npy name, {frame} numbered.")
@click.option("--normals", default=None, help="With --turntable: normals .npy name, {frame} numbered.")
@click.option("--stats", default=None, help="With --turntable: stats .json name, {frame} numbered.")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="A running Dask scheduler (tcp://host:port, or its scheduler file) instead of a local cluster.")
@click.option("--workers", type=click.IntRange(1, 256), default=None,
              help="Worker processes of the local cluster [default: one per core, at most one per job].")
@click.option("--retries", type=click.IntRange(0, 10), default=2, show_default=True,
              help="Retries of a job that crashes.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@camera_options
@render_options
def batch(jobs, turntable, output, method, demo, depth, normals, stats, scheduler, workers, retries, as_json, **kw):
    """Render the jobs of JOBS (a JSON or YAML list of `surfel render` options) on Dask distributed.

    Each job is a mapping of `surfel render`'s options (input, output, method, size, azimuth, depth,
    ...) and gives exactly that command's files; relative paths are taken from the current
    directory. Workers read the inputs at the same absolute paths (remote workers need a shared
    file system); this command writes the outputs. Render options on this command line apply to
    every job that does not set them (with --turntable, as in `surfel render`: --size defaults to
    1024x1024, --elevation to 15). Exit status 1 if a job failed (the others are written), 2 if
    a job is invalid (none is run). Needs the distributed extra: pip install 'surfel[distributed]'.

    \b
    Examples:
      surfel batch renders.yaml --workers 2
      surfel batch spot.obj --turntable 24 -o frames/spot-{frame:02d}.png --size 512x512
      surfel batch renders.json --scheduler tcp://10.0.0.5:8786 --json
    """
    from click.core import ParameterSource

    from .batch import TURNTABLE_ELEVATION, make_jobs, read_jobs_file, run_batch, turntable_jobs

    ctx = click.get_current_context()
    defaults = {k: v for k, v in kw.items() if ctx.get_parameter_source(k) is not ParameterSource.DEFAULT}
    if method is not None:
        defaults["method"] = method
    if turntable is None:
        if demo or output or depth or normals or stats:
            raise click.UsageError("--demo, -o, --depth, --normals and --stats go with --turntable; "
                                   "jobs name their outputs")
        if jobs is None:
            raise click.UsageError("give a JOBS file, or an input with --turntable N")
        specs, where = read_jobs_file(jobs), jobs
    else:
        if demo == (jobs is not None):
            raise click.UsageError("with --turntable give an input file or --demo (not both)")
        if output is None:
            raise click.UsageError("--turntable needs -o/--output")
        fixed = sorted({"view", "azimuth", "eye", "opencv"} & set(defaults))
        if fixed:
            raise click.UsageError(f"--turntable sets the camera; drop --{', --'.join(fixed)}")
        specs = turntable_jobs(turntable, output, input=jobs, demo=demo, depth=depth, normals=normals, stats=stats,
                               elevation=defaults.pop("elevation", TURNTABLE_ELEVATION))
        where = "turntable"
    summary = run_batch(make_jobs(specs, defaults=defaults, where=where), scheduler=scheduler, workers=workers,
                        retries=retries)
    click.echo(json.dumps(summary.as_dict(), indent=2) if as_json else summary.text())
    if summary.failed:
        ctx.exit(1)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
