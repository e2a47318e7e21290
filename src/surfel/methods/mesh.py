"""`mesh`: the ground truth every method is measured against.

The input mesh's triangles rasterized with per-pixel interpolated area-weighted vertex
normals, under the same camera and shading models as the splat methods, supersampled
(default 4x4 samples per pixel) and box-filtered for anti-aliased edges.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..gl.context import get_context
from ..gl.targets import GBuffer, gbuffer_result
from ..gl.uniforms import apply_common
from ..options import Settings

SHADER = Path(__file__).with_suffix(".glsl")
DEFAULT_SUPERSAMPLE = 4


@dataclass(frozen=True)
class MeshParams(Settings):
    """The ground truth has no parameters: the common options (shading, supersampling) only."""


def render_mesh(cloud, camera, options, params: MeshParams, renderer):
    ctx = get_context()
    ss = options.supersample or DEFAULT_SUPERSAMPLE
    program = renderer.program(SHADER)
    apply_common(program, camera, cloud.local_origin, ss, options)
    renderer.use_color_table(options)
    n = len(cloud)
    colors = cloud.colors if cloud.colors is not None else np.ones((n, 3), np.float32)
    data = np.hstack([cloud.local_positions(), cloud.normals, colors]).astype(np.float32)
    vbo = ctx.buffer(data)
    ibo = ctx.buffer(cloud.faces.astype(np.uint32))
    vao = ctx.vertex_array(program, [(vbo, "3f 3f 3f", "in_position", "in_normal", "in_color")], ibo)
    gbuffer = GBuffer(camera.width * ss, camera.height * ss)
    try:
        gbuffer.fbo.use()
        gbuffer.clear()
        ctx.disable(ctx.BLEND | ctx.CULL_FACE)
        ctx.enable(ctx.DEPTH_TEST)
        vao.render()
        ctx.finish()
        return gbuffer_result(gbuffer, camera, options, ss, {"splats": 0, "triangles": len(cloud.faces)},
                              surface=renderer.surface_colors(cloud, camera.supersampled(ss), options))
    finally:
        for obj in (vao, vbo, ibo):
            obj.release()
        gbuffer.release()
