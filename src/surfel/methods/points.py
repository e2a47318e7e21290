"""`points`: the naive method of the survey's Fig. 6 (left), the baseline splatting beats.

Each point is an OpenGL point sprite of diameter 2 r fy / z_eye pixels (survey eq. 6),
cut to a disk, depth-tested in an ordinary z-buffer and flat-shaded with the point's own
normal: no blending, no filtering, one sample per pixel. This is what general viewers do.
Its one parameter (`params.RadiusParams`) scales the radii.
"""

from __future__ import annotations

from pathlib import Path

from ..gl import splats
from ..gl.context import get_context
from ..gl.targets import GBuffer, gbuffer_result
from ..gl.uniforms import apply_common
from .params import RadiusParams

SHADER = Path(__file__).with_suffix(".glsl")


def render_points(cloud, camera, options, params: RadiusParams, renderer):
    ctx = get_context()
    ss = options.supersample or 1
    program = renderer.program(SHADER)
    lod_k, prefix, drawn = splats.lod_frame(cloud, camera, options.lod_error)
    apply_common(program, camera, cloud.local_origin, ss, options, u_radius_scale=params.radius_scale, u_lod_k=lod_k)
    renderer.use_color_table(options)
    size = (camera.width * ss, camera.height * ss)
    # kept from frame to frame, as the splat methods' targets are: creating the textures took
    # about 27 ms of a 1M-point, 1024x1024 frame on llvmpipe
    gbuffer = renderer.targets("points", size, lambda: GBuffer(*size))
    gbuffer.fbo.use()
    gbuffer.clear()
    ctx.disable(ctx.BLEND | ctx.CULL_FACE)
    ctx.enable(ctx.DEPTH_TEST | ctx.PROGRAM_POINT_SIZE)
    splats.draw(ctx, renderer.splat_buffers(cloud), program, ctx.POINTS, instanced=False, count=prefix)
    ctx.finish()
    return gbuffer_result(gbuffer, camera, options, ss, {"splats": len(cloud) if drawn is None else int(drawn.sum())})
