"""`ewa`: software EWA surface splatting (Zwicker, Pfister, van Baar & Gross, SIGGRAPH 2001).

The full screen-space resampling filter of the paper (survey Sec. 3.2), not the 2005
approximation of Botsch et al. Every splat k has a centre c_k, tangent axes u_k, v_k (scaled
to the ellipse semi-axes, times `radius_scale`) and an elliptical Gaussian reconstruction
kernel r_k(s, t) = G_V(s, t) in its local coordinates (s, t), V = sigma^2 I (s = t = 1 at the
ellipse's rim). Per splat, at its centre:

    J   = dP/dx(c_k) [u_k v_k]           the local affine approximation of the projective
                                          mapping P (eye space -> pixels): 2x2, from the
                                          camera's derivative times the tangent frame;
                                          constant for an orthographic camera
    M   = J V J^T + L,  L = l^2 I         the resampling kernel's covariance: the warped
                                          reconstruction kernel convolved with the screen
                                          low-pass of std dev l = lowpass_radius / 2.5
                                          (the paper's l = 1 px over-blurs: a one-pixel box
                                          has std 0.29 px; 0.4 px still anti-aliases)
    rho_k(x) = 1/|J^-1| G_M(x - m_k)      the EWA resampling filter (eq. 19 of the paper),
             = |det J| / (2 pi sqrt(det M)) exp(-1/2 (x - m_k)^T M^-1 (x - m_k))

(the constant 2 pi cancels in the normalisation and is dropped). The kernel is cut where
(x - m)^T M^-1 (x - m) > R^2 with R^2 = -2 ln(1 - mass), so `cutoff_mass` (default 0.9) of
its mass is kept; the pixel box of the cut ellipse has half-sizes R sqrt(M_00), R sqrt(M_11).

Visibility follows the paper's A-buffer-like rule with a depth threshold
z_t = depth_offset * splat radius + dz, dz the splat plane's own depth range over its
visibility footprint (below), so the fragments of one surface seen at a grazing angle, whose
depths at a pixel spread over more than a radius, are still blended: pass 1 takes per pixel
Z = min over fragments of (depth + z_t); pass 2 blends the fragments with depth <= Z into the
front layer and the others into a back layer, a running z-buffer with the same rule (a
fragment nearer than its depth minus z_t replaces the layer, one within z_t blends). The two
layers are composited front to back ("over") with their coverages, so at an occlusion contour,
where the front surface covers a pixel only partly, the surface behind fills the rest. A
fragment's depth is the splat plane's eye depth, linear in the pixel offset through J^-1
(clamped to the kernel's extent where J is near singular).
Pass 2 accumulates w, w*albedo, w*normal, w*depth; the pixel's albedo, normal and depth are
the normalised sums (per-pixel normalisation) and are shaded afterwards (deferred shading).
Normals are flipped to face the viewer per splat. Colours are thus filtered exactly as the
paper prescribes, which is what anti-aliases texture under minification.

Coverage (alpha): the accumulated weight sum W = sum_k rho_k(x) does not depend on the view
inside a surface (it is the number of splats per unit of local (s, t) area, a property of the
sampling), so alpha = clamp(W / (coverage * W_full)) with W_full the typical W of fully covered
pixels (the 75th percentile of the front layer's W over the image) gives a soft, anti-aliased
silhouette; per layer, alpha = a_front + (1 - a_front) a_back. Beyond the paper, alpha is at
least the pixel's coverage by the kernels' one-sigma ellipses (ewa_kernels.COVERAGE_SIGMAS:
s^2 + t^2 <= sigma^2, half the splat at the default sigma), each anti-aliased over a pixel
(0.5 plus the pixel's distance to its rim, clamped), the most any one covers taken, in pass 1
under the visibility footprint. W alone reads an uneven sampling as partly covered: where
splats barely overlap, and at an occlusion contour, where the front surface and the one
behind it each cover a pixel in part, W falls short of the full weight of the image's denser
parts, and the surface showed dark specks and holes over the background. Raw scans of 13
models (`benchmarks/scan_fidelity.py --methods ewa --oblique`, 18 views at 512 x 512): 104
of 234 renders with more than 0.1% holes, 23 now; median PSNR 31.3 -> 31.0 dB: the flat
cut-outs woody and alligator lose 2 dB at their outlines, which the ellipses' rims move out
a little; the others move by -0.1 to +0.2 dB. The whole ellipse (s^2 + t^2 <= 1) moved the outline
out by up to a splat radius (four of those scans: 1 dB lost); 0.6 sigma left 9 of their 72
renders with holes, 0.8 sigma one, one sigma none.

Pass 1 uses a narrower visibility footprint, J V J^T + v^2 I with v = `visibility` pixels
(default 0.2), instead of M: the low-pass fringe of a splat seen edge-on (tiny weight, but a
plane depth extrapolated far off) must not hide the surface behind it.

The CPU backend `render_ewa_cpu` (numba, parallel over screen tiles, see ewa_kernels.py) ends
in `resolve_accumulators`, which a GL backend reading back its accumulators is meant to share.

Method parameters (`EwaParams`): those of every splat method (radius_scale, depth_offset,
backface_culling, lowpass_radius), sigma (reconstruction std dev in semi-axis units, default
0.5), cutoff_mass (0.9), coverage (fraction of W_full at which alpha reaches 1, default 0.6),
visibility (0.2 px), depth_clamp (cap of a fragment's plane-depth offset, in radii, default 4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ..camera import Camera
from ..cloud import PointCloud, read_only
from ..options import RenderOptions, check_cpu_samples, non_negative, open_unit_interval, positive, setting
from ..preprocess import INACTIVE_CLIP, drawn_normals, has_normal_field, splat_slopes, splat_thickness
from ..result import RenderResult
from ..shading import shade
from .params import SplatParams

DEFAULT_SUPERSAMPLE = 1
TILE_PIXEL_COST = 100  # a tile's pixels cost about what 100 splats do (deferred@cpu: normalization and shading)
# lowpass_radius is the low-pass's radius in pixels, taken as LOWPASS_SIGMAS std devs:
# std 0.4 px at the default 1 px, close to a one-pixel box (std 0.29 px) and thus little blur,
# while still band-limiting minified splats (the paper's unit std over-blurs, see ewa.py).
LOWPASS_SIGMAS = 2.5
# The percentile of the nonzero weight sums taken as the weight of a fully covered pixel.
FULL_WEIGHT_PERCENTILE = 75.0


@dataclass(frozen=True)
class EwaParams(SplatParams):
    sigma: float = setting(0.5, positive)  # reconstruction kernel std dev, in semi-axis units
    cutoff_mass: float = setting(0.9, open_unit_interval)  # mass of the kernel kept inside its cutoff
    coverage: float = setting(0.6, positive)  # fraction of W_full at which alpha reaches 1
    visibility: float = setting(0.2, non_negative)  # std dev in pixels added for the visibility footprint
    depth_clamp: float = setting(4.0, positive)  # cap of a fragment's depth offset from its centre, in radii

    @property
    def cutoff2(self) -> float:
        """R^2, the squared Mahalanobis cutoff radius of the resampling kernel."""
        return -2.0 * math.log(1.0 - self.cutoff_mass)

    @property
    def lowpass(self) -> float:
        """Std dev of the screen low-pass, in render-target pixels."""
        return self.lowpass_radius / LOWPASS_SIGMAS


def target_camera(camera: Camera, supersample: int) -> Camera:
    """The camera of the (supersampled) render target."""
    s = supersample
    if s == 1:
        return camera
    return camera.with_(width=camera.width * s, height=camera.height * s, fx=camera.fx * s, fy=camera.fy * s,
                        cx=camera.cx * s, cy=camera.cy * s)


def ortho_scale(camera: Camera) -> float:
    """Pixels per world unit of an orthographic camera, 0 for a perspective one."""
    return 0.0 if camera.ortho_height is None else camera.height / camera.ortho_height


def splat_categories(cloud: PointCloud, options: RenderOptions) -> tuple[np.ndarray, int]:
    """(N,) int32 palette indices of a categorical colour mode and its code levels, or a
    (1,) placeholder and 0 (no category pass)."""
    coloring = options.coloring
    if coloring is None or not coloring.categorical:
        return np.zeros(1, np.int32), 0
    return coloring.indices(cloud.colors).astype(np.int32), coloring.code_levels


def splat_colors(cloud: PointCloud) -> np.ndarray:
    """(N, 3) albedo, or (1, 3) white for a cloud without colours; read-only either way, as a
    cloud's arrays are, so that the kernels are compiled for one kind of array (numba compiles
    writable and read-only arguments separately)."""
    return cloud.colors if cloud.colors is not None else read_only(np.ones((1, 3), np.float32))


def splat_clip_lines(cloud: PointCloud) -> np.ndarray:
    """(N, 2, 3) clip lines at sharp features (surfel.preprocess), or (1, 2, 3) inactive ones."""
    if "clip_lines" in cloud.attributes:
        return np.ascontiguousarray(cloud.attributes["clip_lines"], np.float32)
    return np.array([[INACTIVE_CLIP, INACTIVE_CLIP]], np.float32)


def splat_fields(cloud: PointCloud) -> np.ndarray:
    """(N, 2) Phong normal-field slopes (alpha, beta), or (1, 2) zeros: flat splats."""
    slopes = splat_slopes(cloud)
    return np.zeros((1, 2), np.float32) if slopes is None else np.ascontiguousarray(slopes[:, :2])


def splat_axes(cloud: PointCloud) -> np.ndarray:
    """(N, 2, 3) tangent axes; from normals and radii when the cloud has none."""
    if cloud.axes is not None:
        return cloud.axes
    n = cloud.normals.astype(np.float64)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    r = cloud.radii.astype(np.float64)[:, None]
    return np.stack([u * r, v * r], axis=1).astype(np.float32)


def splat_inputs(cloud: PointCloud) -> tuple[np.ndarray, ...]:
    """What `ewa_kernels.setup_splats` takes per splat: normals (`drawn_normals`), colours, axes,
    clip lines, normal fields and layer thickness, all read-only as a cloud's own arrays are:
    numba compiles writable and read-only arrays apart, and this kernel takes some 10 s."""
    return tuple(read_only(array) for array in (drawn_normals(cloud), splat_colors(cloud), splat_axes(cloud),
                                                splat_clip_lines(cloud), splat_fields(cloud),
                                                splat_thickness(cloud)))


def resolve_accumulators(acc: np.ndarray, coverage: np.ndarray, camera: Camera, options: RenderOptions,
                         params: EwaParams, supersample: int, stats: dict,
                         categories: np.ndarray | None = None) -> RenderResult:
    """Normalise the accumulated (H, W, 8 or 16) = w*rgb, w, w*normal, w*depth and shade (deferred);
    the pixel's alpha is at least `coverage` (H, W), how much of it the splats' kernel
    ellipses cover (module docstring: coverage).

    With 16 channels the second 8 are the back layer (the nearest surface behind the front
    one), composited under the front layer with the front layer's coverage, so a pixel at an
    occlusion contour that the front surface only partly covers shows the surface behind it.
    Colour modes (surfel.colors): the normalized colour is decoded per layer; in a
    categorical mode `categories` (H, W, 2) holds each layer's packed heaviest category, the
    layer's albedo is its palette entry, and a pixel shows the layer that contributes most
    instead of compositing the two (categories are never blended).
    Shared by both backends so that they differ only by the rasterization itself.
    """
    from ..colors import category_unpack
    from .ewa_kernels import composite_layers, normalise_layers

    front = acc[..., 3]
    nonzero = front[front > 0]
    # The weight of a fully covered pixel: a high percentile of the front layer's weights.
    full = float(np.percentile(nonzero, FULL_WEIGHT_PERCENTILE)) if nonzero.size else 1.0
    albedo, normals, depth, layer_alpha = normalise_layers(np.ascontiguousarray(acc, np.float32),
                                                          np.float32(1.0 / max(params.coverage * full, 1e-30)))
    covered = layer_alpha > 0  # shade only where a layer has a surface (a fraction of the screen)
    coloring = options.coloring
    layer_indices = None
    if coloring is not None and coloring.categorical:
        layer_indices = np.moveaxis(category_unpack(categories, coloring.code_levels), -1, 0)[:len(albedo)]
        albedo = coloring.table[np.maximum(layer_indices, 0)]
    elif coloring is not None:
        albedo[covered] = coloring.decode(albedo[covered])
    shaded = np.zeros_like(albedo)
    shaded[covered] = shade(options.surface_shading, albedo[covered], normals[covered], depth[covered],
                            camera.near, camera.far)
    color, alpha, depth_out, normals_out, top = composite_layers(shaded, layer_alpha, depth, normals,
                                                                 layer_indices is not None)
    alpha = np.maximum(alpha, coverage)
    indices = None
    if layer_indices is not None:
        indices = np.where(alpha > 0, np.take_along_axis(layer_indices, top[None], 0)[0], -1).astype(np.int32)
    stats = dict(stats, full_weight=full)
    return RenderResult.from_samples(color, alpha, depth_out, normals_out, supersample=supersample,
                                     options=options, stats=stats, indices=indices, pinholes=True)


def spatially_ordered(cloud: PointCloud) -> PointCloud:
    """The cloud in Morton order (made once per cloud by the Renderer). Both backends draw it
    in this order: a screen tile's splats then lie close together in memory, and the CPU
    rasterizer, which otherwise waits on a cache miss per splat, runs about twice as fast."""
    from ..lod.build import morton_codes

    return cloud.take(np.argsort(morton_codes(cloud.positions)))


def render_ewa_cpu(cloud: PointCloud, camera: Camera, options: RenderOptions, params: EwaParams,
                   renderer) -> RenderResult:
    """EWA splatting on the CPU: numba kernels, parallel over screen tiles."""
    from . import ewa_kernels as k

    cloud = renderer.cached(cloud, "morton order", lambda: spatially_ordered(cloud))
    supersample = options.supersample or DEFAULT_SUPERSAMPLE
    target = target_camera(camera, supersample)
    w, h = target.width, target.height
    check_cpu_samples(w, h)
    intr = np.array([target.fx, target.fy, target.cx, target.cy], np.float64)
    normals, colors, axes, clip_lines, fields, thickness = splat_inputs(cloud)
    splats, extra, box = k.setup_splats(cloud.positions, np.asarray(cloud.local_origin, np.float64),
                                 np.asarray(target.world_to_eye, np.float64), normals, colors,
                                 axes, clip_lines, fields, thickness, intr,
                                 ortho_scale(target), float(target.near),
                                 np.float32(params.radius_scale), np.float32(params.sigma ** 2),
                                 np.float32(params.lowpass ** 2), np.float32(params.visibility ** 2),
                                 np.float32(params.cutoff2),
                                 np.float32(params.depth_offset), np.float32(params.depth_clamp),
                                 bool(params.backface_culling), w, h)
    tiles_x, tiles_y = -(-w // k.TILE), -(-h // k.TILE)
    offsets, index = k.bin_splats(box, tiles_x, tiles_y)
    codes, levels = splat_categories(cloud, options)
    order = balanced_tile_order(np.diff(offsets), numba.get_num_threads())
    acc, coverage, fragments, categories = k.rasterize_tiles(
        splats, extra, box, offsets, index, order, tiles_x, w, h, np.float32(params.cutoff2),
        len(clip_lines) > 1, has_normal_field(cloud), codes, levels)
    drawn = int(np.count_nonzero(box[:, 0] <= box[:, 1]))
    return resolve_accumulators(acc, coverage, target, options, params, supersample,
                                {"splats": drawn, "fragments": int(fragments)}, categories if levels else None)


def balanced_tile_order(splats_per_tile: np.ndarray, threads: int) -> np.ndarray:
    """The order in which a parallel loop over screen tiles visits them: numba splits a loop's
    iterations into as many equal contiguous ranges as it has threads, so each range gets
    tiles of about equal work, the splats binned to them (the kernels' cost) plus
    TILE_PIXEL_COST for their pixels. The tiles, costliest first, are dealt to the ranges in
    turn, forth then back (0, 1, 1, 0, 0, 1, ...); -1 pads the order to whole ranges. On the
    bunny at 1M splats (`surfel bench`) the busier of 2 threads drew 52.3% of the splats with
    a fixed interleave of the screen, 50.1% dealt."""
    cost = splats_per_tile + TILE_PIXEL_COST
    ranked = np.argsort(-cost, kind="stable")
    rounds = -(-len(ranked) // threads)
    dealt = np.full(rounds * threads, -1, np.int64)
    dealt[:len(ranked)] = ranked
    dealt = dealt.reshape(rounds, threads)
    dealt[1::2] = dealt[1::2, ::-1]
    return np.ascontiguousarray(dealt.T).ravel()
