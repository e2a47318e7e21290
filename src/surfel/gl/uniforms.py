"""The uniforms of common.glsl, from a camera at a given supersampling factor."""

from __future__ import annotations

import numpy as np

from ..shading import MODEL_IDS
from .program import set_uniforms


def camera_uniforms(camera, origin, supersample: int) -> dict:
    s = supersample
    return {
        "u_view": camera.view_matrix(origin),
        "u_projection": camera.projection_matrix(),
        "u_viewport": np.array([camera.width * s, camera.height * s]),
        "u_intrinsics": np.array([camera.fx * s, camera.fy * s, camera.cx * s, camera.cy * s]),
        "u_ortho": 0.0 if camera.ortho_height is None else camera.height * s / camera.ortho_height,
        "u_depth_range": np.array([camera.near, camera.far]),
    }


def apply_common(program, camera, origin, supersample: int, shading: str, **extra) -> None:
    set_uniforms(program, **camera_uniforms(camera, origin, supersample), u_shading=MODEL_IDS[shading], **extra)
