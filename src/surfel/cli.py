"""The `surfel` command line: declarations. The options come from `request.OPTIONS`; what a
command does lives in `request`, `rendering`, `batch`, `turntable`, `viewer`, `bench`,
`metrics`, `preprocess` and `lod`. Every user-fixable error, a usage error too, is one line on
stderr (`surfel: error: ...`) and exit status 2.
"""

from __future__ import annotations

import json
import sys

import click

from .compile_notice import compile_notice
from .errors import SurfelError
from .methods import DEFAULT_METHOD, get_method
from .pages import no_huge_pages
from .request import (
    CAMERA,
    OPTIONS,
    PAGE_COMMAND,
    RENDER,
    RENDER_COMMAND,
    SAMPLE,
    SCAN,
    TURNTABLE_COMMAND,
    TURNTABLE_ELEVATION,
    TURNTABLE_SIZE,
    VIEW_SIZE,
    refuse_folder,
)
from .threads import passive_openmp_workers

CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}


def table_options(*names: str, required: tuple[str, ...] = (), defaults: dict | None = None,
                  helps: dict | None = None):
    """The click declarations of these rows of `request.OPTIONS`, in order. Every value comes
    in as given (text, or a flag's bool; None when not given) for `request` to parse.
    `defaults` and `helps`: the shown default and help where the command's differ from the table's."""
    defaults, helps = defaults or {}, helps or {}

    def decorate(function):
        for name in reversed(names):
            option = OPTIONS[name]
            if name == "input":
                function = click.argument("input", required="input" in required, type=click.Path())(function)
                continue
            declarations = [name, *([option.short] if option.short else []), option.flag or option.label]
            shown = defaults.get(name, option.shown_default())
            help = helps.get(name, option.help) + (f"  [default: {shown}]" if shown is not None else "")
            unset = {} if name in required else {"default": None}  # None: not given, a flag too
            function = click.option(*declarations, is_flag=option.parse is None or None, required=name in required,
                                    help=help, metavar=option.metavar, **unset)(function)
        return function

    return decorate


class SurfelGroup(click.Group):
    """One line on stderr and exit status 2 for every error the user can fix: SurfelErrors,
    usage errors (click prints three lines of its own), running out of memory."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            status = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.NoArgsIsHelpError as exc:  # a bare `surfel` or `surfel lod`: the help
            exc.show()
            status = 2
        except (SurfelError, click.ClickException) as exc:
            message = exc.format_message() if isinstance(exc, click.ClickException) else str(exc)
            click.echo(f"surfel: error: {' '.join(message.split())}", err=True)
            status = 2
        except MemoryError:
            click.echo("surfel: error: out of memory", err=True)
            status = 2
        except click.Abort:
            click.echo("surfel: aborted", err=True)
            status = 1
        if not standalone_mode:
            return status
        sys.exit(status if isinstance(status, int) else 0)


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
    no_huge_pages()
    passive_openmp_workers()
    click.get_current_context().with_resource(compile_notice(sys.stderr))


@main.command(context_settings=CONTEXT)
@table_options(*RENDER_COMMAND)
def render(**values):
    """Render INPUT (PLY, OBJ, STL, OFF, LAS/LAZ, E57, XYZ/PTS/TXT, NPZ, a .lod hierarchy, COPC) to a PNG.

    A .lod directory (`surfel lod build -o NAME.lod`) or a COPC file (NAME.copc.laz) is read
    lazily: only the nodes the view selects at --lod-error (default 1 pixel) are loaded, at
    most --point-budget. An option the method does not use is refused.

    \b
    Example:
      surfel render bunny.obj -o bunny.png --method deferred --size 512x512
      surfel render big.lod -o far.png --lod-error 1 --point-budget 5000000
    """
    from .cloud import PointCloud
    from .preprocess.mesh_samples import OPEN_SHARE, open_face_share
    from .rendering import Renderer
    from .request import parse_render

    request = parse_render(values)
    request.check_outputs()
    cloud = request.open_input()
    result = request.render(Renderer(), cloud)
    request.write(result)
    s = result.stats
    click.echo(f"{request.outputs.png}: {result.width}x{result.height} {request.method}@{s['backend']} "
               f"{s['splats']} splats in {s['ms']:.0f} ms", err=True)
    if isinstance(cloud, PointCloud) and cloud.is_mesh and request.method != "mesh":
        share = open_face_share(cloud)
        if share > OPEN_SHARE:
            click.echo(f"{request.input}: {share:.0%} of its area lies in faces larger than its vertices' splats "
                       f"reach (a CAD export?), which leave them open; `surfel sample {request.input} -o "
                       "POINTS.ply` spreads points over them", err=True)


@main.command("export-html", context_settings=CONTEXT)
@table_options(*PAGE_COMMAND, required=("output",), defaults={"point_budget": "300000"},
               helps={"output": "HTML page to write.", "method": "phong, deferred or gaussian.",
                      "point_budget": "Above N points the page draws a sequential point tree.",
                      "supersample": "Samples per pixel side, 1 to 4 (default: the method's, 2 for phong)."})
def export_html(**values):
    """Write one self-contained HTML page that splats INPUT in the browser (WebGL2, offline).

    It opens at the camera of these flags (as `surfel render`), orbits, pans and zooms with
    the mouse, switches method, colour mode and shading; PAGE.html#capture shows the canvas
    alone. A .lod hierarchy or a COPC file gives the page its uniform cut.

    \b
    Example:
      surfel export-html bunny.obj -o bunny.html --method deferred --size 800x600
      surfel export-html scan.laz -o scan.html --color elevation --shading edl --view iso
    """
    from .files import check_output
    from .rendering import Renderer
    from .web import export_html as do_export
    from .web.export import page_request

    request = page_request(values)
    check_output(request.outputs.png, "--output")
    cloud = request.open_input()
    report = do_export(cloud, request.camera.camera(cloud), request.outputs.png, method=request.method,
                       options=request.options, renderer=Renderer())
    click.echo(f"{request.outputs.png}: {report['points']} points, {report['bytes'] / 1e6:.1f} MB", err=True)


@main.command(context_settings=CONTEXT)
def methods():
    """List the rendering methods and their backends; the default is marked.

    \b
    Example:
      surfel methods
    """
    from .methods import METHODS

    for m in METHODS.values():
        mark = " (the default)" if m.name == DEFAULT_METHOD else ""
        click.echo(f"{m.name:14s} {','.join(m.backends):8s} {m.summary}{mark}")


@main.command(context_settings=CONTEXT)
@click.argument("input", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def info(input, as_json):
    """Counts, bounds, attributes, what would be estimated, and the OpenGL renderer.

    \b
    Example:
      surfel info scan.laz
    """
    from .attributes import summarize, summary_lines
    from .gl.context import gl_available, renderer_string
    from .io import load
    from .lod.source import open_source
    from .preprocess.mesh_samples import open_face_share

    source = open_source(input)
    if source is not None:  # described from its metadata, without loading its points
        lo, hi = source.bounds
        report = {"file": str(input), "kind": type(source).__name__, "points": source.total_points,
                  "bounds_min": lo.tolist(), "bounds_max": hi.tolist(), "geospatial": source.geospatial,
                  **(source.describe() if hasattr(source, "describe") else {}),
                  "opengl": renderer_string() if gl_available() else None}
    else:
        refuse_folder(input)
        cloud = load(input)
        lo, hi = cloud.bounds
        estimate = [name for name in ("normals", "radii", "axes") if getattr(cloud, name) is None]
        report = {
            "file": str(input), "points": len(cloud), "faces": 0 if cloud.faces is None else len(cloud.faces),
            # a CAD export's share of area in faces its vertices leave open (`surfel sample` them)
            "open_faces": round(open_face_share(cloud), 3) if cloud.is_mesh else None,
            "bounds_min": lo.tolist(), "bounds_max": hi.tolist(), "local_origin": cloud.local_origin.tolist(),
            "attributes": cloud.attribute_names(), "schema": summarize(cloud.attributes, cloud.schema),
            "would_estimate": estimate, "geospatial": cloud.geospatial,
            "sensors": None if cloud.sensors is None else cloud.sensors.tolist(),
            "opengl": renderer_string() if gl_available() else None,
        }
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    absent = {"sensors": "none (the file holds no scanner positions)",
              "opengl": "unavailable (use --backend cpu)"}
    for key, value in report.items():
        if key == "schema":
            value = "".join(f"\n  {line}" for line in summary_lines(value)) or "none"
        click.echo(f"{key:15s} {value if value is not None else absent.get(key, 'none')}")


@main.command(context_settings=CONTEXT)
@click.argument("mesh", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default=None,
              help="Side-by-side PNG: mesh, method, error x4 (default compare-METHOD.png).")
@click.option("--json", "as_json", is_flag=True, help="Print the metrics as JSON.")
@click.option("--every", type=click.IntRange(1), default=1, show_default=True, metavar="N",
              help="Splat every Nth vertex only (normals kept, splat sizes estimated): sparse sampling.")
@table_options("method", "backend", *CAMERA, *RENDER)
def compare(mesh, output, as_json, every, **values):
    """Render MESH's ground truth and METHOD on its vertices; print PSNR, holes and spill.

    \b
    Examples:
      surfel compare bunny.obj --method deferred --size 512x512 --shading lambert --json
      surfel compare bunny.obj --method phong --every 4 --size 512x512 --shading lambert
    """
    from .files import check_output, write_atomically
    from .io import load
    from .metrics import compare_with_mesh, side_by_side
    from .rendering import Renderer
    from .request import parse_render

    request = parse_render({**values, "input": mesh}, require_output=False)
    if get_method(request.method).needs_mesh:
        raise SurfelError(f"--method: compare draws the method on {mesh}'s vertices, and {request.method!r} "
                          "draws faces; choose a point method")
    output = output or f"compare-{request.method}.png"
    check_output(output, "--output", (".png",))
    cloud = load(mesh)
    reference, result, metrics = compare_with_mesh(cloud, request.camera.camera(cloud), request.method,
                                                   request.options, Renderer(), backend=request.backend,
                                                   every=every)
    write_atomically(output, side_by_side(reference, result))
    if as_json:
        click.echo(json.dumps(metrics, indent=2))
    else:
        click.echo(f"{request.method}@{metrics['backend']}: PSNR {metrics['psnr']:.2f} dB, interior PSNR "
                   f"{metrics['interior_psnr']:.2f} dB, holes {100 * metrics['holes']:.3f}%, "
                   f"spill {100 * metrics['spill']:.3f}%  ({output})")


@main.command(context_settings=CONTEXT)
@click.argument("input", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, help="PLY to write.")
@click.option("-k", "--neighbors", type=click.IntRange(4, 256), default=16, show_default=True,
              help="Neighbours for normal estimation.")
@click.option("--elliptical", is_flag=True, help="Fit elliptical splats to the neighbourhood (for phong).")
@click.option("--normal-field", is_flag=True, help="Fit Phong splatting's linear normal fields.")
@click.option("--sharp-features/--no-sharp-features", default=True, show_default=True,
              help="Cut splats at creases with clip lines (stored as clip_lines).")
@click.option("--smooth", is_flag=True, help="Denoise the positions first: move them onto the points' MLS surface "
              "(raw scans).")
@table_options("sensor")
def prepare(input, output, neighbors, sensor, elliptical, normal_field, sharp_features, smooth):
    """Estimate normals, splat radii and tangent frames; write a PLY.

    \b
    Example:
      surfel prepare scan.xyz -o scan.ply --sensor 0,0,10
      surfel prepare scan.ply -o smooth.ply --smooth
    """
    from .files import check_output
    from .io import load, write_ply
    from .lod.source import with_sensor
    from .preprocess import prepare as do_prepare
    from .request import parse_values

    position = parse_values({"sensor": sensor}, ("sensor",)).get("sensor")
    check_output(output, "--output", (".ply",))
    cloud = with_sensor(load(input), position)
    prepared, report = do_prepare(cloud.with_(radii=None, axes=None) if elliptical else cloud, k_normals=neighbors,
                                  elliptical=elliptical, normal_field=normal_field, sharp_features=sharp_features,
                                  smooth=smooth)
    write_ply(prepared, output)
    click.echo(f"{output}: {len(prepared)} points; " + ", ".join(f"{k}: {v}" for k, v in report.items()), err=True)


@main.command(context_settings=CONTEXT)
@click.argument("mesh", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, help="PLY to write: positions, the scan index, sensor positions.")
@table_options(*SCAN)
def scan(mesh, output, **values):
    """Scan MESH with a virtual range scanner: depth images from several views, samples lost at
    grazing angles, range noise along each ray, each view misregistered; no normals; the mesh's
    colours where it has them.

    \b
    Example:
      surfel scan bunny.obj -o bunny-scan.ply --views 6 --noise 0.001 --misalignment 0.0005
      surfel render bunny-scan.ply -o bunny-scan.png --method phong
    """
    from .scan import scan_command

    cloud = scan_command(mesh, output, values)
    click.echo(f"{output}: {len(cloud)} points from {len(cloud.sensors)} views", err=True)


@main.command(context_settings=CONTEXT)
@click.argument("mesh", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, help="PLY to write: positions, normals, the mesh's colours.")
@table_options(*SAMPLE)
def sample(mesh, output, **values):
    """Spread points evenly over MESH's faces, for a mesh whose vertices do not sample its
    surface (a CAD part's STL: its flat faces have vertices only on their outlines). Normals
    keep the mesh's edges sharper than --crease-angle; colours come from its vertices.

    \b
    Example:
      surfel sample part.stl -o part.ply --points 200000
      surfel render part.ply -o part.png --view iso
    """
    from .files import check_output
    from .io import load, write_ply
    from .preprocess.mesh_samples import SampleSettings, sample_surface
    from .request import parse_values

    settings = SampleSettings(**parse_values(values, SAMPLE))
    check_output(output, "--output", (".ply",))
    cloud = sample_surface(load(mesh), settings)
    write_ply(cloud, output)
    click.echo(f"{output}: {len(cloud)} points", err=True)


@main.command(context_settings=CONTEXT)
@click.option("--screenshot", type=click.Path(dir_okay=False), default=None,
              help="Draw one frame in the window, save it as PNG and exit (for scripts and tests).")
@table_options("input", "demo", "method", "shading", "color", "colormap", "size",
               defaults={"size": "x".join(map(str, VIEW_SIZE))})
def view(screenshot, **values):
    """Open INPUT in an interactive window (needs the view extra: pip install 'surfel[view]').

    \b
    Mouse: left drag orbits, right drag pans, wheel zooms. Keys: 1-9 method, e EWA filter,
    + - LOD error, s shading, c colour mode, l eye-dome lighting, b back-face culling,
    r reset, h help, q quit.
    Example:
      surfel view bunny.obj --method phong
      xvfb-run surfel view bunny.obj --screenshot shot.png
    """
    from .viewer import view_command

    view_command(values, screenshot=screenshot)


@main.command(context_settings=CONTEXT)
@table_options(*TURNTABLE_COMMAND, required=("input", "output"),
               defaults={"size": "x".join(map(str, TURNTABLE_SIZE)), "elevation": f"{TURNTABLE_ELEVATION:g}"},
               helps={"output": "Animation to write (.gif, or .mp4 with the video extra)."})
def turntable(**values):
    """Render an orbit around INPUT to an animated GIF or MP4 (a .lod hierarchy or a COPC file
    is read lazily, each frame at 1 pixel of error).

    \b
    Example:
      surfel turntable bunny.obj -o bunny.gif --frames 24 --method phong
    """
    from .turntable import turntable_command

    request = turntable_command(values)
    click.echo(f"{request.output}: {request.frames} frames of {request.method}", err=True)


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

    from .files import check_folder, check_output

    if stats is not None:
        check_output(stats, "--stats")
    if output.lower().endswith(".copc.laz"):
        if resume:
            raise click.UsageError("--resume applies to out-of-core builds (-o NAME.lod)")
        from .lod.copc_write import build_command as build_copc

        check_output(output, "--output")
        result = build_copc(input, output, stats)
        click.echo(f"{output}: {result['points']} points, {result['nodes']} COPC nodes (depth {result['depth']}), "
                   f"{result['bytes'] / 1e6:.1f} MB in {result['ms']:.0f} ms", err=True)
        return

    if output.rstrip("/").endswith(".lod") or os.path.isdir(output):
        from .lod.outofcore import build_outofcore, parse_size

        check_folder(output, "--output")
        try:
            budget = parse_size(memory)
        except SurfelError as error:
            raise SurfelError(f"--memory: {error}") from None
        result = build_outofcore(input, output.rstrip("/"), memory=budget, resume=resume, stats_path=stats)
        click.echo(f"{output}: {result['points']} points, {result['nodes']} nodes in {result['partitions']} "
                   f"partitions, {result['ms'] / 1000:.0f} s ({result['points_per_s'] / 1e6:.2f} M points/s)",
                   err=True)
        return
    if resume:
        raise click.UsageError("--resume applies to out-of-core builds (-o NAME.lod)")
    from .lod import build_command

    if not output.lower().endswith(".npz"):  # the in-memory build writes an archive, whatever the name
        raise SurfelError(f"{output}: --output must be named NAME.lod.npz (in memory), NAME.lod (a directory, "
                          "out of core) or NAME.copc.laz")
    check_output(output, "--output")
    result = build_command(input, output, stats)
    click.echo(f"{output}: {result['points']} points, {result['nodes']} nodes in {result['ms']:.0f} ms "
               f"({result['points_per_s'] / 1e6:.2f} M points/s)", err=True)


@main.command(context_settings=CONTEXT)
@click.option("--input", "input_path", type=click.Path(dir_okay=False), default=None,
              help="Model to replicate (default: the demo model).")
@click.option("--points", type=click.IntRange(1), default=None,
              help="Replicate (or subsample) and jitter the input to N points "
                   "[default: the input as it is; 1,000,000 for the demo model].")
@click.option("--methods", default="points,gaussian,deferred", show_default=True,
              help="Comma-separated, each NAME or NAME@BACKEND.")
@click.option("--frames", type=click.IntRange(1), default=5, show_default=True,
              help="Timed frames per method (after one warm-up).")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list of rows.")
@table_options("size", "lod_error", "zoom")
def bench(input_path, points, methods, frames, as_json, **values):
    """Median ms per frame and million splats per second of each method, in one process.

    \b
    Example:
      surfel bench --methods points@gl,deferred,ewa@cpu --points 1000000 --size 1024x1024 --json
    """
    from .bench import bench_command

    click.echo(bench_command(input_path, points, methods, frames, values, as_json=as_json))


@main.command(context_settings=CONTEXT)
@click.argument("jobs", required=False, type=click.Path())
@click.option("--turntable", type=click.IntRange(1, 3600), default=None, metavar="N",
              help="Render N orbit frames of the input JOBS (or --demo): the cameras of `surfel turntable`.")
@click.option("-o", "--output", default=None,
              help="With --turntable: a folder (frames FOLDER/000.png, ...), or a PNG name, {frame} numbered "
                   "(e.g. f-{frame:03d}.png) or numbered before its extension.")
@click.option("--method", "-m", default=None,
              help=f"Rendering method of every job that names none (default {DEFAULT_METHOD}).")
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
@table_options("backend", *CAMERA, *RENDER)
def batch(jobs, turntable, output, method, demo, depth, normals, stats, scheduler, workers, retries, as_json,
          **values):
    """Render the jobs of JOBS (a JSON or YAML list of `surfel render` options) on Dask distributed.

    Each job is a mapping of `surfel render`'s options (input, output, method, size, azimuth, depth,
    ...) and gives exactly that command's files; relative paths are taken from the current
    directory. Workers read the inputs at the same absolute paths (remote workers need a shared
    file system); this command writes the outputs. Render options on this command line apply to
    every job that does not set them (with --turntable, as in `surfel render`: --size defaults to
    1024x1024, --elevation to 15). Exit status 1 if a job failed (the others are written; a job
    whose output folder is missing fails), 2 if a job is invalid (none is run). Needs the
    distributed extra: pip install 'surfel[distributed]'.

    \b
    Examples:
      surfel batch renders.yaml --workers 2
      surfel batch spot.obj --turntable 24 -o frames/spot-{frame:02d}.png --size 512x512
      surfel batch renders.json --scheduler tcp://10.0.0.5:8786 --json
    """
    from .batch import batch_command

    summary = batch_command(jobs, defaults={**values, "method": method}, turntable=turntable, demo=demo,
                            outputs={"output": output, "depth": depth, "normals": normals, "stats": stats},
                            scheduler=scheduler, workers=workers, retries=retries)
    click.echo(json.dumps(summary.as_dict(), indent=2) if as_json else summary.text())
    if summary.failed:
        click.get_current_context().exit(1)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
