"""Measure the README's numbers and write them into it, so that none is copied by hand.

    python benchmarks/readme_numbers.py SECTION [SECTION ...]   # or: all
    python benchmarks/readme_numbers.py --list                  # the sections, with a rough cost

Each section runs its measurements (the `surfel` commands, or the library calls those
commands make) and rewrites the README's block between `<!-- numbers:NAME -->` and
`<!-- /numbers:NAME -->`, ending it with the commands it ran and the machine it ran on (CPU
count, OpenGL renderer, load average). Nothing else in the README changes; the file is
replaced atomically after each section. Run it from anywhere: paths are taken from the
repository root. Inputs: ../shared/data/{stanford-bunny,spot,fandisk}.obj and
autzen_trim.laz (beside the checkout, or --data), Debian's Chromium with Playwright for the
page sections, dask for batch. `all` includes build100m, which writes a 2.4 GB cloud under
--scratch and takes 15 minutes or more.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DATA = ROOT.parent / "shared" / "data"
RUNS = 3  # repeated timings: the README gives the range over runs, since the machine is shared
MODELS = {"bunny": "stanford-bunny.obj", "spot": "spot.obj", "fandisk": "fandisk.obj"}


@dataclass
class Context:
    """What a section needs: the data folder, a scratch folder, and the commands it ran."""

    data: Path
    scratch: Path
    commands: list[str]

    def model(self, name: str) -> Path:
        return self.data / MODELS[name]

    def shown(self, path: Path) -> str:
        """A path as the README's commands write it: a temporary file by its name in the scratch
        folder, the shared data relative to the repository root."""
        path = Path(path)
        if path.is_relative_to(self.scratch):
            return str(path.relative_to(self.scratch))
        beside = Path(os.path.abspath(path)).is_relative_to(ROOT.parent)  # not resolved: ../shared may be a link
        return os.path.relpath(os.path.abspath(path), ROOT) if beside else str(path)

    def argv(self, args) -> tuple[list[str], str]:
        """The arguments to run, and as the footer shows them."""
        return [str(a) for a in args], shlex.join(self.shown(a) if isinstance(a, Path) else str(a) for a in args)

    def record(self, command: str, note: str = "") -> None:
        """Name a command in the block's footer (with a note: how often, what varied)."""
        self.commands.append(f"`{command}`" + (f" ({note})" if note else ""))

    def surfel(self, *args, note: str = "", record: bool = True) -> str:
        """Run `surfel ARGS` (this interpreter's), record the command, return its stdout."""
        args, shown = self.argv(args)
        if record:
            self.record("surfel " + shown, note)
        return run_checked([sys.executable, "-m", "surfel.cli", *args])

    def script(self, name: str, *args, note: str = "", record: bool = True) -> str:
        """Run `python benchmarks/NAME ARGS`, record it, return its stdout."""
        args, shown = self.argv(args)
        if record:
            self.record(f"python benchmarks/{name} " + shown, note)
        return run_checked([sys.executable, str(ROOT / "benchmarks" / name), *args])


def run_checked(argv: list[str]) -> str:
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{shlex.join(argv)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return done.stdout


def compare_request(path: Path, method: str, backend: str | None = None, **values):
    """The request `surfel compare PATH --method M [--backend B] --size 512x512 --shading lambert`
    makes (its own parser, so its defaults and camera)."""
    from surfel.request import parse_render

    given = {"input": str(path), "method": method, "backend": backend, "size": "512x512", "shading": "lambert",
             **values}
    return parse_render(given, require_output=False)


# ---------------------------------------------------------------------------------------------
# Quality


def quality_table(data: Path) -> str:
    """Every method on every model's vertices against the model's mesh, as `surfel compare
    MESH --method NAME --size 512x512 --shading lambert` measures it (front view): PSNR of the
    whole image, holes; and the bunny's ms per frame as `surfel bench --input BUNNY --methods
    NAME@BACKEND --size 512x512 --frames 1` measures it (after a warm-up frame, which compiles
    the shaders and uploads the splats). The one source of the README's quality table
    (docs/gallery/make_gallery.py runs it too)."""
    from surfel.bench import run as bench
    from surfel.io import load
    from surfel.methods import METHODS
    from surfel.metrics import compare_with_mesh
    from surfel.rendering import Renderer

    meshes = {name: load(data / file) for name, file in MODELS.items()}
    rows = ["| method | backend | " + " | ".join(f"{m} PSNR / holes" for m in meshes) + " | ms (bunny) |",
            "|---|---|" + "---|" * len(meshes) + "---|"]
    with Renderer() as renderer:
        for method in METHODS.values():
            if method.name == "mesh":
                continue
            for backend in method.backends:
                cells, ms = [], ""
                for name, mesh in meshes.items():
                    request = compare_request(data / MODELS[name], method.name, backend)
                    arguments = (mesh, request.camera.camera(mesh), method.name, request.options, renderer)
                    metrics = compare_with_mesh(*arguments, backend=backend)[2]
                    cells.append(f"{metrics['psnr']:.1f} dB / {100 * metrics['holes']:.3f}%")
                    if name == "bunny":
                        timed = bench(mesh.with_(faces=None), [f"{method.name}@{backend}"], size=(512, 512), frames=1)
                        ms = f"{timed[0]['ms']:.0f}"
                rows.append(f"| `{method.name}` | {backend} | " + " | ".join(cells) + f" | {ms} |")
                print(rows[-1], file=sys.stderr)
    return "\n".join(rows)


def section_quality(ctx: Context) -> str:
    ctx.record(f"surfel compare {ctx.shown(ctx.data)}/MODEL.obj --method M --backend B --size 512x512 "
               "--shading lambert", "in one process, for every model, method and backend")
    ctx.record(f"surfel bench --input {ctx.shown(ctx.model('bunny'))} --methods M@B --size 512x512 --frames 1",
               "in the same process: the ms column")
    return quality_table(ctx.data)


def section_sparse(ctx: Context) -> str:
    from surfel.io import load
    from surfel.metrics import compare_with_mesh
    from surfel.rendering import Renderer

    path = ctx.model("bunny")
    mesh = load(path)
    methods = ("gaussian", "deferred", "phong")
    rows = ["| view | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    with Renderer() as renderer:
        for view in ("front", "right"):
            cells = []
            for method in methods:
                request = compare_request(path, method, view=view)
                metrics = compare_with_mesh(mesh, request.camera.camera(mesh), method, request.options, renderer,
                                            every=4)[2]
                cells.append(f"{metrics['interior_psnr']:.1f} dB")
            rows.append(f"| {view} | " + " | ".join(cells) + " |")
    ctx.record(f"surfel compare {ctx.shown(path)} --every 4 --method M --size 512x512 --shading lambert --view V",
               "in one process, M: gaussian, deferred, phong; V: front, right")
    return "\n".join(rows)


def section_dense(ctx: Context) -> str:
    """400k points sampled uniformly on the bunny's surface (normals interpolated from its
    vertices), front view, against the mesh."""
    import numpy as np
    import trimesh

    from surfel.cloud import PointCloud
    from surfel.io import load
    from surfel.metrics import compare_results
    from surfel.rendering import Renderer

    path = ctx.model("bunny")
    mesh = load(path)
    surface = trimesh.Trimesh(mesh.positions, mesh.faces, process=False)
    points, face = trimesh.sample.sample_surface(surface, 400_000, seed=1)
    weights = trimesh.triangles.points_to_barycentric(surface.triangles[face], points)
    normals = (weights[..., None] * mesh.normals[mesh.faces[face]]).sum(1)
    cloud = PointCloud(points, normals=normals / np.linalg.norm(normals, axis=1, keepdims=True))
    psnr = {}
    with Renderer() as renderer:
        for method in ("phong", "gaussian", "deferred"):
            request = compare_request(path, method, background="0,0,0")
            camera = request.camera.camera(mesh)
            reference = renderer.render(mesh, camera, "mesh", options=compare_request(path, "mesh",
                                                                                       background="0,0,0").options)
            psnr[method] = compare_results(reference, renderer.render(cloud, camera, method, options=request.options))
    ctx.record("surfel render POINTS --method M --size 512x512 --shading lambert",
               f"in one process, POINTS: 400k points sampled on {ctx.shown(path)} by "
               "trimesh.sample.sample_surface, seed 1; PSNR against the mesh as `surfel compare` computes it")
    return (f"phong {psnr['phong']['psnr']:.1f} dB, gaussian {psnr['gaussian']['psnr']:.1f} dB, "
            f"deferred {psnr['deferred']['psnr']:.1f} dB.")


# ---------------------------------------------------------------------------------------------
# Speed


def bench(ctx: Context, *args, runs: int = 1) -> list[list[dict]]:
    """`surfel bench ARGS --json`, `runs` times: each run's rows."""
    note = f"{runs} runs" if runs > 1 else ""
    return [json.loads(ctx.surfel("bench", *args, "--json", note=note, record=i == 0)) for i in range(runs)]


def section_speed(ctx: Context) -> str:
    rows = bench(ctx, "--input", ctx.model("bunny"), "--methods",
                 "points@gl,gaussian@gl,gaussian@cpu,deferred@gl,deferred@cpu,phong@gl,phong@cpu,object-space@gl,"
                 "ewa@gl,ewa@cpu", "--points", "1000000",
                 "--size", "1024x1024", "--frames", "3")[0]
    command = ctx.commands[-1].strip("`")
    lines = ["```", command.removesuffix(" --json"), "```", "",
             "| method | samples a pixel | ms / frame | Msplats/s |", "|---|---|---|---|"]
    lines += [f"| {r['method']}@{r['backend']} | {r['supersample'] ** 2} | {r['ms']:.0f} | {r['msplats_per_s']:.2f} |"
              for r in rows]
    return "\n".join(lines)


def span(values, digits: int = 0, unit: str = "") -> str:
    """'a-b' over repeated runs (or one value when they agree at this precision)."""
    low, high = f"{min(values):.{digits}f}", f"{max(values):.{digits}f}"
    return (low if low == high else f"{low}-{high}") + unit


def section_demo(ctx: Context) -> str:
    """Issue 18's ratios, in one run each: the splat rates of deferred on the GL path and on
    the CPU against naive point sprites on the GL path."""
    runs = bench(ctx, "--input", ctx.model("bunny"), "--methods", "points@gl,deferred@gl,deferred@cpu", "--points",
                 "1000000", "--size", "1024x1024", runs=RUNS)

    def ms(i):
        return [run[i]["ms"] for run in runs]

    def rate(i):  # method i's splat rate over points'
        return [run[0]["ms"] / run[i]["ms"] for run in runs]
    return (f"Against naive point sprites (`surfel bench --input ../shared/data/stanford-bunny.obj --methods "
            f"points@gl,deferred@gl,deferred@cpu --points 1000000 --size 1024x1024`), {RUNS} runs: points@gl "
            f"{span(ms(0))} ms, deferred@gl {span(ms(1))} ms ({span(rate(1), 2)}x points' splat rate), deferred@cpu "
            f"{span(ms(2))} ms ({span(rate(2), 1)}x).")


def section_lod(ctx: Context) -> str:
    rows = bench(ctx, "--input", ctx.model("bunny"), "--methods", "deferred@gl,deferred@cpu,points@gl", "--points",
                 "4000000", "--size", "1024x1024", "--zoom", "4", "--lod-error", "1", "--frames", "3")[0]
    full = {f"{r['method']}@{r['backend']}": r for r in rows if "lod" not in r}
    lod = {f"{r['method']}@{r['backend']}": r for r in rows if "lod" in r}
    points = full["points@gl"]["points"]
    parts = [f"{name} {full[name]['ms']:.0f} ms at full detail, {lod[name]['ms']:.0f} ms with `--lod-error 1` "
             f"({full[name]['ms'] / lod[name]['ms']:.0f}x faster)" for name in full]
    return (f"Level of detail, {points / 1e6:g}M points at 4x the default distance (`surfel bench --input "
            f"../shared/data/stanford-bunny.obj --methods deferred@gl,deferred@cpu,points@gl --points 4000000 "
            f"--size 1024x1024 --zoom 4 --lod-error 1 --frames 3`), {lod['points@gl']['splats']:,} of "
            f"{points / 1e6:g}M splats drawn with `--lod-error 1`: " + "; ".join(parts) + ".")


# ---------------------------------------------------------------------------------------------
# The page


def section_page(ctx: Context) -> str:
    runs = [json.loads(ctx.script("page_frame_time.py", "--json", note=f"{RUNS} runs", record=i == 0))
            for i in range(RUNS)]
    first = runs[0]
    gl_lod = [next(row["ms"] for row in run["gl"] if "lod" in row) / 1000 for run in runs]
    width, height = first["size"]
    return (f"{first['points'] / 1e6:g}M points (`surfel bench`'s cloud, {width}x{height}, `python "
            f"benchmarks/page_frame_time.py`) make a {first['page_bytes'] / 1e6:.0f} MB page "
            f"({first['page_bytes'] / first['page_nodes']:.0f} bytes a point) that opens in "
            f"{span([r['load_s'] for r in runs], 0, ' s')} in headless Chromium here; it draws "
            f"{first['rest_splats'] / 1000:.0f}k splats in {span([r['rest_ms'] / 1000 for r in runs], 2, ' s')} a "
            f"frame at rest and {span([r['moving_ms'] / 1000 for r in runs], 2, ' s')} while the camera moves, on "
            f"{first['page_renderer']}, where the GL path on {first['gl'][0]['renderer']} takes "
            f"{span(gl_lod, 2, ' s')} for the same view and LOD (the ranges: {RUNS} runs, with the other load on "
            f"this machine). A GPU browser is far faster.")


def section_page_match(ctx: Context) -> str:
    """The page's picture against `surfel render`'s, demo model, same flags (the default method both)."""
    import numpy as np
    from page_frame_time import FLAGS
    from PIL import Image
    from playwright.sync_api import sync_playwright

    from surfel.metrics import psnr

    flags = ["--size", "800x600"]
    reference, page_path = ctx.scratch / "render.png", ctx.scratch / "page.html"
    ctx.surfel("render", "--demo", "-o", reference, *flags)
    ctx.surfel("export-html", "--demo", "-o", page_path, *flags)
    shot = ctx.scratch / "page.png"
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS, headless=True)
        page = browser.new_page(viewport={"width": 800, "height": 600}, device_scale_factor=1)
        page.goto(page_path.as_uri() + "#capture")
        page.wait_for_function("window.surfelStats && (surfelStats.ready || surfelStats.error)", timeout=600_000)
        error = page.evaluate("surfelStats.error")
        if error:
            raise RuntimeError(f"page.html: {error}")
        page.screenshot(path=str(shot))
        browser.close()
    ctx.record("chromium page.html#capture", "headless, through Playwright: its screenshot at 800x600, PSNR "
               "against render.png")
    rgb = [np.asarray(Image.open(f).convert("RGB"), np.float64) for f in (reference, shot)]
    return f"The page against `surfel render --demo --size 800x600`: {psnr(*rgb):.0f} dB PSNR."


# ---------------------------------------------------------------------------------------------
# Batches, COPC, out of core


def section_batch(ctx: Context) -> str:
    frames, spot = 24, ctx.model("spot")
    batch_dir, single_dir = ctx.scratch / "batch", ctx.scratch / "single"
    batch_dir.mkdir()
    single_dir.mkdir()
    start = time.perf_counter()
    ctx.surfel("batch", spot, "--turntable", frames, "-o", f"{batch_dir}/", "--size", "512x512", "--workers", 2,
               record=False)
    batch_s = time.perf_counter() - start
    start = time.perf_counter()
    for i in range(frames):
        ctx.surfel("render", spot, "-o", single_dir / f"{i:03d}.png", "--size", "512x512",
                   "--azimuth", f"{360 * i / frames:g}", "--elevation", "15", record=False)
    single_s = time.perf_counter() - start
    ctx.record(f"surfel batch {ctx.shown(spot)} --turntable {frames} -o batch/ --size 512x512 --workers 2")
    ctx.record(f"surfel render {ctx.shown(spot)} -o single/NNN.png --size 512x512 --azimuth A --elevation 15",
               f"NNN = 000 ... {frames - 1:03d}, A = 360 NNN / {frames}")
    same = all((batch_dir / f"{i:03d}.png").read_bytes() == (single_dir / f"{i:03d}.png").read_bytes()
               for i in range(frames))
    sameness = "the same bytes as" if same else "NOT the same bytes as"
    return (f"{frames} turntable frames of spot at 512x512 on a local cluster of two workers: {batch_s:.1f} s, "
            f"{sameness} {frames} `surfel render` calls ({single_s:.1f} s).")


def section_scans(ctx: Context) -> str:
    """Range scans of the shared models by `surfel scan`'s scanner, against their meshes."""
    models = [ctx.model(name) for name in MODELS]
    rows = ["| scan | deferred | phong |", "|---|---|---|"]
    for label, extra in (("as rendered (normals of noisy scans select their neighbourhood size)", ()),
                         ("`--smooth` (positions projected onto their MLS surface first)", ("--smooth",))):
        result = json.loads(ctx.script("scan_fidelity.py", *models, *extra, "--json"))
        cells = [f"{result['median_psnr'][m]:.1f} dB, {result['max_holes_percent'][m]:.2f}%"
                 for m in ("deferred", "phong")]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def section_cad(ctx: Context) -> str:
    """A CAD export (tests/data/octagonal_pocket.stl): its vertices, and `surfel sample`'s points."""
    part = ROOT / "tests" / "data" / "octagonal_pocket.stl"
    rows = ["| input | reference | deferred | phong |", "|---|---|---|---|"]
    inputs = (("its 1,658 vertices", ("--vertices",)), ("`surfel sample`, 200,000 points", ("--sampled", "200000")))
    for label, mode in inputs:
        for shading, extra in (("the mesh's vertex normals", ()), ("crease normals", ("--crease-reference",))):
            result = json.loads(ctx.script("scan_fidelity.py", part, *mode, "--oblique", *extra, "--json"))
            cells = [f"{result['median_psnr'][m]:.1f} dB, {result['max_holes_percent'][m]:.2f}%"
                     for m in ("deferred", "phong")]
            rows.append(f"| {label} | {shading} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def section_copc(ctx: Context) -> str:
    copc, stats = ctx.scratch / "autzen.copc.laz", ctx.scratch / "far.json"
    ctx.surfel("lod", "build", ctx.data / "autzen_trim.laz", "-o", copc)
    ctx.surfel("render", copc, "-o", ctx.scratch / "far.png", "--zoom", "4", "--size", "512x512", "--stats", stats)
    lod = json.loads(stats.read_text())
    read = lod["bytes_read"] / lod["file_bytes"]
    return f"A far view of the Autzen tile as COPC, `--zoom 4` at 512x512, reads {100 * read:.1f}% of the file."


def peak_run(ctx: Context, argv: list[str], shown: str, note: str | None = "peak memory from its rusage",
             env: dict[str, str] | None = None) -> tuple[float, float]:
    """Run argv (with `env` added to the environment), recorded with `note` (None: not recorded,
    a rerun); (wall seconds, peak resident GB of the process)."""
    if note is not None:
        ctx.record(shown, note)
    start = time.perf_counter()
    process = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, env={**os.environ, **(env or {})})
    _, status, usage = os.wait4(process.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{shown} failed")
    return time.perf_counter() - start, usage.ru_maxrss * 1024 / 1e9  # ru_maxrss: KiB on Linux


def section_build100m(ctx: Context) -> str:
    cloud, lod, stats = ctx.scratch / "cloud100m.ply", ctx.scratch / "cloud100m.lod", ctx.scratch / "render.json"
    surfel_cli = [sys.executable, "-m", "surfel.cli"]
    ctx.script("make_big_cloud.py", cloud, "--points", 100_000_000)
    build_s, build_gb = peak_run(ctx, [*surfel_cli, "lod", "build", str(cloud), "-o", str(lod), "--memory", "4GB"],
                                 "surfel lod build cloud100m.ply -o cloud100m.lod --memory 4GB")
    _, render_gb = peak_run(ctx, [*surfel_cli, "render", str(lod), "-o", str(ctx.scratch / "c.png"), "--method",
                                  "deferred", "--lod-error", "1", "--size", "1024x1024", "--stats", str(stats)],
                            "surfel render cloud100m.lod --method deferred --lod-error 1 --size 1024x1024")
    read_mb = json.loads(stats.read_text())["bytes_read"] / 1e6
    return (f"On this machine a 100M-point binary PLY with normals ({cloud.stat().st_size / 1e9:.1f} GB, "
            f"`benchmarks/make_big_cloud.py`) builds in {build_s / 60:.1f} min "
            f"({1e8 / build_s / 1e6:.2f}M points/s) at {build_gb:.1f} GB peak memory "
            f"(`surfel lod build cloud100m.ply -o cloud100m.lod --memory 4GB`), and `surfel render cloud100m.lod "
            f"--method deferred --lod-error 1 --size 1024x1024` draws it hole-free from {read_mb:.0f} MB read at "
            f"{render_gb:.2f} GB peak.")


def section_build20m(ctx: Context) -> str:
    cloud, cache = ctx.scratch / "cloud20m.ply", ctx.scratch / "numba-cache"
    after_demo = ctx.scratch / "numba-cache-demo"
    ctx.script("make_big_cloud.py", cloud, "--points", 20_000_000)
    argv = [sys.executable, "-m", "surfel.cli", "lod", "build", str(cloud), "-o", str(ctx.scratch / "cloud20m.lod"),
            "--memory", "4GB"]
    demo = [sys.executable, "-m", "surfel.cli", "render", "--demo", "-o", str(ctx.scratch / "demo.png")]
    shown = "surfel lod build cloud20m.ply -o cloud20m.lod --memory 4GB"
    first, _ = peak_run(ctx, argv, shown, "from an empty NUMBA_CACHE_DIR, then again", {"NUMBA_CACHE_DIR": str(cache)})
    later, _ = peak_run(ctx, argv, shown, None, {"NUMBA_CACHE_DIR": str(cache)})
    peak_run(ctx, demo, "surfel render --demo -o demo.png", "from another empty NUMBA_CACHE_DIR, then the build",
             {"NUMBA_CACHE_DIR": str(after_demo)})
    demoed, _ = peak_run(ctx, argv, shown, None, {"NUMBA_CACHE_DIR": str(after_demo)})

    def rate(seconds: float) -> str:
        return f"{seconds:.0f} s ({2e7 / seconds / 1e6:.2f}M points/s)"

    return (f"The first build after installing also compiles the workers' numba kernels (once; the workers "
            f"share the compiling): a 20M-point binary PLY with normals builds in {rate(first)} from an empty "
            f"numba cache, in {rate(demoed)} after the demo render above (which compiles the kernels a build shares "
            f"with rendering), and in {rate(later)} once every kernel is cached.")


def section_firstrun(ctx: Context) -> str:
    cache = ctx.scratch / "numba-cache"
    argv = [sys.executable, "-m", "surfel.cli", "render", "--demo", "-o", str(ctx.scratch / "demo.png")]
    shown = "surfel render --demo -o demo.png"
    first, _ = peak_run(ctx, argv, shown, "from an empty NUMBA_CACHE_DIR, then again", {"NUMBA_CACHE_DIR": str(cache)})
    later, _ = peak_run(ctx, argv, shown, None, {"NUMBA_CACHE_DIR": str(cache)})
    return (f"The first render after installing compiles surfel's numba kernels, once (numba keeps them on disk; "
            f"a terminal is told so). A CPU render compiles the method's kernels in a second process while it "
            f"compiles the preprocessing's (`compile_ahead.py`): `surfel render --demo` takes {first:.0f} s from an "
            f"empty numba cache, {later:.1f} s once they are cached.")


# ---------------------------------------------------------------------------------------------
# The driver


@dataclass(frozen=True)
class Section:
    measure: Callable[[Context], str]
    cost: str
    what: str


SECTIONS = {
    "quality": Section(section_quality, "4 min", "every method against the mesh: PSNR, holes, ms"),
    "sparse": Section(section_sparse, "30 s", "every 4th bunny vertex: interior PSNR, front and right"),
    "dense": Section(section_dense, "1 min", "400k points on the bunny: PSNR"),
    "speed": Section(section_speed, "2 min", "surfel bench table, bunny at 1M points"),
    "demo": Section(section_demo, "2 min", f"deferred on GL and CPU against point sprites, {RUNS} runs"),
    "lod": Section(section_lod, "2 min", "level of detail at 4M points"),
    "page": Section(section_page, "6 min", f"the exported page's frame time, {RUNS} runs"),
    "page-match": Section(section_page_match, "30 s", "the page's picture against surfel render"),
    "batch": Section(section_batch, "2 min", "24 turntable frames: surfel batch against surfel render"),
    "scans": Section(section_scans, "2 min", "range scans of the shared models: median PSNR, worst holes"),
    "cad": Section(section_cad, "1 min", "a CAD part's STL: its vertices against surfel sample's points"),
    "copc": Section(section_copc, "30 s", "bytes a far COPC view reads"),
    "firstrun": Section(section_firstrun, "3 min", "the demo render, first (compiling) and later"),
    "build20m": Section(section_build20m, "5 min, 0.5 GB disk", "a 20M-point build: first, after the demo, later"),
    "build100m": Section(section_build100m, "20 min, 2.4 GB disk (expensive)", "the 100M-point out-of-core build"),
}


def markers(name: str) -> tuple[str, str]:
    return f"<!-- numbers:{name} -->", f"<!-- /numbers:{name} -->"


def replace_block(text: str, name: str, body: str) -> str:
    """`text` with the block of `name` (between its markers, which stay) replaced by `body`,
    indented as the opening marker is (a block inside a list item stays in it); the markers
    must occur exactly once each, the opening one first, each on a line of its own."""
    begin, end = markers(name)
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise ValueError(f"README: {begin} ... {end} must occur exactly once, in that order")
    pattern = re.compile(r"^([ \t]*)" + re.escape(begin) + r"\n.*?^[ \t]*" + re.escape(end) + "$",
                         re.DOTALL | re.MULTILINE)
    found = pattern.search(text)
    if found is None:
        raise ValueError(f"README: {begin} and {end} must stand on lines of their own")
    indent = found.group(1)
    lines = [begin, *body.splitlines(), end]
    block = "\n".join(indent + line if line else "" for line in lines)
    return text[:found.start()] + block + text[found.end():]


def machine() -> str:
    from surfel import bench
    from surfel.gl.context import gl_available, renderer_string

    renderer = f"OpenGL renderer `{renderer_string()}`" if gl_available() else "no OpenGL"
    return f"{bench.machine()}, {renderer}, load average {os.getloadavg()[0]:.1f} at the start"


def footer(name: str, commands: list[str], where: str) -> str:
    """The block's last line: how it was made, and where."""
    ran = "; ".join(commands)
    day = datetime.date.today().isoformat()
    return (f"<sub>`python benchmarks/readme_numbers.py {name}`, {day}, {where}. Ran: {ran}.</sub>")


def regenerate(names: list[str], data: Path = DATA, scratch: str | None = None) -> None:
    """Measure the named sections, rewriting each one's README block (atomically) as soon as it
    is measured, so that a failure later keeps what was done."""
    from surfel.files import write_atomically

    text = README.read_text()
    for name in names:  # a missing marker fails before anything is measured
        replace_block(text, name, "")
    where = machine()
    for name in names:
        print(f"== {name}", file=sys.stderr)
        with tempfile.TemporaryDirectory(dir=scratch) as folder:
            ctx = Context(data, Path(folder), [])
            body = SECTIONS[name].measure(ctx)
        print(body, file=sys.stderr)
        text = replace_block(README.read_text(), name, f"{body}\n\n{footer(name, ctx.commands, where)}")
        write_atomically(README, text.encode())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sections", nargs="*", help=f"{', '.join(SECTIONS)} or all")
    parser.add_argument("--list", action="store_true", help="the sections, with what each measures and its cost")
    parser.add_argument("--data", type=Path, default=DATA, help="the folder of the shared models (%(default)s)")
    parser.add_argument("--scratch", default=None, help="folder for temporary files (default: the system's)")
    args = parser.parse_args()
    if args.list or not args.sections:
        for name, section in SECTIONS.items():
            print(f"{name:12s} {section.cost:34s} {section.what}")
        return
    names = list(SECTIONS) if "all" in args.sections else args.sections
    unknown = [n for n in names if n not in SECTIONS]
    if unknown:
        parser.exit(2, f"readme_numbers.py: unknown section {', '.join(unknown)} (see --list)\n")
    try:
        regenerate(names, args.data, args.scratch)
    except (RuntimeError, ValueError) as exc:  # a command that failed, a README without a block's markers
        parser.exit(1, f"readme_numbers.py: {exc}\n")


if __name__ == "__main__":
    main()
