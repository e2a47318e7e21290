"""`surfel bench`: median milliseconds per frame and splats per second, every method on the same data.

The input is replicated with jitter to the requested point count; radii shrink by
1/sqrt(copies) so that the splats keep their overlap, as a denser scan of the same surface
would. Each frame is one full `render()` call (all passes, ctx.finish(), readback), timed
after warm-up frames; the median over the frames is reported.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from .cloud import PointCloud
from .options import RenderOptions
from .preprocess import complete
from .rendering import default_camera, render


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
    data = replicate(cloud, points) if points else complete(cloud)[0]
    camera = default_camera(data, size, zoom=zoom)
    rows = []
    for spec in methods:
        name, _, backend = spec.partition("@")
        for lod in [None] if lod_error is None else [None, lod_error]:
            options = RenderOptions(shading=shading, lod_error=lod)
            times, result = [], None
            for i in range(warmup + frames):
                start = time.perf_counter()
                result = render(data, camera, name, backend=backend or None, options=options)
                if i >= warmup:
                    times.append((time.perf_counter() - start) * 1000)
            ms = statistics.median(times)
            row = {"method": name, "backend": result.stats["backend"], "renderer": result.stats["renderer"],
                   "points": len(data), "splats": result.stats["splats"], "width": size[0], "height": size[1],
                   "ms": round(ms, 2), "msplats_per_s": round(len(data) / ms / 1000, 3), "frames": frames}
            if lod is not None:
                row["lod"] = lod
            if zoom != 1.0:
                row["zoom"] = zoom
            rows.append(row)
    return rows
