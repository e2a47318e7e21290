"""`surfel bench`: median milliseconds per frame and splats per second, every method on the same data.

The input is replicated with jitter to the requested point count; radii shrink by
1/sqrt(copies) so that the splats keep their overlap, as a denser scan of the same surface
would. Each frame is one full `render()` call (all passes, ctx.finish(), readback), timed
after warm-up frames; the median over the frames is reported. The methods take turns, one
frame each, so that on a shared machine they all meet the same load and their ratios hold. The benchmark holds its own
Renderer, so its caches (GPU buffers, programs, targets) live exactly as long as the run.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time

import numpy as np

from .cloud import PointCloud
from .errors import SurfelError
from .methods import get_method
from .options import RenderOptions
from .preprocess import complete
from .rendering import Renderer, default_camera
from .request import parse_values


def replicate(cloud: PointCloud, points: int, seed: int = 0) -> PointCloud:
    """`points` points: copies of the cloud jittered within their splats, radii scaled down."""
    cloud, _ = complete(cloud)
    n = len(cloud)
    if points <= n:
        pick = np.random.default_rng(seed).choice(n, points, replace=False) if points < n else np.arange(n)
        return PointCloud(cloud.positions[pick], cloud.normals[pick],
                          None if cloud.colors is None else cloud.colors[pick], cloud.radii[pick],
                          cloud.axes[pick], geospatial=cloud.geospatial, source=cloud.source)
    rng = np.random.default_rng(seed)
    idx = np.arange(points) % n
    copies = points / n
    axes = cloud.axes[idx]
    # jitter inside the splat's tangent plane so the surface stays the same surface
    uv = rng.uniform(-0.5, 0.5, size=(points, 2)).astype(np.float32)
    jitter = uv[:, :1] * axes[:, 0] + uv[:, 1:] * axes[:, 1]
    jitter[:n] = 0
    shrink = np.float32(1 / np.sqrt(copies))
    return PointCloud(cloud.positions[idx] + jitter, cloud.normals[idx],
                      None if cloud.colors is None else cloud.colors[idx], cloud.radii[idx] * shrink,
                      axes * shrink, geospatial=cloud.geospatial, source=cloud.source)


def run(cloud: PointCloud, methods: list[str], *, points: int | None = None, size=(1024, 1024),
        frames: int = 5, warmup: int = 1, lod_error: float | None = None, zoom: float = 1.0,
        shading: str = "lambert") -> list[dict]:
    """One row per method (and per LOD setting): the median ms per frame and Msplats/s."""
    specs = [parse_method(spec, lod_error) for spec in methods]
    data = replicate(cloud, points) if points else complete(cloud)[0]
    camera = default_camera(data, size, zoom=zoom)
    runs = [(name, backend, RenderOptions(shading=shading, lod_error=lod)) for name, backend in specs
            for lod in ([None] if lod_error is None else [None, lod_error])]
    times: list[list[float]] = [[] for _ in runs]
    results = [None] * len(runs)
    with Renderer() as renderer:
        # round robin, one frame of each method in turn: on a machine shared with other work,
        # every method meets the same load, so their ratios hold whatever it does meanwhile
        for frame_number in range(warmup + frames):
            for k, (name, backend, options) in enumerate(runs):
                start = time.perf_counter()
                results[k] = renderer.render(data, camera, name, backend=backend, options=options)
                if frame_number >= warmup:
                    times[k].append((time.perf_counter() - start) * 1000)
    return [_row(data, name, options, results[k], times[k], size, zoom) for k, (name, _, options) in enumerate(runs)]


def machine() -> str:
    """The processor and how many cores this process may use: what the timings depend on."""
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as info:  # Linux names the model here; platform often does not
            name = next(line.split(":", 1)[1].strip() for line in info if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{cores} cores of {name}, {platform.system()} {platform.release()}, Python {platform.python_version()}"


def parse_method(spec: str, lod_error: float | None) -> tuple[str, str | None]:
    """NAME or NAME@BACKEND, checked (with --lod-error, only methods that draw splats)."""
    name, _, backend = spec.partition("@")
    method = get_method(name)
    if backend:
        method.function(backend)
    if lod_error is not None and not method.uses("lod_error"):
        raise SurfelError(f"--lod-error: method {name!r} does not use it")
    return name, backend or None


def _row(data, name, options, result, times, size, zoom) -> dict:
    ms = statistics.median(times)
    row = {"method": name, "backend": result.stats["backend"], "backend_choice": result.stats["backend_choice"],
           "renderer": result.stats["renderer"], "machine": machine(),
           "points": len(data), "splats": result.stats["splats"], "width": size[0], "height": size[1],
           "ms": round(ms, 2), "msplats_per_s": round(len(data) / ms / 1000, 3), "frames": len(times),
           "supersample": result.stats.get("supersample", 1)}
    if options.lod_error is not None:
        row["lod"] = options.lod_error
    if zoom != 1.0:
        row["zoom"] = zoom
    return row


def bench_command(input_path, points, methods: str, frames: int, values: dict, *, as_json: bool) -> str:
    """`surfel bench`: the report, as text or JSON."""
    parsed = parse_values(values, ("size", "lod_error", "zoom"))
    size, zoom = parsed.get("size", (1024, 1024)), parsed.get("zoom", 1.0)
    lod_error = parsed.get("lod_error")
    names = [m.strip() for m in methods.split(",") if m.strip()]
    for spec in names:  # before anything is loaded
        parse_method(spec, lod_error)
    if input_path:
        from .io import load

        cloud = load(input_path)
    else:
        from .data import demo_cloud

        cloud = demo_cloud()
        points = points or 1_000_000
    rows = run(cloud, names, points=points, size=size, frames=frames, lod_error=lod_error, zoom=zoom)
    if as_json:
        return json.dumps(rows, indent=2)
    gl = [row["renderer"] for row in rows if row["backend"] == "gl"]
    lines = [f"machine: {machine()}", f"{rows[0]['points']} points, {size[0]}x{size[1]}, OpenGL renderer: "
             f"{gl[0] if gl else 'not used'}"]
    for row in rows:
        lod = f" lod {row['lod']}px" if "lod" in row else ""
        samples = f", {row['supersample']}x{row['supersample']} samples a pixel" if row["supersample"] > 1 else ""
        chosen = f"  [{row['backend_choice']}]" if row["backend_choice"] != "asked" else ""
        lines.append(f"{row['method'] + '@' + row['backend'] + lod:24s} {row['ms']:9.1f} ms  "
                     f"{row['msplats_per_s']:7.2f} Msplats/s  ({row['splats']} splats{samples}){chosen}")
    return "\n".join(lines)
