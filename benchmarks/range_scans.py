"""Issue 17's fidelity on real range scans: the scans a `.conf` file registers (the Stanford
3D Scanning Repository's format, e.g. the bunny's bun.conf and bun000.ply ... bun315.ply,
which are not redistributed here), merged into one cloud without normals and rendered by each
method against the mesh made from them (`surfel compare`'s metrics, surfel.metrics, at
512 x 512 with lambert shading, from the front and from azimuth 60, elevation 20).

    python benchmarks/range_scans.py bunny/data/bun.conf bun_zipper.ply [--methods deferred,phong]
        [--json]

A `.conf` line `bmesh FILE tx ty tz qx qy qz qw` places FILE's points p at R⁻¹ p + t, R the
rotation of the unit quaternion (qx, qy, qz, qw): on the bunny the scans then lie a median
0.5 mm from the mesh's vertices (28 mm with R p + t). Lines naming a file that is absent are
skipped, with a note.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.io import load
from surfel.metrics import compare_results
from surfel.options import RenderOptions
from surfel.rendering import Renderer

SIZE = (512, 512)
VIEWS = {"front": (None, None), "az60el20": (60.0, 20.0)}


def registered_scans(conf: Path) -> PointCloud:
    """The scans of a .conf file, each moved into the common frame, as one cloud."""
    parts = []
    for number, line in enumerate(conf.read_text().splitlines(), 1):
        fields = line.split()
        if not fields or fields[0] != "bmesh":
            continue
        if len(fields) != 9:
            raise SystemExit(f"{conf}:{number}: a bmesh line needs a file and 7 numbers")
        path = conf.parent / fields[1]
        if not path.is_file():
            print(f"{path}: absent, skipped", file=sys.stderr)
            continue
        translation, quaternion = np.array(fields[2:5], float), np.array(fields[5:9], float)
        positions = np.array(load(path).positions, np.float64)
        parts.append(Rotation.from_quat(quaternion).inv().apply(positions) + translation)
    if not parts:
        raise SystemExit(f"{conf}: names no scan that is present")
    return PointCloud(np.concatenate(parts))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("conf", type=Path)
    parser.add_argument("mesh")
    parser.add_argument("--methods", default="gaussian,deferred,phong,ewa")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    mesh, cloud = load(args.mesh), registered_scans(args.conf)
    options = RenderOptions(shading="lambert", background=(0.0, 0.0, 0.0))
    rows = []
    with Renderer() as renderer:
        for view, (azimuth, elevation) in VIEWS.items():
            camera = frame(mesh.center, mesh.bounding_radius, azimuth=azimuth, elevation=elevation, size=SIZE)
            reference = renderer.render(mesh, camera, "mesh", options=options)
            for method in args.methods.split(","):
                metrics = compare_results(reference, renderer.render(cloud, camera, method, options=options))
                rows.append({"points": len(cloud), "view": view, "method": method,
                             "psnr": round(metrics["psnr"], 2), "interior psnr": round(metrics["interior_psnr"], 2),
                             "holes %": round(100 * metrics["holes"], 3), "spill %": round(100 * metrics["spill"], 3)})
                if not args.json:
                    print("  ".join(f"{key} {value}" for key, value in rows[-1].items()), flush=True)
    if args.json:
        print(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
