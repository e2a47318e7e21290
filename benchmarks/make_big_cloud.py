"""Write an N-point binary PLY with normals sampled from a mesh surface, in bounded memory.

The out-of-core LOD test input (issue 9): points are drawn uniformly over the mesh surface
(faces chosen with probability proportional to their area, then uniform barycentric
coordinates (1 - sqrt(r1), sqrt(r1)(1 - r2), sqrt(r1) r2)), with normals interpolated from
the area-weighted vertex normals. The body is written chunk by chunk, so memory stays
O(chunk) whatever N: float32 x y z nx ny nz, 24 bytes per point.

    python benchmarks/make_big_cloud.py /work/big/cloud100m.ply --points 100000000
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from surfel.io import load

CHUNK = 4_000_000


def write_sampled_ply(mesh_path: str, out_path: str, points: int, *, seed: int = 0) -> None:
    """Sample `points` points of the mesh surface into a binary little-endian PLY."""
    mesh = load(mesh_path)
    tri = mesh.positions[mesh.faces]                       # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cdf = np.cumsum(area) / area.sum()
    normals = mesh.normals[mesh.faces].astype(np.float64)  # (F, 3, 3)
    rng = np.random.default_rng(seed)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"comment sampled from {os.path.basename(mesh_path)}\n"
              f"element vertex {points}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\nend_header\n")
    tmp = out_path + ".tmp"
    with open(tmp, "wb") as file:
        file.write(header.encode())
        done = 0
        while done < points:
            m = min(CHUNK, points - done)
            face = np.minimum(np.searchsorted(cdf, rng.random(m)), len(cdf) - 1)
            s = np.sqrt(rng.random(m))
            r2 = rng.random(m)
            bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)[:, :, None]
            record = np.empty((m, 6), np.float32)
            record[:, :3] = (tri[face] * bary).sum(axis=1)
            n = (normals[face] * bary).sum(axis=1)
            record[:, 3:] = n / np.linalg.norm(n, axis=1, keepdims=True)
            file.write(record.tobytes())
            done += m
            print(f"\r{done}/{points}", end="", file=sys.stderr)
    print(file=sys.stderr)
    os.replace(tmp, out_path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output")
    parser.add_argument("--points", type=int, default=100_000_000)
    parser.add_argument("--mesh", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared",
                                                       "data", "spot.obj"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    write_sampled_ply(args.mesh, args.output, args.points, seed=args.seed)


if __name__ == "__main__":
    main()
