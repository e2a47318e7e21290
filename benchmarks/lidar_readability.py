"""Issue 14's measures of LiDAR tiles, rendered as `surfel render` renders them.

For each tile, a top orthographic view framed by its extent (`--view top --ortho auto`):
* default render: far (covered pixels farther than 4 spacings from every return) and
  uncovered (footprint left open), surfel.metrics.top_view_footprint;
* `--color elevation --colormap viridis --shading none`: Spearman correlation between the
  elevation read back through the colour map and the surface's elevation from the depth;
* `--color classification --shading none` (tiles with classes): the share of fully covered
  pixels whose colour is none of the classes' palette colours;
* the default render's time (estimation included, in a warm process).

    python benchmarks/lidar_readability.py TILE.laz [TILE.las ...]
"""

from __future__ import annotations

import sys
import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from surfel import colors
from surfel.metrics import top_view_footprint
from surfel.rendering import Renderer
from surfel.request import parse_render


def measure(path: str) -> dict:
    renderer = Renderer()

    def render(**values):
        request = parse_render({"input": path, "view": "top", "ortho": "auto", "output": "unused.png", **values})
        return request, request.render(renderer, cloud)

    cloud = parse_render({"input": path, "output": "unused.png"}).open_input()
    start = time.perf_counter()
    request, default = render()
    seconds = time.perf_counter() - start
    far, uncovered = top_view_footprint(default, request.camera.camera(cloud), cloud.positions)
    row = {"tile": path.rsplit("/", 1)[-1], "points": len(cloud), "far %": 100 * far,
           "uncovered %": 100 * uncovered, "default s": seconds,
           "color": default.stats["color"], "shading": default.stats["shading"]}
    _, ramp = render(color="elevation", colormap="viridis", shading="none")
    full = ramp.alpha > 0.99
    _, level = cKDTree(colors.colormap_table("viridis")).query(ramp.color[full])
    row["spearman"] = float(spearmanr(level, -ramp.depth[full]).correlation)  # top view: nearer is higher
    if "classification" in cloud.attributes:
        _, classes = render(color="classification", shading="none")
        full = classes.alpha > 0.99
        codes = np.unique(np.asarray(cloud.attributes["classification"]))
        distance, _ = cKDTree(colors.palette("classification", codes)).query(classes.color[full])
        row["not a class %"] = 100 * float((distance > 0.02).mean())
    return row


def main(paths: list[str]) -> None:
    if not paths:
        sys.exit(__doc__)
    for path in paths:
        row = measure(path)
        print("  ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
