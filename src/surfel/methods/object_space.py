"""`object-space`: object-space EWA surface splatting with textured quads.

Ren, Pfister & Zwicker 2002, "Object space EWA surface splatting: a hardware accelerated
approach to high quality point rendering" (survey 2.1.2). The EWA resampling filter is
built in the surfel's local tangent parameterisation u = (u_s, u_t) (p(u) = o + u_s s + u_t t):

    p'_k(u) = G_{M_k}(u),   M_k = V_k + J_k^-1 J_k^-T

with V_k the reconstruction kernel's variance (std KERNEL_STD x the splat semi-axes) and J_k
the Jacobian of the tangent-plane-to-image mapping at the surfel centre, so J_k^-1 J_k^-T is the
screen-space low-pass (std LOWPASS_STD x lowpass_radius pixels) mapped back to object space.
The symmetric 2x2 M_k = Rot(theta) diag(r0^2, r1^2) Rot(theta)^T gives

    u = Rot(theta) Lambda y,  Lambda = diag(r0, r1)                                 (eq. 3)
    G_{M_k}(Rot(theta) Lambda y) = 1 / (2 pi r0 r1) exp(-y.y / 2)                     (eq. 4)

a unit Gaussian in y. A quad's texture coordinates v in {0, 1}^2 map to y by

    y = 2 c (v - 1/2)                                                                 (eq. 5)

so the quad spans y in [-c, c]^2 and circumscribes the cutoff circle |y| = c (its corners lie
at |y| = sqrt(2) c, its edge midpoints on the circle). The survey's constant 2 sqrt(2) c is the
same quad when the cutoff is stated on the exponent, y.y / 2 <= c^2, i.e. |y| <= sqrt(2) c.
The vertex shader places the quad with eq. 3 and p(u); a 2D alpha texture holds exp(-y.y / 2)
(zero beyond the cutoff) and the vertex colour's alpha carries 1 / (r0 r1) (the 1 / 2 pi is
common to every surfel and dropped).

Passes (gl/passes.py): (1) visibility splatting, a square of side 2 r in each surfel's tangent
plane whose eye depth pushed back by z_t is MIN-blended into a float texture, together with
the pixel coverage of the disk inscribed in the square (for anti-aliased silhouettes); (2) the
textured quads, additively blended (w rgb, w, w n, w z) where no farther than that depth;
(3) a full-screen pass writing the G-buffer with deferred shading from the accumulated normals.

Normalization (`ObjectSpaceParams.normalization`): "per-surfel" is the paper's: a
preprocessing pass (on the CPU, cached per cloud) sums the neighbouring object-space kernels
at each surfel centre, S_k = sum_j G_{V_j}(x_k - x_j) (in j's tangent plane, the same cut-off,
unnormalised-by-2pi Gaussians the GPU draws) and scales the surfel's weight by 1 / S_k; the
accumulated colour is then used as it is. It darkens and mottles the surface wherever the
screen-space sums drift from 1 (measured on the bunny: 16 dB interior PSNR), so the default is
"per-pixel", the later improvement of Botsch & Kobbelt 2003: raw weights, colour divided by
the accumulated weight per pixel (40 dB interior). `--per-surfel-normalization` compares.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import PointCloud
from ..gl import splats
from ..gl.context import get_context
from ..gl.passes import UNIFORM_UNITS, SplatPasses
from ..gl.uniforms import apply_common
from .params import SplatParams

SHADER = Path(__file__).with_suffix(".glsl")
KERNEL_STD = 0.5            # reconstruction std / splat semi-axis: the cutoff sits at the radius
CUTOFF = 2.0                # c, in standard deviations of y
LOWPASS_STD = 0.5           # screen low-pass std / lowpass_radius (output pixels), as `deferred`
KERNEL_TEXELS = 32          # side of the discrete Gaussian alpha texture
DEFAULT_SUPERSAMPLE = 2
NEIGHBOURS = 32             # kernels summed per surfel centre in the normalization pass
QUERY_CHUNK = 500_000       # surfels per neighbour query (bounds memory on big clouds)


@dataclass(frozen=True)
class ObjectSpaceParams(SplatParams):
    # per-surfel darkens and mottles wherever the sums drift from 1: per-pixel by default
    normalization: Literal["per-pixel", "per-surfel"] = "per-pixel"


def surfel_weights(cloud: PointCloud, radius_scale: float = 1.0) -> np.ndarray:
    """Per-surfel normalization 1 / S_k, S_k = sum_j exp(-y.y/2) / (sigma_s sigma_t) of the
    neighbours' cut-off kernels at x_k."""
    axes = cloud.axes.astype(np.float64) * radius_scale
    sigma = KERNEL_STD * np.linalg.norm(axes, axis=2)                  # (N, 2)
    frame = axes / np.maximum(np.linalg.norm(axes, axis=2, keepdims=True), 1e-30)
    positions = cloud.local_positions().astype(np.float64)
    tree = cKDTree(positions)
    reach = CUTOFF * float(sigma.max())
    k = min(NEIGHBOURS, len(cloud))
    total = np.empty(len(cloud))
    for start in range(0, len(cloud), QUERY_CHUNK):
        stop = min(start + QUERY_CHUNK, len(cloud))
        dist, idx = tree.query(positions[start:stop], k=k, distance_upper_bound=reach)
        found = np.isfinite(dist)
        j = np.where(found, idx, 0)
        offset = positions[start:stop, None, :] - positions[j]          # x_k - x_j
        y = np.einsum("kjad,kjd->kja", frame[j], offset) / np.maximum(sigma[j], 1e-30)
        yy = (y**2).sum(axis=-1)
        kernel = np.exp(-0.5 * yy) / np.maximum(sigma[j].prod(axis=-1), 1e-60)
        total[start:stop] = np.where(found & (yy <= CUTOFF**2), kernel, 0.0).sum(axis=1)
    return (1.0 / np.maximum(total, 1e-30)).astype(np.float32)


def gaussian_texture(ctx):
    """The discrete Gaussian alpha texture exp(-y.y/2) over the quad, y = 2 c (v - 1/2)."""
    v = (np.arange(KERNEL_TEXELS) + 0.5) / KERNEL_TEXELS
    y = 2.0 * CUTOFF * (v - 0.5)
    yy = y[:, None] ** 2 + y[None, :] ** 2
    alpha = np.where(yy <= CUTOFF**2, np.exp(-0.5 * yy), 0.0).astype(np.float32)
    tex = ctx.texture((KERNEL_TEXELS, KERNEL_TEXELS), 1, alpha.tobytes(), dtype="f4")
    tex.repeat_x = tex.repeat_y = False
    return tex


def render_object_space(cloud, camera, options, params: ObjectSpaceParams, renderer):
    ctx = get_context()
    ss = options.supersample or DEFAULT_SUPERSAMPLE
    width, height = camera.width * ss, camera.height * ss
    per_surfel = params.normalization == "per-surfel"
    categorical = options.coloring is not None and options.coloring.categorical
    passes = ("PASS_VISIBILITY", "PASS_ATTRIBUTE", *(("PASS_CATEGORY",) if categorical else ()), "PASS_NORMALIZE")
    programs = {p: renderer.program(SHADER, {p: True, "PER_SURFEL_NORMALIZATION": per_surfel,
                                             "CLIP_LINES": "clip_lines" in cloud.attributes})
                for p in passes}
    for program in programs.values():
        apply_common(program, camera, cloud.local_origin, ss, options,
                     u_radius_scale=params.radius_scale, u_depth_offset=params.depth_offset,
                     u_kernel_std=KERNEL_STD, u_cutoff=CUTOFF,
                     u_lowpass_std=LOWPASS_STD * params.lowpass_radius * ss,
                     u_backface_culling=int(params.backface_culling), u_kernel=0, **UNIFORM_UNITS)
    extra = None
    if per_surfel:
        scale = params.radius_scale
        extra = {"in_weight": renderer.cached(cloud, ("surfel weights", scale),
                                              lambda: surfel_weights(cloud, scale))}

    renderer.use_color_table(options)
    kernel = gaussian_texture(ctx)
    buffers = renderer.splat_buffers(cloud)
    try:
        with SplatPasses(renderer.splat_targets(width, height)) as passes:
            kernel.use(0)
            passes.visibility_pass(lambda: splats.draw(ctx, buffers, programs["PASS_VISIBILITY"],
                                                       ctx.TRIANGLE_STRIP, instanced=True))
            passes.attribute_pass(lambda: splats.draw(ctx, buffers, programs["PASS_ATTRIBUTE"],
                                                      ctx.TRIANGLE_STRIP, instanced=True, extra=extra))
            if categorical:
                passes.category_pass(lambda: splats.draw(ctx, buffers, programs["PASS_CATEGORY"],
                                                         ctx.TRIANGLE_STRIP, instanced=True, extra=extra))
            passes.normalize_pass(programs["PASS_NORMALIZE"])
            stats = {"splats": len(cloud), "vertices": 4 * len(cloud), "supersample": ss,
                     "normalization": "per-surfel" if per_surfel else "per-pixel"}
            return passes.result(camera, options, ss, stats)
    finally:
        kernel.release()
