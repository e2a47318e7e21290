"""`mls-gpu`: GPU ray casting of the MLS point set surface, Tejada et al. 2006 (survey 2.3.2).

The same surface as the CPU `mls` (surface.py: Gaussian weights w_i = exp(-|p_i - r|^2 / h_i^2)
within 2.5 h_i, weighted plane fit, bivariate quadratic g over it, domain test), found per pixel
by multi-pass rendering into float targets (gpu.glsl), with no spatial data structure: a
point's screen-space disc is the set of pixels whose ray or hit it can influence.

0. pre-pass: the polynomial fitted at every sample p_i. It is computed once per cloud on the
   CPU (surface.point_polynomials, numba, cached with the CPU tracer's scene) and uploaded to a
   storage buffer -- where the paper renders one fragment per point to fit it on the GPU. The
   fit is the same operator as the per-pixel fits below, so the result is the same.
1. intersection: per point, a quad over the screen bounds of its bounding sphere (radius
   domain * s_i); each fragment meets its pixel ray o + t d with the point's polynomial inside
   the sphere; the nearest t survives MIN blending (t is the eye depth: d_eye.z = -1).
Then `iterations` times (default 3), at r = o + t d:
2. covariance: per point, a quad over its kernel support 2.5 h_i; fragments with |p_i - r| <
   2.5 h_i add w (x, 1), w x x^T, the neighbour count, the domain-test count and w rgb
   (x = (p_i - r) / h, h the median kernel width) with additive blending. Each quad lies at
   the near end of its support and is depth tested (read only) against the hits' depths, so
   supports wholly behind the surface (the far side of a closed object) never reach the
   fragment shader -- a third of the cost on llvmpipe;
3. frame (full screen): q = r + mean, C = sum w x x^T - W m m^T, n its smallest eigenvector;
   too few neighbours, the domain test failing or a degenerate C make the pixel a miss;
4. system: the supports again; with (u, v, f) the coordinates of (p_i - q) / h in (e1, e2, n),
   the normal equations of  min sum w (g(u, v) - f)^2  need only the 15 moments w u^a v^b
   (a + b <= 4) and the 6 sums w f u^a v^b (a + b <= 2): six RGBA32F targets, full system;
5. solve + re-intersect (full screen): Cholesky of the 6x6 (double precision), then the ray
   meets the new quadratic within 2.5 h of r (the CPU tracer's window) -- the next t, whose
   window depth is rewritten for the next culling test. Where the CPU tracer moves on to the
   next bounding sphere after a failed fit, a pixel here becomes a miss.
6. shading (full screen): normal n - g_u e1 - g_v e2 of the last quadratic, the fit's weighted
   neighbour colour, eye depth t, into the G-buffer layout; supersampled 2x2 by default and
   box filtered (RenderResult.from_samples) for anti-aliased silhouettes.

Parameters (`MlsGpuParams`): h_scale (1.5), domain (2.0) as in `mls` (surface.MlsKernel);
iterations (3). Shadows and reflections are the CPU tracer's only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..cloud import PointCloud
from ..gl.context import get_context
from ..gl.program import set_uniforms
from ..gl.targets import GBuffer, check_target_size, gbuffer_result, read_texture
from ..gl.uniforms import apply_common
from ..options import RenderOptions, at_least, setting
from ..result import RenderResult
from .raytrace import DEFAULT_SUPERSAMPLE, MLSScene, cached_scene
from .surface import P_C, P_E1, P_E2, P_N, P_Q, SUPPORT, MlsKernel

SHADER = Path(__file__).with_suffix(".glsl")
FAR = 3.0e38


@dataclass(frozen=True)
class MlsGpuParams(MlsKernel):
    iterations: int = setting(3, at_least(1))  # projection steps after the first intersection


def pack_points(scene: MLSScene) -> np.ndarray:
    """(N, 2, 4) float32: (p_i, h_i), (colour, s_i), positions relative to the local origin."""
    s = scene.surface
    out = np.empty((len(s.points), 2, 4), np.float32)
    out[:, 0, :3] = s.points
    out[:, 0, 3] = s.h
    out[:, 1, :3] = s.colors
    out[:, 1, 3] = s.spacing
    return out


def pack_polynomials(scene: MLSScene) -> np.ndarray:
    """(N, 6, 4) float32: (q, valid), (n, 0), (e1, 0), (e2, 0), (c0..c3), (c4, c5, 0, 0)."""
    polys = scene.polys
    out = np.zeros((len(polys), 6, 4), np.float32)
    out[:, 0, :3] = polys[:, P_Q:P_Q + 3]
    out[:, 0, 3] = scene.valid
    out[:, 1, :3] = polys[:, P_N:P_N + 3]
    out[:, 2, :3] = polys[:, P_E1:P_E1 + 3]
    out[:, 3, :3] = polys[:, P_E2:P_E2 + 3]
    out[:, 4] = polys[:, P_C:P_C + 4]
    out[:, 5, :2] = polys[:, P_C + 4:P_C + 6]
    return out


class SceneBuffers:
    """The two storage buffers of a scene, uploaded once per cloud and kernel (kept by the Renderer)."""

    def __init__(self, scene: MLSScene):
        ctx = get_context()
        self.points, self.polys = ctx.buffer(pack_points(scene)), ctx.buffer(pack_polynomials(scene))

    def release(self) -> None:
        self.points.release()
        self.polys.release()


def _bind(program, textures: dict) -> None:
    """Bind sampler uniforms to consecutive texture units (those the program uses)."""
    unit = 0
    for name, texture in textures.items():
        set_uniforms(program, **{name: unit})  # refuses a name the source does not declare
        if name in program:
            texture.use(unit)
            unit += 1


def render_mls_gl(cloud: PointCloud, camera: Camera, options: RenderOptions, params: MlsGpuParams,
                  renderer) -> RenderResult:
    ctx = get_context()
    ss = options.supersample or DEFAULT_SUPERSAMPLE
    iterations = params.iterations
    scene = cached_scene(cloud, params, renderer)
    surface = scene.surface
    n = len(surface.points)
    buffers = renderer.cached_gl(cloud, ("mls buffers", params.h_scale, params.domain), lambda: SceneBuffers(scene))
    view = camera.view_matrix(surface.origin)
    common = {"u_view_inv": np.linalg.inv(view), "u_scale": surface.scale, "u_domain": surface.domain,
              "u_window": SUPPORT * surface.scale, "u_guard": 0.0}
    programs = {name: renderer.program(SHADER, {f"PASS_{name.upper()}": True})
                for name in ("intersect", "covariance", "frame", "system", "solve", "shade")}
    for program in programs.values():
        apply_common(program, camera, surface.origin, ss, options, **common)
    renderer.use_color_table(options)
    size = (camera.width * ss, camera.height * ss)
    check_target_size(*size)

    def texture():
        tex = ctx.texture(size, 4, dtype="f4")
        tex.filter = (ctx.NEAREST, ctx.NEAREST)
        return tex

    state = [texture(), texture()]
    cov = [texture() for _ in range(4)]
    frame = [texture() for _ in range(2)]
    system = [texture() for _ in range(6)]
    surf = [texture() for _ in range(2)]  # normal, albedo of the last fit
    depth = ctx.depth_texture(size)  # window depth of the current hits
    fbos = {
        "state": [ctx.framebuffer(color_attachments=[state[k], *surf], depth_attachment=depth) for k in range(2)],
        "intersect": ctx.framebuffer(color_attachments=[state[0]], depth_attachment=depth),
        "covariance": ctx.framebuffer(color_attachments=cov, depth_attachment=depth),
        "frame": ctx.framebuffer(color_attachments=frame),
        "system": ctx.framebuffer(color_attachments=system, depth_attachment=depth),
    }
    gbuffer = GBuffer(*size)
    vaos = {name: ctx.vertex_array(prog, []) for name, prog in programs.items()}
    buffers.points.bind_to_storage_buffer(0)
    buffers.polys.bind_to_storage_buffer(1)

    def discs(name):
        vaos[name].render(ctx.TRIANGLE_STRIP, vertices=4, instances=n)

    def full_screen(name):
        vaos[name].render(ctx.TRIANGLES, vertices=3)

    try:
        ctx.disable(ctx.CULL_FACE)
        ctx.enable(ctx.BLEND | ctx.DEPTH_TEST)
        # 1. nearest intersection with the points' own polynomials: t by MIN blending, its
        # window depth by the depth test
        fbos["intersect"].use()
        fbos["intersect"].clear(FAR, 0.0, 0.0, 0.0, depth=1.0)
        ctx.depth_func = "<"
        ctx.blend_equation = ctx.MIN
        discs("intersect")
        current = 0
        for _ in range(iterations):
            # 2. weighted sums about r; the depth test (read only) culls supports behind r
            ctx.enable(ctx.DEPTH_TEST)
            ctx.depth_func = "<="
            for name in ("covariance", "system"):
                fbos[name].depth_mask = False
            ctx.enable(ctx.BLEND)
            ctx.blend_equation = ctx.FUNC_ADD
            ctx.blend_func = ctx.ONE, ctx.ONE
            fbos["covariance"].use()
            fbos["covariance"].clear(0.0, 0.0, 0.0, 0.0)
            _bind(programs["covariance"], {"u_state": state[current]})
            discs("covariance")
            # 3. reference plane
            ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
            fbos["frame"].use()
            _bind(programs["frame"], {"u_state": state[current], "u_sum": cov[0], "u_xx": cov[1],
                                           "u_yz": cov[2]})
            full_screen("frame")
            # 4. normal equations of the quadratic
            ctx.enable(ctx.BLEND | ctx.DEPTH_TEST)
            fbos["system"].use()
            fbos["system"].clear(0.0, 0.0, 0.0, 0.0)
            _bind(programs["system"], {"u_state": state[current], "u_q": frame[0], "u_n": frame[1]})
            discs("system")
            # 5. solve and move along the ray onto the quadratic, rewriting the hit depths
            ctx.disable(ctx.BLEND)
            ctx.depth_func = "1"
            fbos["state"][1 - current].use()
            _bind(programs["solve"], {"u_state": state[current], "u_q": frame[0], "u_n": frame[1],
                                           **{f"u_m{k}": system[k] for k in range(6)},
                                           "u_color": cov[3], "u_weight": cov[0]})
            full_screen("solve")
            current = 1 - current
        # 6. shading into the G-buffer
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        gbuffer.fbo.use()
        gbuffer.clear()
        _bind(programs["shade"], {"u_state": state[current], "u_normal": surf[0], "u_albedo": surf[1]})
        full_screen("shade")
        ctx.finish()
        final = read_texture(state[current], 2)
        hit = final[..., 0] < FAR / 10
        steps = final[..., 1][hit]
        stats = {"splats": n, "rays": int(size[0] * size[1]), "hits": int(hit.sum()), "iterations": iterations,
                 "last_step_median": float(np.median(steps)) if steps.size else 0.0,
                 "point_fit_failures": int((~scene.valid).sum()), "supersample": ss,
                 "kernel_width": surface.scale, "polynomial_prepass": "cpu"}
        return gbuffer_result(gbuffer, camera, options, ss, stats,
                              surface=renderer.surface_colors(cloud, camera.supersampled(ss), options))
    finally:
        ctx.blend_equation = ctx.FUNC_ADD
        ctx.depth_func = "<"
        for obj in (depth, *vaos.values(), *state, *cov, *frame, *system, *surf,
                    *fbos["state"], fbos["intersect"], fbos["covariance"], fbos["frame"], fbos["system"]):
            obj.release()
        gbuffer.release()
