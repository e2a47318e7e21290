"""The uniforms of common.glsl (camera, shading, colour mode), from a camera at a given
supersampling factor and the render's options."""

from __future__ import annotations

import numpy as np

from ..colors import NEUTRAL
from ..shading import MODEL_IDS
from .program import set_uniforms

SPLATS_UNIT = 13  # texture units above those any method's passes use: the compute programs' splats (splats.py)
COLOR_TABLE_UNIT = 14
CATEGORY_UNIT = 15
COLOR_MODES = {"rgb": 0, "continuous": 1, "categorical": 2}


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


def color_uniforms(options) -> dict:
    """colors.glsl's uniforms for the options' resolved colour mode (rgb when unresolved)."""
    coloring = options.coloring
    return {"u_color_mode": COLOR_MODES[coloring.kind if coloring is not None else "rgb"],
            "u_neutral": np.array(NEUTRAL), "u_color_table": COLOR_TABLE_UNIT,
            "u_code_levels": float(coloring.code_levels if coloring is not None else 2)}


def apply_common(program, camera, origin, supersample: int, options, **extra) -> None:
    set_uniforms(program, **camera_uniforms(camera, origin, supersample),
                 u_shading=MODEL_IDS[options.surface_shading], **color_uniforms(options), **extra)
