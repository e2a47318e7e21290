"""`mls-gpu`: GPU ray casting of the MLS point set surface, Tejada et al. 2006 (survey 2.3.2).

The same surface as the CPU `mls` (surface.py): adaptive kernel widths h_i, weights
w_i = exp(-|p_i - r|^2 / h_i^2 - |n_i - n_r|^2 / sigma_n^2 - (n_i . (r - p_i))^2 / (sigma_r h_i)^2)
within 2.5 h_i for the pixel's reference normal n_r, weighted plane fit, bivariate quadratic g
over it in units of the local width l = sum w_i h_i / sum w_i, the domain test and the edge
tests (edges.py). It is found per pixel by multi-pass rendering into float targets (gpu.glsl),
with no spatial data structure: a point's screen-space disc is the set of pixels whose ray or
hit it can influence.

0. pre-pass: the polynomial fitted at every sample p_i for its own normal. It is computed once
   per cloud on the CPU (surface.point_polynomials, numba, cached with the CPU tracer's scene)
   and uploaded once per cloud to storage buffers kept by the Renderer, as are the float
   targets of the passes (per frame size) -- where the paper renders one fragment per point to
   fit it on the GPU. The fit is the same operator as the per-pixel fits below.
1. intersection: per point, a quad over the screen bounds of its bounding sphere (radius
   domain * s_i); each fragment meets its pixel ray o + t d with the point's polynomial inside
   the sphere; the depth test keeps the nearest t (t is the eye depth: d_eye.z = -1), and the
   sample's normal n_i becomes the pixel's n_r. A full-screen pass then sets the depth of
   pixels without a hit to 0, so that the support passes skip them.
Then `iterations` times (default 3), at r = o + t d:
2. means: per point, a quad over its kernel support 2.5 h_i; fragments with |p_i - r| <
   2.5 h_i add w (x, 1), w n_i, w rgb, w h_i, the count of samples facing n_r and of those
   passing the domain test (x = (p_i - r) / u_scale, u_scale the median width) with additive
   blending. Each quad lies at the near end of its support and is depth tested (read only)
   against the hits' depths, so supports wholly behind the surface never reach the fragment
   shader -- a third of the cost on llvmpipe;
3. frame (full screen): q = r + mean, n = sum w n_i normalised (surface.fit), and l;
   too few facing samples, the domain test failing or normals that cancel out or turn away
   from n_r make the pixel a miss;
4. system: the supports again; with (u, v, f) the coordinates of (p_i - q) / l in (e1, e2, n),
   the normal equations of  min sum w (g(u, v) - f)^2  need only the 15 moments w u^a v^b
   (a + b <= 4) and the 6 sums w f u^a v^b (a + b <= 2): six RGBA32F targets, full system;
   a seventh sums the half-disc test's area-weighted offsets of the samples from r, and
   a spare channel counts the extent test's samples (edges.sample_beyond);
5. solve + re-intersect (full screen): Cholesky of the 6x6 (double precision; where it is
   singular, again with surface.fit's regularisation), then the ray meets the new quadratic
   within 2.5 l of r (the CPU tracer's window) -- the next t, whose window depth is rewritten
   for the next culling test. As in the CPU tracer, the last iterates above and below their
   fits bracket the surface (a target of their t and heights): where the ray misses the new
   quadratic or r's height did not shrink, and the next t falls outside the bracket, the next
   t is the false position between them (Illinois). The last step keeps its hit only within
   LAST_HEIGHT local widths of its fit (the CPU tracer iterates to its tolerance). Without
   the two a grazing ray overshot further each step, and a ray passing between a coarse
   part's rings kept a point in the air: spot's front view at 512 x 512 went 36.05 -> 38.18
   dB against the mesh (the bright line along the top of her back thinner; 38.68 -> 43.17 dB
   against the CPU tracer), the bunny's two views within 0.1 dB, fandisk's front 32.99 ->
   32.36 dB (the CPU tracer's 31.64), its oblique view within 0.05 dB. The fit's normal at
   the new point is the next n_r for the first REFERENCE_UPDATES steps, as on the CPU. At the
   last step the half-disc and extent tests reject a hit past the edge of its sheet.
6. keep / retry: converged pixels keep their hit; where the fits failed, the next candidate
   (`candidates`, default 8) is the nearest intersection beyond the failed one -- the CPU
   tracer's walk on to the next bounding sphere, bounded here to a few candidates. An
   occlusion query counts the pixels that failed, and the walk stops when none did: the
   later candidates' passes would draw every support for nothing.
7. shading normal, once for the kept hits of all candidates: their window depths (the
   supports' culling reads them), passes 2 to 4 under the shading weights for each hit's
   normal as n_r, and the gradient of that quadratic at the hit (the pass-5 source with
   SHADING_NORMAL defined), as the CPU tracer shades (surface.py: shading normal); where that
   fit fails, the last step's normal stays. Done once per frame rather than per candidate:
   the bunny at 512 x 512 on llvmpipe (2 cores), run back to back, 15.1 s without the shading
   normal, 20.6 s with it per candidate, 14.7 s once (`surfel bench --methods mls-gpu@gl`).
8. shading (full screen): the normal, the last fit's weighted neighbour colour, eye depth t,
   into the G-buffer layout; supersampled 2x2 by default and box filtered
   (RenderResult.from_samples) for anti-aliased silhouettes.

Parameters (`MlsGpuParams`): the surface's (surface.MlsKernel: h_scale, domain, normal_sigma,
residual_sigma, boundary, shading_normal_sigma, shading_residual_sigma), as in `mls`;
iterations (3), candidates (8). Shadows and reflections are the CPU tracer's only.
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
from .edges import EDGE_LATERAL, EDGE_SHEET_COS
from .polynomial import P_C, P_E1, P_E2, P_N, P_Q, P_SCALE
from .raytrace import DEFAULT_SUPERSAMPLE, TOLERANCE, MLSScene, cached_scene, scene_kernel
from .surface import (
    MIN_NEIGHBOURS,
    REFERENCE_UPDATES,
    RIDGE,
    MlsKernel,
)

SHADER = Path(__file__).with_suffix(".glsl")
FAR = 3.0e38


@dataclass(frozen=True)
class MlsGpuParams(MlsKernel):
    iterations: int = setting(3, at_least(1))  # projection steps after the first intersection
    candidates: int = setting(8, at_least(1))  # intersections tried per pixel, nearest first (4 left 0.38% holes)


def pack_points(scene: MLSScene) -> np.ndarray:
    """(N, 3, 4) float32: (p_i, h_i), (colour, s_i), (n_i, h_scale m_i), positions relative to the local origin."""
    s = scene.surface
    out = np.zeros((len(s.points), 3, 4), np.float32)
    out[:, 0, :3] = s.points
    out[:, 0, 3] = s.samples.h
    out[:, 1, :3] = s.samples.colors
    out[:, 1, 3] = s.samples.spacing
    out[:, 2, :3] = s.normals
    out[:, 2, 3] = s.density_width
    return out


def pack_polynomials(scene: MLSScene) -> np.ndarray:
    """(N, 6, 4) float32: (q, valid), (n, 0), (e1, 0), (e2, 0), (c0..c3), (c4, c5, l, 0)."""
    polys = scene.polys
    out = np.zeros((len(polys), 6, 4), np.float32)
    out[:, 0, :3] = polys[:, P_Q:P_Q + 3]
    out[:, 0, 3] = scene.valid
    out[:, 1, :3] = polys[:, P_N:P_N + 3]
    out[:, 2, :3] = polys[:, P_E1:P_E1 + 3]
    out[:, 3, :3] = polys[:, P_E2:P_E2 + 3]
    out[:, 4] = polys[:, P_C:P_C + 4]
    out[:, 5, :2] = polys[:, P_C + 4:P_C + 6]
    out[:, 5, 2] = polys[:, P_SCALE]
    return out


class SceneBuffers:
    """The two storage buffers of a scene, uploaded once per cloud and kernel (kept by the Renderer)."""

    def __init__(self, scene: MLSScene):
        ctx = get_context()
        self.points, self.polys = ctx.buffer(pack_points(scene)), ctx.buffer(pack_polynomials(scene))

    def release(self) -> None:
        self.points.release()
        self.polys.release()


class CasterTargets:
    """The float targets of the passes at one (supersampled) size, kept by the Renderer from
    one frame to the next: the hit state and reference normal (ping-pong), the support sums,
    the reference frame, the normal equations, the surface's normal and albedo, the G-buffer."""

    def __init__(self, size: tuple[int, int]):
        ctx = get_context()

        def texture():
            tex = ctx.texture(size, 4, dtype="f4")
            tex.filter = (ctx.NEAREST, ctx.NEAREST)
            return tex

        self.state = [texture(), texture()]
        self.reference = [texture(), texture()]
        self.bracket = [texture(), texture()]  # the false position's iterates above and below
        self.sums = [texture() for _ in range(4)]
        self.frame = [texture(), texture()]
        self.system = [texture() for _ in range(7)]
        self.normal, self.albedo = texture(), texture()
        self.first = texture()  # t of a candidate
        # t of a candidate whose fits failed, and 1 there: a power-of-two size for mipmaps
        # whose texels cover whole blocks of pixels (gpu.glsl nothing_to_retry)
        self.failed = ctx.texture(tuple(1 << (side - 1).bit_length() for side in size), 2, dtype="f4")
        self.kept = [texture() for _ in range(3)]  # state, normal and albedo of converged candidates
        self.depth = ctx.depth_texture(size)  # window depth of the current hits
        self.solve = [ctx.framebuffer(color_attachments=[self.state[k], self.reference[k], self.normal, self.albedo,
                                                         self.bracket[k]],
                                      depth_attachment=self.depth) for k in range(2)]
        self.intersect = ctx.framebuffer(color_attachments=[self.state[0], self.reference[0], self.first,
                                                            self.bracket[0]],
                                         depth_attachment=self.depth)
        self.cull = ctx.framebuffer(depth_attachment=self.depth)
        self.keep = ctx.framebuffer(color_attachments=self.kept)
        self.shading = ctx.framebuffer(color_attachments=[self.kept[1]])  # the shading normal over the kept one
        self.retry = ctx.framebuffer(color_attachments=[self.failed])
        self.means = ctx.framebuffer(color_attachments=self.sums, depth_attachment=self.depth)
        self.frame_fbo = ctx.framebuffer(color_attachments=self.frame)
        self.system_fbo = ctx.framebuffer(color_attachments=self.system, depth_attachment=self.depth)
        for fbo in (self.means, self.system_fbo):
            fbo.depth_mask = False  # their depth test reads the hits' depths, never writes
        self.gbuffer = GBuffer(*size)
        # pixels whose candidate failed, counted (moderngl frees queries with the context)
        self.retries = ctx.query(samples=True)

    def release(self) -> None:
        for obj in (*self.state, *self.reference, *self.bracket, *self.sums, *self.frame, *self.system, self.normal,
                    self.albedo, self.first, self.failed, *self.kept, self.depth, *self.solve,
                    self.intersect, self.cull, self.means, self.frame_fbo, self.system_fbo, self.keep, self.shading,
                    self.retry):
            obj.release()
        self.gbuffer.release()


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
    buffers = renderer.cached_gl(cloud, ("mls buffers", scene_kernel(params)), lambda: SceneBuffers(scene))
    size = (camera.width * ss, camera.height * ss)
    check_target_size(*size)
    targets = renderer.targets("mls caster", size, lambda: CasterTargets(size))
    view = camera.view_matrix(surface.origin)
    # the surface's weights and bounds as its scene holds them for the CPU tracer: one source
    weights = surface.samples
    common = {"u_view_inv": np.linalg.inv(view), "u_scale": surface.scale, "u_domain": surface.domain,
              "u_normal_weight": weights.normal_weight, "u_residual_weight": weights.residual_weight,
              "u_boundary": weights.boundary,
              "u_edge_cos": EDGE_SHEET_COS, "u_edge_lateral": EDGE_LATERAL,
              "u_ridge": RIDGE, "u_min_neighbours": float(MIN_NEIGHBOURS), "u_tolerance": TOLERANCE,
              "u_guard": 0.0}
    programs = {name: renderer.program(SHADER, {f"PASS_{name.upper()}": True})
                for name in ("intersect", "cull", "means", "frame", "system", "solve", "keep", "retry", "shade")}
    programs["shading"] = renderer.program(SHADER, {"PASS_SOLVE": True, "SHADING_NORMAL": True})
    for program in programs.values():
        apply_common(program, camera, surface.origin, ss, options, **common)
    renderer.use_color_table(options)
    vaos = {name: ctx.vertex_array(prog, []) for name, prog in programs.items()}

    def fit(state, reference) -> None:
        """Passes 2 to 4 at the hits of the texture `state`, for the reference normals of the
        texture `reference`, under the weights the programs hold."""
        # 2. weighted sums about r; the depth test (read only) culls supports behind r
        ctx.enable(ctx.BLEND | ctx.DEPTH_TEST)
        ctx.depth_func = "<="
        ctx.blend_equation = ctx.FUNC_ADD
        ctx.blend_func = ctx.ONE, ctx.ONE
        targets.means.use()
        targets.means.clear(0.0, 0.0, 0.0, 0.0)
        _bind(programs["means"], {"u_state": state, "u_reference": reference,
                                  "u_failed": targets.failed})
        discs("means")
        # 3. reference plane
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        targets.frame_fbo.use()
        _bind(programs["frame"], {"u_state": state, "u_reference": reference,
                                  "u_sum": targets.sums[0], "u_normal_sum": targets.sums[1],
                                  "u_inside": targets.sums[2], "u_color": targets.sums[3]})
        full_screen("frame")
        # 4. normal equations of the quadratic
        ctx.enable(ctx.BLEND | ctx.DEPTH_TEST)
        targets.system_fbo.use()
        targets.system_fbo.clear(0.0, 0.0, 0.0, 0.0)
        _bind(programs["system"], {"u_state": state, "u_reference": reference,
                                   "u_q": targets.frame[0], "u_n": targets.frame[1], "u_failed": targets.failed})
        discs("system")

    def iterate(step: int, current: int) -> int:
        """One projection step of every pixel's hit: passes 2 to 5; returns the new state's index."""
        fit(targets.state[current], targets.reference[current])
        # 5. solve and move along the ray onto the quadratic, rewriting the hit depths
        ctx.disable(ctx.BLEND)
        ctx.depth_func = "1"
        targets.solve[1 - current].use()
        set_uniforms(programs["solve"], u_last=step == iterations - 1, u_update_reference=step < REFERENCE_UPDATES)
        _bind(programs["solve"], {"u_state": targets.state[current], "u_reference": targets.reference[current],
                                  "u_q": targets.frame[0], "u_n": targets.frame[1],
                                  **{f"u_m{k}": targets.system[k] for k in range(7)},
                                  "u_color": targets.sums[3], "u_weight": targets.sums[0],
                                  "u_bracket": targets.bracket[current]})
        full_screen("solve")
        return 1 - current

    buffers.points.bind_to_storage_buffer(0)
    buffers.polys.bind_to_storage_buffer(1)

    def discs(name):
        vaos[name].render(ctx.TRIANGLE_STRIP, vertices=4, instances=n)

    def full_screen(name):
        vaos[name].render(ctx.TRIANGLES, vertices=3)

    try:
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        targets.keep.clear(FAR, 0.0, 0.0, 0.0)
        for candidate in range(params.candidates):
            # 1. nearest intersection with the points' own polynomials (the depth test keeps the
            # nearest t and its sample's normal); later candidates lie beyond a failed one
            ctx.enable(ctx.DEPTH_TEST)
            targets.intersect.use()
            targets.intersect.clear(FAR, 0.0, 0.0, 0.0, depth=1.0)
            ctx.depth_func = "<"
            for name in ("intersect", "means", "system"):
                set_uniforms(programs[name], u_retry=candidate > 0)
            _bind(programs["intersect"], {"u_failed": targets.failed})
            discs("intersect")
            targets.cull.use()
            ctx.depth_func = "1"
            _bind(programs["cull"], {"u_state": targets.state[0]})
            full_screen("cull")
            current = 0
            for step in range(iterations):
                current = iterate(step, current)
            # 6. keep what converged; the t of the candidates that failed bounds the next ones
            ctx.disable(ctx.DEPTH_TEST)
            targets.keep.use()
            _bind(programs["keep"], {"u_state": targets.state[current], "u_normal": targets.normal,
                                     "u_albedo": targets.albedo})
            full_screen("keep")
            if candidate + 1 < params.candidates:
                targets.retry.use()
                targets.retry.clear(FAR, 0.0, 0.0, 0.0)
                ctx.viewport = (0, 0, *size)  # the pixels of the image in the larger texture
                _bind(programs["retry"], {"u_state": targets.state[current], "u_first": targets.first})
                with targets.retries:
                    full_screen("retry")
                if targets.retries.samples == 0:  # every pixel hit or missed for good: no later candidate
                    break
                targets.failed.build_mipmaps()
        # 7. the shading normal of every kept hit: the hits' depths (the supports' culling reads
        # them), passes 2 to 4 under its weights for the hit's normal, and that fit's gradient
        ctx.enable(ctx.DEPTH_TEST)
        ctx.depth_func = "1"
        targets.cull.use()
        _bind(programs["cull"], {"u_state": targets.kept[0]})
        full_screen("cull")
        for name in ("means", "system"):  # the frame's next call sets the surface's weights again
            set_uniforms(programs[name], u_retry=False, u_normal_weight=surface.shading.normal_weight,
                         u_residual_weight=surface.shading.residual_weight)
        fit(targets.kept[0], targets.kept[1])
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        targets.shading.use()
        _bind(programs["shading"], {"u_state": targets.kept[0], "u_q": targets.frame[0], "u_n": targets.frame[1],
                                    **{f"u_m{k}": targets.system[k] for k in range(6)}})
        full_screen("shading")
        # 8. shading into the G-buffer
        targets.gbuffer.fbo.use()
        targets.gbuffer.clear()
        _bind(programs["shade"], {"u_state": targets.kept[0], "u_normal": targets.kept[1],
                                  "u_albedo": targets.kept[2]})
        full_screen("shade")
        ctx.finish()
        final = read_texture(targets.kept[0], 2)
        hit = final[..., 0] < FAR / 10
        steps = final[..., 1][hit]
        stats = {"splats": n, "rays": int(size[0] * size[1]), "hits": int(hit.sum()), "iterations": iterations,
                 "candidates_tried": candidate + 1,
                 "last_step_median": float(np.median(steps)) if steps.size else 0.0,
                 "point_fit_failures": int((~scene.valid).sum()), "supersample": ss,
                 "kernel_width": surface.scale, "polynomial_prepass": "cpu"}
        return gbuffer_result(targets.gbuffer, camera, options, ss, stats,
                              surface=renderer.surface_colors(cloud, camera.supersampled(ss), options))
    finally:
        ctx.blend_equation = ctx.FUNC_ADD
        ctx.depth_func = "<"
        for vao in vaos.values():
            vao.release()
