"""GPU surface splatting in three passes: `gaussian` and `deferred`.

`gaussian` -- Botsch & Kobbelt 2003, "High-quality point-based rendering on modern GPUs"
(survey 2.1.3): splats rasterized as screen-aligned quads covering the projected disk
(eq. 6 made conservative: the bounding box of the disk's projected bounding square),
elliptical shape and per-pixel depth from the exact ray-disk intersection
q = o + d (c - o).n / d.n (the δz offset of the survey, perspective accurate), a Gaussian
weight alpha = G(|(u, v)|) looked up in a 1D texture, and three passes:
  1. visibility: the nearest eye depth pushed back by z_t (MIN blending into a float target);
  2. attribute: additive blending of (w rgb, w, w n, w z) of fragments no farther than it;
     the visibility depth is copied into a depth buffer first and each splat drawn at the
     least depth any of its fragments can have (its plane's depth at the corners of its
     screen box, the least of a function whose reciprocal is affine there), so the early
     depth test drops hidden splats' fragments before their shader runs: the sums are the
     same, the work less (gl/passes.py);
  3. normalization: rgb = sum(w rgb) / sum(w).
Colours are shaded per splat before blending: the Gouraud look of the survey's Fig. 6.

`deferred` -- Botsch, Hornung, Zwicker & Kobbelt 2005, "High-quality surface splatting on
today's GPUs" (survey 2.1.5, 2.1.6): the same visibility pass; the attribute pass blends
albedo and normals into two render targets; the shading pass lights every pixel from its
normalized normal and depth. With the EWA filter approximation (on by default) a fragment's
distance is min(|(u, v)|², |x - m(c)|² / r_lp²): the union of the object-space
reconstruction kernel and a screen-space low-pass of radius r_lp ≈ 1 pixel, so every
splat covers at least 2x2 pixels and minified textures do not alias (Fig. 10). Splats are
two-sided, each turned to face the camera; where front- and back-facing splats blend (a
closed surface's outline), a back one weighs BACK_SPLAT_WEIGHT (splatting.glsl), so the
blended normal is the front's, not an average that faces the camera (+1 to +2.7 dB on coarse
figures, `surfel compare`). A back splat's z_t is also BACK_SPLAT_BEHIND radii longer (capped
by the layer's thickness like any z_t), so that it hides no front splat lying within a radius
or so behind it: near a closed surface's outline a back splat's disk can reach that far in
front of the front's, won the visibility pass, and drew a crescent lit by its turned normal
(the demo's chin, `tests/test_splatting.py`); a sheet seen from behind still hides what lies
farther back (13 models' vertices: mean +0.03 dB, homer +0.5 dB; raw scans unchanged). A
low-pass fragment off its splat's disk filters but hides
nothing in the visibility pass: at an occluding contour the edge-on splats in front would
otherwise claim a pixel-wide band of the surface behind, drawn with their grazing normals
(ogre, 512x512, front and oblique: +1.9 dB). Beyond the paper, the splats are elliptical
(fitted where the cloud brings no radii; circles of given radii are kept) and curved as
`phong`'s (below) -- the ray meets the surface their fitted normal field
describes, so a splat ends at the true contour (issue 17: a coarse CAD part in an oblique
view, 26.0 dB flat, 30.3 dB curved, 30.7 dB with the low-pass hiding nothing; phong 31.6 dB).
Each fragment's normal is its splat's linear normal field, `phong`'s (below), evaluated
where the ray meets the splat (`DeferredParams.phong_normals`, on by default; off,
`--splat-normals`, each splat's one normal, which the paper blends). Blended with Gaussian
weights, one normal per splat shows a coarse surface's splats as bands (the demo model's
body and legs striped). Over the vertices of 14 models, 48 oblique views each at 512x512:
median PSNR per model spot 35.6 -> 36.8 dB, fandisk 31.3 -> 33.9, cheburashka 36.7 -> 37.7,
casting.obj 30.0 -> 31.6 (views below 28 dB: 8 -> 0), cow 28.2 -> 29.1, the bunny 37.6 ->
38.1, six others -0.05 to +0.35; rocker-arm 36.0 -> 34.5 and the teapot 29.8 -> 28.9, whose
fine features a field fitted over a few coarse neighbours turns too far. On raw scans of 9
of them (benchmarks/scan_fidelity.py --oblique) every model gains 0 to 0.6 dB, median 32.7
-> 33.0 dB. The splat's own surface field, which shapes it, lights it no better: the same
on curved surfaces, 1.3 and 0.8 dB below on fandisk and casting.obj, whose rims it leaves
out. The splats were bent by the shading field, rim included, so that a face's splats
bent down at its edge left its outline to the rim's normal; but then the outline withdrew up
to half a pixel behind the mesh's (casting.obj: 0.1-0.19% holes in 13 of 48 oblique views
at 512x512). Shaped as `phong`'s, a face stays whole up to its edge, and the crease blend
(below) rounds its shading there. A level-of-detail cut's splats are flat (rendering.py):
fitting fields to every frame's cut would cost more than the frame.

`phong` -- Botsch, Spernat & Kobbelt 2004, "Phong splatting" (survey 2.1.4): elliptical
splats (c_j, u_j, v_j) aligned with the principal curvature directions, the per-fragment
ray-plane intersection q = q_n (cᵀn)/(q_nᵀn) and local (u, v) = (u_jᵀ(q - c_j),
v_jᵀ(q - c_j)) / |axis|² (eq. 7), discarding u² + v² > 1, exact per-pixel depth, and the
linear normal field N_j(u, v) = n̄_j + u α_j û_j + v β_j v̂_j (eq. 8, α_j and β_j fitted in
preprocessing: surfel.preprocess.fit_normal_field), blended with Gaussian weights,
normalized and lit per pixel as in `deferred`. Beyond the paper, each splat is the curved
surface a normal field describes (the height field h = -(k_u s_u² + k_v s_v²)/2 over the
splat plane, k the field's tilt per unit length; the field fitted without a face's rim,
curve_alpha and curve_beta, so that a face stays flat up to its edge: normal_field.py): the
ray meets that instead of the plane, which puts the depth on the surface and ends the splat
at the surface's true contour. Flat
splats stick out past the outline of a coarsely sampled curved surface, dark (their field
normals turn edge-on there) over the bright surface behind: the largest error of sparse
sampling (bunny thinned to every 4th point: +0.7 to +2.5 dB interior PSNR over five views;
spot, coarsely sampled: +6 dB). The slopes are the fields' tilts at the fitted rim; a splat
drawn radius_scale times as large reaches radius_scale times as far, where they have turned
as much more, so every program multiplies them by radius_scale (the normals of 800 samples
of a sphere at radius_scale 1.6: 0.03 degrees off the sphere's on average, as at 1; 0.52
without). A curved splat also ends where its field has turned by 45 degrees,
|α u| <= MAX_RIM_TILT = 1 (splatting.glsl): drawn, its axes are divided by max(1, |α|) and
max(1, |β|), its slopes with them (its curvature α / |u_j| is kept), and its clip lines are
moved into those coordinates. Past that tilt the paraboloid parts from the
surface it stands for (a fillet, a rim, a spout) and spills past the outline with grazing
normals, while the neighbours' splats there describe the surface; the stored axes, the
cells' covering ellipses, stay as they are for the flat splats of the other methods. (Mesh
vertices of 13 models, two views each: `phong` median 34.1 -> 34.5 dB, `deferred` 33.1 ->
33.5 dB, the CAD part's oblique view +1.1 and +1.3 dB; raw scans of them within 0.05 dB.
A limit of 0.5 gained 1 dB but opened holes of 0.1-0.7% on coarse figures.)

Crease blend (beyond the papers; all three methods): the clip lines end each face's splats
at a crease, and the crease's own points are dropped (preprocess.sharp_features), so the
faces meet with a hard step in shading where a mesh's interpolated normals round the edge
over a triangle's width. In the attribute pass a fragment reaches CREASE_BLEND = 1/2 splat
radius past its splat's clip lines, its weight fading to 0 there, so the faces' normals (or
shaded colours) blend across the crease. It blends only where it lies within
CREASE_BLEND_DEPTH = 2 z_t in front of the visibility depth, on the surface across the
crease: past a border clip line, over an opening, it would float in front of what the
opening shows (the bunny's base, seen from below: -2 dB without that test). The visibility
pass keeps the exact clip lines, so outlines and coverage do not change. (14 models'
vertices, 48 oblique views each at 512x512, median PSNR per model: `phong` fandisk +0.4 dB,
casting.obj +0.2 dB, the rest within 0.1 dB; `gaussian` +0.2 and +0.16 dB, the rest within
0.13 dB; `deferred`, with its splats shaped as `phong`'s, fandisk +0.6 dB, cheburashka +0.35
dB, rocker-arm -0.15 dB, the rest -0.04 to +0.22 dB, and no view over 0.1% holes, where 15
were.)

Passes without the rasterizer (beyond the papers; splatting.glsl's COMPUTE_SHADER variants):
with point sprites, the visibility and attribute passes run as compute programs, one
invocation a splat visiting the pixels of its sprite with the fragment shader's arithmetic
(Schütz, Kerbl & Wimmer 2021, "Rendering point clouds with compute shaders"). The
visibility pass takes its two minima by atomic MIN on the bits of non-negative floats; the
attribute pass sums in 32-bit fixed point by atomic ADD (gl/passes.glsl ACCUMULATOR_SUMS),
which, unlike blended floats, gives the same sums in any order, and which the normalization
reads where they lie. They draw on targets without a guard band, which only rasterized
sprites need: every per-pixel pass then covers the image alone (on llvmpipe, resolving the
sums into textures and a guard band cost a sixth of bench's frame, 1M splats at 1024x1024).
A point sprite costs llvmpipe
about 250 ns to set up whatever its shader (bench's 1M splats: 250 ms a pass); GPUs too
spend more on small primitives than on their pixels. The passes agree with the rasterized
ones (tests/test_splatting.py); the rasterized passes stay for quads (splats that may cross
the near plane or outgrow the guard band), categorical colour modes' category pass, clouds
streamed in chunks and targets whose sums outgrow a storage buffer.

Samples (beyond the papers): `phong`, the default method, renders a still image at 2x2
samples a pixel, box filtered (`--supersample` sets another count; the viewer and the page
draw a moving camera's frames at one; an image too large for its targets at 2x2 takes one,
`options.fitting_supersample`). A pixel's edge coverage (splatting_cpu.py, pass 1)
anti-aliases an outline against the background, but not where a nearer surface ends over a
farther one, nor the shading of creases and fine folds; the ground truth, 4x4 samples a
pixel, resolves both (13 mesh-vertex models, two views each: median 33.1 -> 33.6 dB, +2 to +3
dB on the finely sampled ones; raw scans 31.1 -> 31.4 dB) for four times the fragments.
`gaussian` and `deferred` take one sample, as in the papers (bench's frame rates are theirs).

Parameters: those every blended splat method has (`params.SplatParams`: radius_scale, z_t as
depth_offset, backface_culling, lowpass_radius r_lp) and ewa_filter, whose default is each
paper's: on for `deferred` (`DeferredParams`), off for `gaussian` and `phong`. The program's
variants: CURVED_SPLATS for `deferred` and `phong`, NORMAL_FIELD for `phong`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..gl import splats
from ..gl.context import get_context
from ..gl.passes import SUM_CHANNELS, UNIFORM_UNITS, SplatPasses
from ..gl.targets import max_target_side
from ..gl.uniforms import apply_common
from ..options import fitting_supersample
from .params import SplatParams

SHADER = Path(__file__).with_suffix(".glsl")
KERNEL_SIZE = 256
# samples per pixel side where the options name none, box filtered (RenderResult.from_samples):
# one for gaussian and deferred, as in the papers; 2x2 for phong, the default method (module
# docstring, "Samples")
DEFAULT_SUPERSAMPLES = {"gaussian": 1, "deferred": 1, "phong": 2}
GAUSSIAN_SHARPNESS = 3.0     # w = exp(-3 d²): the disk rim at 2.4 standard deviations
GUARD = 128                  # guard band in pixels: half of llvmpipe's (and most GPUs') 255 px point limit
MAX_SPRITE = 255


def use_point_sprites(cloud, camera, radius_scale: float, supersample: int, lowpass: float, drawn=None) -> bool:
    """Point sprites (one vertex a splat) unless a splat could cross the near plane or need
    a sprite larger than the guard band allows; then instanced quads (four vertices a splat).
    `drawn`: mask of the splats a level-of-detail cut draws (None: all)."""
    if drawn is None:
        max_radius = cloud.max_splat_radius * radius_scale
    elif drawn.any():
        max_radius = float(np.linalg.norm(cloud.axes[drawn], axis=2).max()) * radius_scale
    else:
        return True
    if camera.ortho_height is not None:
        pixels = max_radius * camera.height * supersample / camera.ortho_height
    else:
        distance = float(-(camera.view_matrix() @ np.append(cloud.center, 1.0))[2])
        nearest = distance - cloud.bounding_radius - max_radius
        if nearest <= camera.near:
            return False
        pixels = max_radius * camera.fy * supersample / nearest * 1.5  # 1.5: off-axis stretch
    return 2 * (pixels + lowpass) + 2 <= min(2 * GUARD, MAX_SPRITE)


def use_compute_passes(sprites: bool, buffers, target_pixels: int) -> bool:
    """Whether the visibility and attribute passes run as compute programs (splatting.glsl's
    compute variants): for point sprites, whose pixels one invocation visits cheaply, of a
    cloud whose buffers stay on the GPU, on render targets whose fixed-point sums fit one
    storage buffer (gl/passes.py)."""
    return sprites and buffers.kept is not None and target_pixels * SUM_CHANNELS * 4 <= splats.max_storage_bytes()


def gaussian_kernel_texture(ctx):
    """The 1D Gaussian lookup table of Botsch & Kobbelt 2003, indexed by squared distance."""
    d2 = (np.arange(KERNEL_SIZE, dtype=np.float32) + 0.5) / KERNEL_SIZE
    tex = ctx.texture((KERNEL_SIZE, 1), 1, np.exp(-GAUSSIAN_SHARPNESS * d2).astype(np.float32).tobytes(), dtype="f4")
    tex.repeat_x = tex.repeat_y = False
    return tex


@dataclass(frozen=True)
class GaussianParams(SplatParams):
    ewa_filter: bool = False  # Botsch et al. 2005's screen-space filter approximation


@dataclass(frozen=True)
class DeferredParams(SplatParams):
    ewa_filter: bool = True  # the paper's: minified textures do not alias (Fig. 10)
    phong_normals: bool = True  # each fragment's normal from its splat's normal field; False: one per splat


@dataclass(frozen=True)
class PhongParams(SplatParams):
    ewa_filter: bool = False


def render_gaussian(cloud, camera, options, params: GaussianParams, renderer):
    return _render(cloud, camera, options, params, renderer, per_splat_shading=True,
                   supersample=DEFAULT_SUPERSAMPLES["gaussian"])


def render_deferred(cloud, camera, options, params: DeferredParams, renderer):
    return _render(cloud, camera, options, params, renderer, per_splat_shading=False, curved=True,
                   normal_field=params.phong_normals, supersample=DEFAULT_SUPERSAMPLES["deferred"])


def render_phong(cloud, camera, options, params: PhongParams, renderer):
    return _render(cloud, camera, options, params, renderer, per_splat_shading=False, curved=True, normal_field=True,
                   supersample=DEFAULT_SUPERSAMPLES["phong"])


def _render(cloud, camera, options, params, renderer, *, per_splat_shading: bool, curved: bool = False,
            normal_field: bool = False, supersample: int):
    ctx = get_context()
    # the default yields to the targets' side limit with the guard band a sprite pass may add
    ss = options.supersample or fitting_supersample(supersample, camera.width, camera.height,
                                                    max_target_side() - 2 * GUARD)
    width, height = camera.width * ss, camera.height * ss
    ewa_filter = params.ewa_filter
    lowpass = params.lowpass_radius * ss if ewa_filter else 0.0
    lod_k, prefix, drawn = splats.lod_frame(cloud, camera, options.lod_error)
    sprites = use_point_sprites(cloud, camera, params.radius_scale, ss, lowpass, drawn)
    categorical = options.coloring is not None and options.coloring.categorical
    buffers = renderer.splat_buffers(cloud)
    # the compute passes clamp a sprite to the target themselves: only rasterized sprites need the
    # guard band (OpenGL drops a point whose centre is clipped), and the category pass rasterizes
    guard = GUARD if sprites and (categorical or not use_compute_passes(sprites, buffers, width * height)) else 0
    compute = use_compute_passes(sprites, buffers, (width + 2 * guard) * (height + 2 * guard))
    variant = {"PER_SPLAT_SHADING": per_splat_shading, "EWA_FILTER": ewa_filter, "CURVED_SPLATS": curved,
               "NORMAL_FIELD": normal_field,
               "POINT_SPRITES": sprites, "CLIP_LINES": "clip_lines" in cloud.attributes}
    # one albedo code for every splat: the compute pass's sums skip it (gl/passes.glsl UNIFORM_COLOR)
    uniform_color = splats.NO_COLOR if cloud.colors is None and not per_splat_shading else None
    raster = {"PASS_NORMALIZE"}
    if not compute:
        raster |= {"PASS_VISIBILITY", "PASS_OCCLUSION", "PASS_ATTRIBUTE"}
    if categorical:
        raster |= {"PASS_OCCLUSION", "PASS_CATEGORY"}
    # after the compute attribute pass, the normalization reads its sums where they lie
    sums = {"ACCUMULATOR_SUMS": True, "UNIFORM_COLOR": False if uniform_color is None else uniform_color} \
        if compute else {}
    programs = {p: renderer.program(SHADER, {p: True, **variant, **(sums if p == "PASS_NORMALIZE" else {})})
                for p in sorted(raster)}
    if compute:
        for name, defines in (("visibility", {"PASS_VISIBILITY": True}),
                              ("attribute", {"PASS_ATTRIBUTE": True, **sums}),
                              ("resolve visibility", {"PASS_RESOLVE": True})):
            layout = {"SPLAT_TEXELS": splats.TEXELS, "SPLAT_ROW": splats.TEXTURE_ROW}
            programs[name] = renderer.program(SHADER, {**defines, **layout, **variant}, compute=True)
    for program in programs.values():
        apply_common(program, camera, cloud.local_origin, ss, options,
                     u_radius_scale=params.radius_scale, u_depth_offset=params.depth_offset,
                     u_lowpass_radius=params.lowpass_radius * ss, u_guard=float(guard),
                     u_backface_culling=int(params.backface_culling),
                     u_kernel=0, u_lod_k=lod_k, **UNIFORM_UNITS)

    renderer.use_color_table(options)
    kernel = gaussian_kernel_texture(ctx)
    mode = ctx.POINTS if sprites else ctx.TRIANGLE_STRIP

    def draw(program):
        return lambda: splats.draw(ctx, buffers, program, mode, instanced=not sprites, count=prefix)

    def run(name):
        def dispatch():
            program = programs[name]
            for count in splats.compute_chunks(buffers, program, prefix):
                program.run(splats.compute_groups(count))
        return dispatch

    try:
        with SplatPasses(renderer.splat_targets(width, height, guard)) as passes:
            kernel.use(0)
            if compute:
                passes.visibility_compute(run("visibility"), programs["resolve visibility"])
                passes.attribute_compute(run("attribute"), uniform_color)
            else:
                passes.visibility_pass(draw(programs["PASS_VISIBILITY"]))
            if "PASS_OCCLUSION" in programs:
                passes.occlusion_pass(programs["PASS_OCCLUSION"])
            if not compute:
                passes.attribute_pass(draw(programs["PASS_ATTRIBUTE"]))
            if categorical:
                passes.category_pass(draw(programs["PASS_CATEGORY"]))
            passes.normalize_pass(programs["PASS_NORMALIZE"])
            stats = {"splats": len(cloud) if drawn is None else int(drawn.sum()), "supersample": ss,
                     "ewa_filter": ewa_filter, "primitive": "point sprites" if sprites else "quads",
                     "visibility": "compute" if compute else "raster"}
            return passes.result(camera, options, ss, stats)
    finally:
        kernel.release()
