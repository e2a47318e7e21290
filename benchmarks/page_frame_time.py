"""Frame time of the exported page in headless Chromium beside the GL path, same cloud and view.

    python benchmarks/page_frame_time.py [--points 1000000] [--size 1024] [--frames 5] [--json]

The cloud is `surfel bench`'s (the demo model replicated and jittered to --points); the page
is exported with the default camera and `deferred`, and opens with its point tree at 1 pixel
of LOD error, so the GL row is `surfel bench --methods deferred@gl --points N --size SxS --lod-error 1`. The
page's time is what it reports itself (window.surfelStats: draw calls to a one-pixel
readback); Chromium runs WebGL2 on SwiftShader here, the GL path on Mesa's llvmpipe.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

FLAGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--disable-dev-shm-usage"]


def main():
    from playwright.sync_api import sync_playwright

    from surfel.bench import replicate, run
    from surfel.data import demo_cloud
    from surfel.rendering import default_camera
    from surfel.web import export_html

    parser = argparse.ArgumentParser()
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--json", action="store_true", help="print the measurements as one JSON object")
    args = parser.parse_args()
    size = (args.size, args.size)
    cloud = replicate(demo_cloud(), args.points)
    with tempfile.TemporaryDirectory() as folder:
        page_path = Path(folder) / "page.html"
        start = time.perf_counter()
        report = export_html(cloud, default_camera(cloud, size), page_path, method="deferred")
        export_s = time.perf_counter() - start
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS, headless=True)
            page = browser.new_page(viewport={"width": size[0], "height": size[1]}, device_scale_factor=1)
            start = time.perf_counter()
            page.goto(page_path.as_uri() + "#capture")
            page.wait_for_function("window.surfelStats && (surfelStats.ready || surfelStats.error)", timeout=600_000)
            load_s = time.perf_counter() - start
            times = page.evaluate(f"""() => {{ const out = [];
                for (let i = 0; i < {args.frames}; i++) {{ surfelView.render(); out.push(surfelStats.frameMs); }}
                return out; }}""")
            stats = page.evaluate("({...surfelStats, history: undefined})")
            coarse = page.evaluate(f"""() => {{ const out = [];
                for (let i = 0; i < {args.frames}; i++) {{ surfelView.render(true); out.push(surfelStats.frameMs); }}
                return out; }}""")  # frames of a moving camera: coarser LOD, half resolution
            moving = page.evaluate("({...surfelStats, history: undefined})")
            browser.close()
    gl = run(cloud, ["deferred@gl"], size=size, frames=args.frames, lod_error=1.0)
    if args.json:  # benchmarks/readme_numbers.py reads this
        print(json.dumps({"points": len(cloud), "size": size, "page_nodes": report["points"],
                          "page_bytes": report["bytes"], "export_s": export_s, "load_s": load_s,
                          "page_renderer": stats["renderer"], "rest_ms": statistics.median(times),
                          "rest_splats": stats["drawn"], "rest_lod": stats["lodError"],
                          "moving_ms": statistics.median(coarse), "moving_splats": moving["drawn"],
                          "moving_lod": moving["lodError"], "gl": gl}))
        return
    print(f"{len(cloud)} points, {size[0]}x{size[1]}; page: {report['points']} nodes, "
          f"{report['bytes'] / 1e6:.1f} MB, exported in {export_s:.1f} s, opened in {load_s:.1f} s")
    print(f"page  {stats['renderer']}: {statistics.median(times):7.1f} ms/frame at rest "
          f"({stats['drawn']} splats, LOD {stats['lodError']} px), {statistics.median(coarse):.1f} ms moving "
          f"({moving['drawn']} splats, LOD {moving['lodError']} px, half resolution)")
    for row in gl:
        lod = f" lod {row['lod']} px" if "lod" in row else ""
        print(f"gl    {row['renderer']}: {row['ms']:7.1f} ms/frame{lod} ({row['splats']} splats)")


if __name__ == "__main__":
    main()
