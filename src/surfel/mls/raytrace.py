"""`mls` (CPU): ray tracing the MLS point set surface, Adamson & Alexa 2003 (survey 2.3.1, Fig. 15).

Every sample p_i carries a bounding sphere of radius domain * s_i (the domain test of
surface.py accepts exactly the points within such a sphere, so the spheres enclose the
surface) and the polynomial fitted at p_i (precomputed once per cloud, cached weakly).
The spheres sit in a bounding volume hierarchy: an implicit complete binary tree over the
points sorted in Morton order, 8 spheres a leaf. Per ray (numba, parallel over rays):

1. collect the spheres the ray passes through and visit them nearest entry first;
2. intersect the ray with the sphere centre's polynomial inside the sphere (poly_ray);
3. project that point r_k: fit the MLS polynomial at r_k; if |P(r_k) - r_k| < eps the
   intersection is found, else r_{k+1} = ray meets the new polynomial near r_k; repeat
   (typically 2 to 3 fits). A failed fit or a diverging ray moves on to the next sphere.

Colour is the fit's weighted mean of the neighbours' colours, the normal the gradient of
the last polynomial (n - g_u e1 - g_v e2). Parameters (`MlsParams`):
    h_scale (1.5)       kernel width h_i = h_scale * local spacing s_i (surface.MlsKernel)
    domain (2.0)        domain test / sphere radius in units of s_i (surface.MlsKernel)
    tolerance (1e-3)    eps, as a fraction of the median kernel width
    max_iterations (8)  fits per candidate sphere before giving up on it
    shadows (False)     a shadow ray to the directional key light of shading.py (eye space
                        (-0.4, 0.6, 0.8)); shadowed pixels keep only the ambient 0.2 albedo
    reflect (False)     one mirror bounce traced against the surface, or else a sky/ground
                        gradient environment, mixed in with `reflectivity` (0.3)
Supersampling defaults to 2x2 rays per pixel (box filtered like every method).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ..options import at_least, between, check_cpu_samples, positive, setting
from ..result import RenderResult
from ..shading import KEY_LIGHT, shade
from .surface import (
    DEFAULT_KERNEL,
    FIT_OK,
    MAX_NEIGHBOURS,
    POLY_SIZE,
    SUPPORT,
    MlsKernel,
    MLSSurface,
    build_surface,
    fit,
    point_polynomials,
    poly_normal,
    poly_project,
    poly_ray,
)

DEFAULT_SUPERSAMPLE = 2  # rays per pixel side, box filtered like every method
LEAF = 8
MAX_CANDIDATES = 4096
STACK = 64
DONE = 1e30  # marks a visited candidate (finite: fastmath assumes no infinities)
SKY = np.array([0.55, 0.7, 0.95])
GROUND = np.array([0.25, 0.22, 0.2])


@dataclass(frozen=True)
class MlsParams(MlsKernel):
    tolerance: float = setting(1e-3, positive)  # eps, as a fraction of the median kernel width
    max_iterations: int = setting(8, at_least(1))  # fits per candidate sphere before giving up on it
    shadows: bool = False  # a shadow ray to the key light
    reflect: bool = False  # one mirror bounce
    reflectivity: float = setting(0.3, between(0, 1))  # weight of the mirror bounce


@dataclass(frozen=True, eq=False)
class MLSScene:
    """A cloud ready to ray trace: surface, per-point polynomials, spheres and their BVH."""

    surface: MLSSurface
    polys: np.ndarray       # (N, POLY_SIZE)
    valid: np.ndarray       # (N,) bool: the point's own fit succeeded
    radius: np.ndarray      # (N,) bounding sphere radius
    leaf_order: np.ndarray  # (L * LEAF,) point indices in Morton order, -1 padding
    boxes: np.ndarray       # (2L - 1, 2, 3) node AABBs of the implicit heap-ordered tree


def _morton(points: np.ndarray) -> np.ndarray:
    lo, hi = points.min(axis=0), points.max(axis=0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-30) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return code


def build_bvh(centers: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Implicit complete binary tree: leaves of LEAF Morton-consecutive spheres, bounds bottom-up."""
    order = np.argsort(_morton(centers), kind="stable")
    leaves = 1 << max(0, math.ceil(math.log2(max(1, math.ceil(len(centers) / LEAF)))))
    leaf_order = np.full(leaves * LEAF, -1, np.int64)
    leaf_order[: len(order)] = order
    lo = np.full((leaves * LEAF, 3), DONE)  # empty padding boxes (finite, see DONE)
    hi = np.full((leaves * LEAF, 3), -DONE)
    lo[: len(order)] = centers[order] - radius[order, None]
    hi[: len(order)] = centers[order] + radius[order, None]
    level_lo = lo.reshape(leaves, LEAF, 3).min(axis=1)
    level_hi = hi.reshape(leaves, LEAF, 3).max(axis=1)
    boxes = np.empty((2 * leaves - 1, 2, 3))
    first = leaves - 1
    while True:
        boxes[first: first + len(level_lo), 0] = level_lo
        boxes[first: first + len(level_lo), 1] = level_hi
        if first == 0:
            break
        level_lo = np.minimum(level_lo[0::2], level_lo[1::2])
        level_hi = np.maximum(level_hi[0::2], level_hi[1::2])
        first = (first - 1) // 2
    return leaf_order, boxes


def prepare_scene(cloud, kernel: MlsKernel = DEFAULT_KERNEL) -> MLSScene:
    """The ray tracing scene of `cloud`."""
    surface = build_surface(cloud, kernel)
    polys, status = point_polynomials(surface)
    radius = kernel.domain * surface.spacing
    leaf_order, boxes = build_bvh(surface.points, radius)
    return MLSScene(surface, polys, status == FIT_OK, radius, leaf_order, boxes)


def cached_scene(cloud, kernel: MlsKernel, renderer) -> MLSScene:
    """The scene, made once per cloud and kernel by the Renderer (both MLS methods share it)."""
    key = ("mls scene", kernel.h_scale, kernel.domain)
    return renderer.cached(cloud, key, lambda: prepare_scene(cloud, MlsKernel(kernel.h_scale, kernel.domain)))


@numba.njit(cache=True, fastmath=True)
def _box_entry(box, o, inv_d, t_max):
    """Entry parameter of the ray into the AABB, or -1 if it misses within [0, t_max]
    (no infinities anywhere: fastmath lets the compiler assume there are none)."""
    t0, t1 = 0.0, t_max
    for a in range(3):
        ta = (box[0, a] - o[a]) * inv_d[a]
        tb = (box[1, a] - o[a]) * inv_d[a]
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    return t0 if t0 <= t1 else -1.0


@numba.njit(cache=True, fastmath=True)
def trace_ray(o, d, t_min, t_max, points, spacing, h, colors, domain, cell, lower, dims, order, starts,
              scale, polys, valid, radius, leaf_order, boxes, tolerance, max_iter,
              cand_t, cand_i, stack, poly, work, nb, x, y, normal, color):
    """Nearest intersection of o + t d (|d| = 1) with the MLS surface in [t_min, t_max].

    Returns (t, fits); t < 0 when the ray misses. On a hit `normal` and `color` are set.
    """
    inv_d = np.empty(3)
    for a in range(3):
        inv_d[a] = 1.0 / d[a] if d[a] != 0.0 else 1e30
    # 1. spheres pierced by the ray, through the BVH
    n_cand = 0
    top = 0
    stack[0] = 0
    top = 1
    first_leaf = (boxes.shape[0] + 1) // 2 - 1
    while top > 0:
        top -= 1
        node = stack[top]
        if _box_entry(boxes[node], o, inv_d, t_max) < 0.0:
            continue
        if node >= first_leaf:
            base = (node - first_leaf) * LEAF
            for s in range(base, base + LEAF):
                i = leaf_order[s]
                if i < 0 or not valid[i]:
                    continue
                ox, oy, oz = o[0] - points[i, 0], o[1] - points[i, 1], o[2] - points[i, 2]
                b = ox * d[0] + oy * d[1] + oz * d[2]
                c = ox * ox + oy * oy + oz * oz - radius[i] * radius[i]
                disc = b * b - c
                if disc < 0.0:
                    continue
                t_exit = -b + math.sqrt(disc)
                t_in = -b - math.sqrt(disc)
                if t_exit < t_min or t_in > t_max or n_cand >= MAX_CANDIDATES:
                    continue
                cand_t[n_cand] = max(t_in, t_min)
                cand_i[n_cand] = i
                n_cand += 1
        elif top + 2 <= stack.shape[0]:
            stack[top] = 2 * node + 2
            stack[top + 1] = 2 * node + 1
            top += 2
    # 2./3. nearest sphere first: its polynomial, then iterated projection
    fits = 0
    window = SUPPORT * scale
    for _ in range(n_cand):
        best = 0
        for k in range(1, n_cand):
            if cand_t[k] < cand_t[best]:
                best = k
        if cand_t[best] >= DONE:
            break
        t_in = cand_t[best]
        i = cand_i[best]
        cand_t[best] = DONE
        ox, oy, oz = o[0] - points[i, 0], o[1] - points[i, 1], o[2] - points[i, 2]
        b = ox * d[0] + oy * d[1] + oz * d[2]
        c = ox * ox + oy * oy + oz * oz - radius[i] * radius[i]
        t_out = min(-b + math.sqrt(max(b * b - c, 0.0)), t_max)
        t = poly_ray(polys[i], o, d, t_in, t_out)
        if t < 0.0:
            continue
        for _ in range(max_iter):
            for a in range(3):
                x[a] = o[a] + t * d[a]
            fits += 1
            if fit(x, points, spacing, h, colors, domain, cell, lower, dims, order, starts, scale,
                   poly, work, nb) != FIT_OK:
                break
            if poly_project(poly, x, y) < (tolerance * scale) ** 2:
                poly_normal(poly, x, normal)
                for a in range(3):
                    color[a] = poly[18 + a]
                return t, fits
            t = poly_ray(poly, o, d, max(t - window, t_min), min(t + window, t_max))
            if t < 0.0:
                break
    return -1.0, fits


@numba.njit(cache=True, parallel=True, fastmath=True)
def trace_rays(origins, directions, t_min, t_max, points, spacing, h, colors, domain, cell, lower, dims,
               order, starts, scale, polys, valid, radius, leaf_order, boxes, tolerance, max_iter,
               out_t, out_normal, out_color, out_fits):
    """trace_ray for every ray, in parallel blocks that each own their scratch buffers."""
    n = len(origins)
    block = 256
    for bi in numba.prange((n + block - 1) // block):
        cand_t = np.empty(MAX_CANDIDATES)
        cand_i = np.empty(MAX_CANDIDATES, np.int64)
        stack = np.empty(STACK, np.int64)
        poly = np.empty(POLY_SIZE)
        work = np.empty((7, 7))
        nb = np.empty((MAX_NEIGHBOURS, 4))
        x = np.empty(3)
        y = np.empty(3)
        for r in range(bi * block, min(n, (bi + 1) * block)):
            t, fits = trace_ray(origins[r], directions[r], t_min, t_max, points, spacing, h, colors, domain,
                                cell, lower, dims, order, starts, scale, polys, valid, radius, leaf_order,
                                boxes, tolerance, max_iter, cand_t, cand_i, stack, poly, work, nb, x, y,
                                out_normal[r], out_color[r])
            out_t[r] = t
            out_fits[r] = fits


@dataclass
class Hits:
    """Per-ray results of `trace`: t (< 0 missed), world normals, colours, fits used."""

    t: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    fits: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.t >= 0


def trace(scene: MLSScene, origins: np.ndarray, directions: np.ndarray, t_min: float, t_max: float,
          tolerance: float = 1e-3, max_iter: int = 8) -> Hits:
    """Trace rays given in the surface's local coordinates (directions unit length)."""
    n = len(origins)
    hits = Hits(np.empty(n), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n, np.int64))
    s = scene.surface
    trace_rays(np.ascontiguousarray(origins, np.float64), np.ascontiguousarray(directions, np.float64),
               float(t_min), float(t_max), s.points, s.spacing, s.h, s.colors, s.domain, s.cell, s.lower,
               s.dims, s.order, s.starts, s.scale, scene.polys, scene.valid, scene.radius,
               scene.leaf_order, scene.boxes, float(tolerance), int(max_iter),
               hits.t, hits.normals, hits.colors, hits.fits)
    return hits


def supersampled(camera, ss: int):
    """The same view with ss x ss rays per pixel (intrinsics scaled, pixel centres kept)."""
    return camera.with_(width=camera.width * ss, height=camera.height * ss, fx=camera.fx * ss,
                        fy=camera.fy * ss, cx=camera.cx * ss, cy=camera.cy * ss)


def environment(directions_eye: np.ndarray) -> np.ndarray:
    """A sky/ground gradient seen along eye-space directions (image up is sky)."""
    k = (0.5 + 0.5 * directions_eye[:, 1:2]) ** 0.7
    return GROUND * (1 - k) + SKY * k


def render_mls_cpu(cloud, camera, options, params: MlsParams, renderer) -> RenderResult:
    ss = options.supersample or DEFAULT_SUPERSAMPLE
    check_cpu_samples(camera.width * ss, camera.height * ss)
    tolerance, max_iter = params.tolerance, params.max_iterations
    scene = cached_scene(cloud, params, renderer)
    surface = scene.surface
    cam = supersampled(camera, ss)
    o_eye, d_eye = cam.rays()
    h, w = cam.height, cam.width
    rot = camera.world_to_eye[:3, :3]
    view = camera.view_matrix(surface.origin)  # eye = view (local)
    to_local = np.linalg.inv(view)
    origins = o_eye.reshape(-1, 3) @ to_local[:3, :3].T + to_local[:3, 3]
    dirs = d_eye.reshape(-1, 3) @ rot  # rows times R = R^T d
    t_max = 2.0 * (camera.far + np.linalg.norm(view[:3, 3]))
    hits = trace(scene, origins, dirs, 0.0, t_max, tolerance, max_iter)
    hit = hits.hit
    x_local = origins + hits.t[:, None] * dirs
    x_eye = x_local @ view[:3, :3].T + view[:3, 3]
    depth = np.where(hit, -x_eye[:, 2], np.inf)
    n_eye = hits.normals @ rot.T
    to_eye = -d_eye.reshape(-1, 3)
    flip = np.sum(n_eye * to_eye, axis=1) < 0
    n_eye[flip] *= -1
    n_eye[~hit] = 0
    albedo = np.where(hit[:, None], hits.colors, 1.0)
    indices = None
    coloring = options.coloring
    colors_of = renderer.surface_colors(cloud, cam, options)
    if colors_of is not None:  # the surface's own elevation, the nearest sample's category (never a blend)
        surface_albedo, indices = colors_of(depth.reshape(h, w))
        albedo = np.where(hit[:, None], surface_albedo.reshape(-1, 3), 1.0)
    elif coloring is not None:
        albedo = np.where(hit[:, None], coloring.decode(hits.colors), 1.0)
    shaded = shade(options.surface_shading, albedo, n_eye, depth, camera.near, camera.far).astype(np.float64)
    stats = {"splats": len(cloud), "rays": int(h * w), "hits": int(hit.sum()),
             "iterations_mean": round(float(hits.fits[hit].mean()), 3) if hit.any() else 0.0,
             "iterations_max": int(hits.fits[hit].max()) if hit.any() else 0,
             "point_fit_failures": int((~scene.valid).sum()), "supersample": ss,
             "kernel_width": surface.scale}
    offset = 2.0 * tolerance * surface.scale + 0.25 * surface.scale
    idx = np.flatnonzero(hit)
    n_world = n_eye[idx] @ rot  # flipped towards the viewer
    if params.shadows and idx.size:
        light = KEY_LIGHT @ rot  # eye-space key light to world
        facing = n_world @ light > 0
        start = x_local[idx] + offset * np.where(facing[:, None], n_world, -n_world)
        blocked = trace(scene, start, np.broadcast_to(light, start.shape), 0.0, t_max, tolerance, max_iter).hit
        shadowed = idx[blocked | ~facing]
        shaded[shadowed] = 0.2 * albedo[shadowed]
        stats["shadowed"] = int(len(shadowed))
    if params.reflect and idx.size:
        reflectivity = params.reflectivity
        dv = dirs[idx]
        refl = dv - 2 * np.sum(dv * n_world, axis=1)[:, None] * n_world
        bounce = trace(scene, x_local[idx] + offset * n_world, refl, 0.0, t_max, tolerance, max_iter)
        seen = environment(refl @ rot.T)
        if bounce.hit.any():
            b = bounce.hit
            bn = bounce.normals[b] @ rot.T
            bd = refl[b] @ rot.T
            bn *= np.where(np.sum(bn * bd, axis=1) > 0, -1.0, 1.0)[:, None]
            bounce_albedo = bounce.colors[b] if coloring is None else coloring.decode(bounce.colors[b])
            seen[b] = shade(options.surface_shading, bounce_albedo, bn, depth[idx][b], camera.near, camera.far)
        shaded[idx] = (1 - reflectivity) * shaded[idx] + reflectivity * seen
        stats["reflected_hits"] = int(bounce.hit.sum())
    coverage = hit.astype(np.float32)
    return RenderResult.from_samples(shaded.reshape(h, w, 3).astype(np.float32), coverage.reshape(h, w),
                                     depth.reshape(h, w), n_eye.reshape(h, w, 3), supersample=ss,
                                     options=options, stats=stats, indices=indices)
