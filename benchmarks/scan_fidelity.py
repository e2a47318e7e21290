"""Issue 17's fidelity on raw range scans: each mesh is scanned by the virtual range scanner
(`surfel scan`'s defaults: 6 views of 256 x 256, range noise 0.1% and misregistration 0.05% of
the model's size, samples lost at grazing angles, no normals), and each method's render of the
scan is compared with the mesh's (`surfel compare`'s metrics, surfel.metrics.compare_results)
at 512 x 512 with lambert shading, from the front and from azimuth 60, elevation 20; with
--oblique also from 16 oblique directions (azimuth 0 to 315 in steps of 45, elevation -25 and
25), which see parts of the model that the scan's views saw at grazing angles or not at all.

    python benchmarks/scan_fidelity.py MESH.obj [MESH.ply ...] [--methods deferred,phong]
        [--smooth [--prepared] | --vertices | --bare | --sampled N] [--oblique] [--crease-reference] [--json]

--smooth denoises the scan first: the positions of `surfel prepare --smooth` (normals and
splats are then estimated by each method's completion, as for the raw scan); with
--prepared, the whole cloud `surfel prepare --smooth --elliptical --normal-field` writes
(its normals, splats and clip lines), as a user who prepares the scan first renders it. --vertices
renders the mesh's own vertices (with the mesh's normals) instead of a scan; --bare, the same
vertices without normals, which each method's completion then estimates (as for a point file
without normals); --sampled N, about N points that `surfel sample` spreads evenly over the
mesh's faces (with its crease-angle normals), as for a CAD export whose vertices lie only on its
faces' outlines. --crease-reference shades the mesh it compares with by those crease-angle
normals instead of its vertex normals (which blend across a CAD part's 90 degree edges).
Prints one row per model and view, then the median PSNR of each method over all of them.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.io import load
from surfel.metrics import compare_results
from surfel.options import RenderOptions
from surfel.preprocess import prepare
from surfel.preprocess.mesh_samples import SampleSettings, corner_normals, sample_surface
from surfel.rendering import Renderer
from surfel.scan import ScanSettings, scan

SIZE = (512, 512)
VIEWS = {"front": (None, None), "az60el20": (60.0, 20.0)}
OBLIQUE_VIEWS = {f"az{azimuth}el{elevation}": (float(azimuth), float(elevation))
                 for elevation in (-25, 25) for azimuth in range(0, 360, 45)}


def crease_shaded(mesh: PointCloud) -> PointCloud:
    """The mesh with a vertex per face corner, each with `surfel sample`'s crease-angle normal."""
    normals = corner_normals(mesh.positions, mesh.faces, SampleSettings().crease_angle)
    return PointCloud(mesh.positions[mesh.faces].reshape(-1, 3), normals=normals.reshape(-1, 3),
                      faces=np.arange(3 * len(mesh.faces)).reshape(-1, 3), source=mesh.source)


def measure(path: str, methods: list[str], smooth: bool, vertices: bool, renderer: Renderer,
            prepared: bool = False, views: dict = VIEWS, bare: bool = False, sampled: int = 0,
            crease_reference: bool = False) -> list[dict]:
    mesh = load(path)
    truth = crease_shaded(mesh) if crease_reference else mesh
    if sampled:
        cloud = sample_surface(mesh, SampleSettings(points=sampled))
    else:
        cloud = mesh.take(np.arange(len(mesh))) if vertices or bare else scan(mesh, ScanSettings(), renderer)
    if bare:
        cloud = PointCloud(cloud.positions)
    if smooth and prepared:
        cloud = prepare(cloud, smooth=True, elliptical=True, normal_field=True)[0]
    elif smooth:
        cloud = cloud.with_(positions=prepare(cloud, smooth=True)[0].positions)
    options = RenderOptions(shading="lambert", background=(0.0, 0.0, 0.0))
    rows = []
    for view, (azimuth, elevation) in views.items():
        camera = frame(mesh.center, mesh.bounding_radius, azimuth=azimuth, elevation=elevation, size=SIZE)
        reference = renderer.render(truth, camera, "mesh", options=options)
        for method in methods:
            start = time.perf_counter()
            result = renderer.render(cloud, camera, method, options=options)
            metrics = compare_results(reference, result)
            rows.append({"model": path.rsplit("/", 1)[-1], "points": len(cloud), "view": view, "method": method,
                         "psnr": round(metrics["psnr"], 2), "holes %": round(100 * metrics["holes"], 3),
                         "s": round(time.perf_counter() - start, 2)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("meshes", nargs="+")
    parser.add_argument("--methods", default="deferred,phong")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--smooth", action="store_true")
    mode.add_argument("--vertices", action="store_true")
    mode.add_argument("--bare", action="store_true")
    mode.add_argument("--sampled", type=int, default=0, metavar="N")
    parser.add_argument("--prepared", action="store_true")
    parser.add_argument("--oblique", action="store_true")
    parser.add_argument("--crease-reference", action="store_true")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.prepared and not args.smooth:
        parser.error("--prepared: renders the cloud --smooth prepares; give --smooth too")
    methods = args.methods.split(",")
    renderer = Renderer()
    views = {**VIEWS, **OBLIQUE_VIEWS} if args.oblique else VIEWS
    rows = []
    for path in args.meshes:
        for row in measure(path, methods, args.smooth, args.vertices, renderer, args.prepared, views, args.bare,
                           args.sampled, args.crease_reference):
            rows.append(row)
            if not args.json:
                print("  ".join(f"{key} {value}" for key, value in row.items()), flush=True)
    medians = {m: float(np.median([r["psnr"] for r in rows if r["method"] == m])) for m in methods}
    worst_holes = {m: max(r["holes %"] for r in rows if r["method"] == m) for m in methods}
    over = {m: sum(r["holes %"] > 0.1 for r in rows if r["method"] == m) for m in methods}
    if args.json:
        print(json.dumps({"rows": rows, "median_psnr": medians, "max_holes_percent": worst_holes,
                          "renders_over_0.1_percent_holes": over}, indent=2))
    else:
        for m in methods:
            print(f"{m}: median PSNR {medians[m]:.2f} dB, worst holes {worst_holes[m]:.3f}%, "
                  f"{over[m]} of {len(rows) // len(methods)} renders with more than 0.1%")


if __name__ == "__main__":
    main()
