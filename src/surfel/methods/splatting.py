"""GPU surface splatting in three passes: `gaussian` and `deferred`.

`gaussian` -- Botsch & Kobbelt 2003, "High-quality point-based rendering on modern GPUs"
(survey 2.1.3): splats rasterized as screen-aligned quads covering the projected disk
(eq. 6 made conservative: the bounding box of the disk's projected bounding square),
elliptical shape and per-pixel depth from the exact ray-disk intersection
q = o + d (c - o).n / d.n (the δz offset of the survey, perspective accurate), a Gaussian
weight alpha = G(|(u, v)|) looked up in a 1D texture, and three passes:
  1. visibility: the nearest eye depth pushed back by z_t (MIN blending into a float target);
  2. attribute: additive blending of (w rgb, w, w n, w z) of fragments no farther than it;
  3. normalization: rgb = sum(w rgb) / sum(w).
Colours are shaded per splat before blending: the Gouraud look of the survey's Fig. 6.

`deferred` -- Botsch, Hornung, Zwicker & Kobbelt 2005, "High-quality surface splatting on
today's GPUs" (survey 2.1.5, 2.1.6): the same visibility pass; the attribute pass blends
albedo and normals into two render targets; the shading pass lights every pixel from its
normalized normal and depth. With the EWA filter approximation (on by default) a fragment's
distance is min(|(u, v)|², |x - m(c)|² / r_lp²): the union of the object-space
reconstruction kernel and a screen-space low-pass of radius r_lp ≈ 1 pixel, so every
splat covers at least 2x2 pixels and minified textures do not alias (Fig. 10).

`phong` -- Botsch, Spernat & Kobbelt 2004, "Phong splatting" (survey 2.1.4): elliptical
splats (c_j, u_j, v_j), the per-fragment ray-plane intersection q = q_n (cᵀn)/(q_nᵀn) and
local (u, v) = (u_jᵀ(q - c_j), v_jᵀ(q - c_j)) / |axis|² (eq. 7), discarding u² + v² > 1,
exact per-pixel depth, and the linear normal field N_j(u, v) = n̄_j + u α_j û_j + v β_j v̂_j
(eq. 8, α_j and β_j fitted in preprocessing: surfel.preprocess.fit_normal_field), blended
with Gaussian weights, normalized and lit per pixel as in `deferred`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..gl import splats
from ..gl.context import get_context
from ..gl.program import build_program, set_uniforms
from ..gl.targets import GBuffer, gbuffer_result, read_texture
from ..gl.uniforms import apply_common

SHADER = Path(__file__).with_suffix(".glsl")
KERNEL_SIZE = 256
DEFAULT_DEPTH_OFFSET = 1.0   # z_t = one splat radius
DEFAULT_SUPERSAMPLE = 1      # as in the papers; --supersample 2 smooths silhouettes further
GAUSSIAN_SHARPNESS = 2.0     # w = exp(-2 d²): the disk boundary sits at two standard deviations
GUARD = 128                  # guard band in pixels: half of llvmpipe's (and most GPUs') 255 px point limit
MAX_SPRITE = 255


def use_point_sprites(cloud, camera, radius_scale: float, supersample: int, lowpass: float, drawn=None) -> bool:
    """Point sprites (one vertex a splat) unless a splat could cross the near plane or need
    a sprite larger than the guard band allows; then instanced quads (four vertices a splat).
    `drawn`: mask of the splats a level-of-detail cut draws (None: all)."""
    axes = cloud.axes if drawn is None else cloud.axes[drawn]
    if len(axes) == 0:
        return True
    max_radius = float(np.linalg.norm(axes, axis=2).max()) * radius_scale
    if camera.ortho_height is not None:
        pixels = max_radius * camera.height * supersample / camera.ortho_height
    else:
        distance = float(-(camera.view_matrix() @ np.append(cloud.center, 1.0))[2])
        nearest = distance - cloud.bounding_radius - max_radius
        if nearest <= camera.near:
            return False
        pixels = max_radius * camera.fy * supersample / nearest * 1.5  # 1.5: off-axis stretch
    return 2 * (pixels + lowpass) + 2 <= min(2 * GUARD, MAX_SPRITE)


def gaussian_kernel_texture(ctx):
    """The 1D Gaussian lookup table of Botsch & Kobbelt 2003, indexed by squared distance."""
    d2 = (np.arange(KERNEL_SIZE, dtype=np.float32) + 0.5) / KERNEL_SIZE
    tex = ctx.texture((KERNEL_SIZE, 1), 1, np.exp(-GAUSSIAN_SHARPNESS * d2).astype(np.float32).tobytes(), dtype="f4")
    tex.repeat_x = tex.repeat_y = False
    return tex


def render_gaussian(cloud, camera, options):
    return _render(cloud, camera, options, per_splat_shading=True,
                   ewa_filter=bool(options.ewa_filter) if options.ewa_filter is not None else False)


def render_deferred(cloud, camera, options):
    return _render(cloud, camera, options, per_splat_shading=False,
                   ewa_filter=options.ewa_filter is None or bool(options.ewa_filter))


def render_phong(cloud, camera, options):
    return _render(cloud, camera, options, per_splat_shading=False, normal_field=True,
                   ewa_filter=bool(options.ewa_filter) if options.ewa_filter is not None else False)


def _render(cloud, camera, options, *, per_splat_shading: bool, ewa_filter: bool, normal_field: bool = False):
    ctx = get_context()
    ss = options.supersample or DEFAULT_SUPERSAMPLE
    width, height = camera.width * ss, camera.height * ss
    lowpass = options.lowpass_radius * ss if ewa_filter else 0.0
    lod_k, prefix, drawn = splats.lod_frame(cloud, camera, options.lod_error)
    sprites = use_point_sprites(cloud, camera, options.radius_scale, ss, lowpass, drawn)
    guard = GUARD if sprites else 0
    variant = {"PER_SPLAT_SHADING": per_splat_shading, "EWA_FILTER": ewa_filter, "NORMAL_FIELD": normal_field,
               "POINT_SPRITES": sprites}
    programs = {p: build_program(SHADER, {p: True, **variant})
                for p in ("PASS_VISIBILITY", "PASS_ATTRIBUTE", "PASS_NORMALIZE")}
    depth_offset = DEFAULT_DEPTH_OFFSET if options.depth_offset is None else options.depth_offset
    for program in programs.values():
        apply_common(program, camera, cloud.local_origin, ss, options.shading,
                     u_radius_scale=options.radius_scale, u_depth_offset=depth_offset,
                     u_lowpass_radius=options.lowpass_radius * ss, u_guard=float(guard),
                     u_backface_culling=int(options.backface_culling),
                     u_kernel=0, u_visibility=1, u_accum_color=2, u_accum_normal=3, u_lod_k=lod_k)

    kernel = gaussian_kernel_texture(ctx)
    target = (width + 2 * guard, height + 2 * guard)
    visibility = ctx.texture(target, 2, dtype="f4")
    accum = [ctx.texture(target, 4, dtype="f4") for _ in range(2)]
    for tex in (visibility, *accum):
        tex.filter = (ctx.NEAREST, ctx.NEAREST)
    vis_fbo = ctx.framebuffer(color_attachments=[visibility])
    accum_fbo = ctx.framebuffer(color_attachments=accum)
    out = GBuffer(width, height)
    empty = ctx.vertex_array(programs["PASS_NORMALIZE"], [])
    try:
        ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.enable(ctx.BLEND | ctx.PROGRAM_POINT_SIZE)
        mode = ctx.POINTS if sprites else ctx.TRIANGLE_STRIP
        kernel.use(0)

        vis_fbo.use()
        vis_fbo.clear(3.0e38, 1.0, 0, 0)
        ctx.blend_equation = ctx.MIN
        splats.draw(ctx, cloud, programs["PASS_VISIBILITY"], mode, instanced=not sprites, count=prefix)

        accum_fbo.use()
        accum_fbo.clear(0, 0, 0, 0)
        ctx.blend_equation = ctx.FUNC_ADD
        ctx.blend_func = ctx.ONE, ctx.ONE
        visibility.use(1)
        splats.draw(ctx, cloud, programs["PASS_ATTRIBUTE"], mode, instanced=not sprites, count=prefix)

        ctx.disable(ctx.BLEND)
        out.fbo.use()
        out.clear()
        visibility.use(1)
        accum[0].use(2)
        accum[1].use(3)
        empty.render(ctx.TRIANGLES, vertices=3)
        ctx.finish()
        stats = {"splats": len(cloud) if drawn is None else int(drawn.sum()), "supersample": ss, "ewa_filter": ewa_filter,
                 "primitive": "point sprites" if sprites else "quads"}
        result = gbuffer_result(out, camera, options, ss, stats)
        if options.dump_passes:
            dump_passes(options.dump_passes, visibility, accum, result, guard)
        return result
    finally:
        ctx.blend_equation = ctx.FUNC_ADD
        for obj in (kernel, visibility, *accum, vis_fbo, accum_fbo, empty):
            obj.release()
        out.release()


def dump_passes(folder, visibility, accum, result, guard: int) -> None:
    """The survey's Fig. 5: visibility depth, accumulated weight and colour, normalized result."""
    from PIL import Image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    inner = (slice(guard, visibility.height - guard), slice(guard, visibility.width - guard))
    depth = read_texture(visibility)[inner][..., 0]
    valid = depth < 1e37
    gray = np.zeros_like(depth)
    if valid.any():
        lo, hi = depth[valid].min(), depth[valid].max()
        gray[valid] = 1 - 0.8 * (depth[valid] - lo) / max(hi - lo, 1e-12)
    color = read_texture(accum[0])[inner]
    weight = color[..., 3] / max(float(color[..., 3].max()), 1e-12)

    def save(name, image):
        Image.fromarray(np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)).save(folder / name)

    save("1-visibility-depth.png", gray)
    save("2-accumulated-weight.png", weight)
    save("3-accumulated-color.png", np.clip(color[..., :3], 0, 1))
    save("4-normalized.png", result.color)
