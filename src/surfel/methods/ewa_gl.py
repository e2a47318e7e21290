"""`ewa`, OpenGL backend: EWA surface splatting (Zwicker, Pfister, van Baar & Gross 2001).

The same full screen-space resampling filter as the CPU backend (equations in ewa.py):
per splat k, at its centre, J = dP/dx(c_k) [u_k v_k], M = J V J^T + l^2 I with V = sigma^2 I,
and the resampling filter

    rho_k(x) = |det J| / sqrt(det M) exp(-1/2 (x - m_k)^T M^-1 (x - m_k)),

cut where (x - m_k)^T M^-1 (x - m_k) > R^2. The vertex stage of ewa_gl.glsl computes J, the
conic M^-1, the amplitude |det J| / sqrt(det M), the splat plane's depth gradient h J^-1 and
the pixel box of the cut ellipse for each instance and draws a screen-aligned quad over the
box; the fragment stage evaluates the conic at the pixel centre. The CPU's visibility, as
three draws (z_t here is depth_offset x radius widened by the clamped depth range):

1. visibility: Z = min over fragments of (clamped plane depth + z_t), over the narrow
   footprint N = J V J^T + v^2 I, and the most any of them covers the pixel (gl/passes.py,
   MIN blending of 1 - coverage);
2. back layer: Z_b = min plane depth over the fragments behind Z (MIN blending);
3. accumulation: w rgb, w, w n, w z of the fragments with depth <= Z into the front layer, of
   those with Z < depth <= Z_b + z_t into the back layer (additive blending into four RGBA32F
   targets, the channel order of ewa_kernels.ACC_CHANNELS). The CPU keeps the back layer as a
   running z-buffer in draw order; this order-independent form is its end state, so the two
   differ only where draw order mattered there.

The accumulators and the coverage are read back and resolved by ewa.resolve_accumulators
(normalisation, alpha, deferred shading), so both backends share that step exactly.
"""

from __future__ import annotations

from pathlib import Path

from ..camera import Camera
from ..cloud import PointCloud
from ..gl import splats
from ..gl.context import get_context
from ..gl.passes import BACK_LAYER_UNITS, SplatPasses
from ..gl.uniforms import apply_common
from ..options import RenderOptions
from ..result import RenderResult
from .ewa import DEFAULT_SUPERSAMPLE, EwaParams, resolve_accumulators, spatially_ordered, target_camera

SHADER = Path(__file__).with_suffix(".glsl")
PASSES = ("PASS_VISIBILITY", "PASS_BACK", "PASS_ATTRIBUTE")


def render_ewa_gl(cloud: PointCloud, camera: Camera, options: RenderOptions, params: EwaParams,
                  renderer) -> RenderResult:
    """EWA splatting with instanced quads on the OpenGL pipeline; see the module docstring."""
    cloud = renderer.cached(cloud, "morton order", lambda: spatially_ordered(cloud))  # the CPU's order
    ctx = get_context()
    supersample = options.supersample or DEFAULT_SUPERSAMPLE
    target = target_camera(camera, supersample)
    categorical = options.coloring is not None and options.coloring.categorical
    programs = {p: renderer.program(SHADER, {p: True}) for p in (*PASSES, *(("PASS_CATEGORY",) if categorical else ()))}
    for program in programs.values():
        # The target camera already carries the supersampling: factor 1 here.
        apply_common(program, target, cloud.local_origin, 1, options,
                     u_radius_scale=params.radius_scale, u_sigma2=params.sigma ** 2,
                     u_lowpass2=params.lowpass ** 2, u_vis2=params.visibility ** 2, u_cutoff2=params.cutoff2,
                     u_depth_offset=params.depth_offset, u_depth_clamp=params.depth_clamp,
                     u_backface_culling=int(params.backface_culling), **BACK_LAYER_UNITS)
    fragments = ctx.query(samples=True)
    buffers = renderer.splat_buffers(cloud)

    def draw(name: str):
        return lambda: splats.draw(ctx, buffers, programs[name], ctx.TRIANGLE_STRIP, instanced=True)

    with SplatPasses(renderer.splat_targets(target.width, target.height, back_layer=True)) as passes:
        passes.visibility_pass(draw("PASS_VISIBILITY"))
        passes.back_pass(draw("PASS_BACK"))
        with fragments:  # the fragments blended into either layer, as the CPU's count
            passes.attribute_pass(draw("PASS_ATTRIBUTE"))
        categories = None
        if categorical:
            passes.category_pass(draw("PASS_CATEGORY"))
            categories = passes.categories()
        acc = passes.accumulators()
        stats = {"splats": len(cloud), "fragments": int(fragments.samples)}
        result = resolve_accumulators(acc, passes.coverage(), target, options, params, supersample, stats,
                                      categories)
        if options.dump_passes is not None:
            passes.dump(options.dump_passes, result)
    return result
