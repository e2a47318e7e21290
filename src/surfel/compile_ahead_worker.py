"""The helper process of compile_ahead.py: `python -m surfel.compile_ahead_worker SPEC` renders
a small synthetic cloud as SPEC (`compile_ahead.render_spec`) describes the real render, so
that numba compiles the method's CPU kernels into its cache for the process that waits.

The cloud is a sphere of SPHERE_POINTS splats that already has everything the method needs
(normals, radii, axes, and Phong splatting's normal fields), so that completing it compiles
nothing: the other process compiles those kernels. It has clip lines exactly when the real
cloud will, since the kernels take them or None.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from .attributes import FIELD_SLOPES
from .camera import frame
from .cloud import PointCloud
from .preprocess import CLIP_LINES, INACTIVE_CLIP, tangent_frames
from .rendering import Renderer

SPHERE_POINTS = 512


def synthetic_cloud(clip: bool) -> PointCloud:
    """A unit sphere of splats covering it, with inactive clip lines if `clip`."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(SPHERE_POINTS, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    radii = np.full(SPHERE_POINTS, 4.0 / np.sqrt(SPHERE_POINTS))
    attributes = {name: np.zeros(SPHERE_POINTS, np.float32) for name in FIELD_SLOPES}
    if clip:
        attributes["clip_lines"] = np.tile(np.asarray(INACTIVE_CLIP, np.float32), (SPHERE_POINTS, CLIP_LINES, 1))
    return PointCloud(points, normals=points.astype(np.float32), radii=radii.astype(np.float32),
                      axes=tangent_frames(points, radii), attributes=attributes)


def compile_for(spec: dict) -> None:
    """Render the synthetic cloud as `spec` describes the real render."""
    width, height = spec["size"]
    with Renderer(compile_ahead=False) as renderer:  # nothing to compile ahead of: it is the helper
        renderer.render(synthetic_cloud(spec["clip"]), frame(np.zeros(3), 1.0, size=(width, height)), spec["method"],
                        backend="cpu", shading=spec["shading"], supersample=spec["supersample"], **spec["params"])


if __name__ == "__main__":
    compile_for(json.loads(sys.argv[1]))
