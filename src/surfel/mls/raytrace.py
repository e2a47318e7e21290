"""`mls` (CPU): ray tracing the MLS point set surface, Adamson & Alexa 2003 (survey 2.3.1, Fig. 15).

Every sample p_i carries a bounding sphere of radius domain * s_i (the domain test of
surface.py accepts exactly the points within such a sphere, so the spheres enclose the
surface) and the polynomial fitted at p_i (precomputed once per cloud, cached weakly).
The spheres sit in a bounding volume hierarchy: an implicit complete binary tree over the
points sorted in Morton order, 8 spheres a leaf. A camera ray whose pixel centre lies in
no sphere's screen footprint (the projected bounding box of the sphere's bounding cube,
`primary_candidates`) meets no sphere and is not traced: most rays of a frame miss, and
those that pass near the surface would descend the hierarchy for nothing. Per ray traced
(numba, parallel over rays):

1. collect the spheres the ray passes through and visit them nearest entry first;
2. intersect the ray with the sphere centre's polynomial inside the sphere (poly_ray);
3. project that point r_k: fit the MLS polynomial at r_k; if |P(r_k) - r_k| < eps the
   intersection is found (unless the half-disc or extent test of edges.py puts r_k past
   the edge of its sheet), else r_{k+1} = ray meets the new polynomial near r_k; repeat
   (typically 2 to 3 fits). A failed fit or a diverging ray moves on to the next sphere.
   Once one iterate lies above its fit and another below (the sign of n . (r_k - P(r_k))),
   the crossing is bracketed; a step that misses the polynomial, or that leaves the bracket
   from an iterate no nearer the surface than the one before, is replaced by false position
   between the last iterates above and below. Without it a ray that grazes the surface (just
   inside an outline) overshoots: each fit's polynomial, tilted a little from the last, sends
   the next iterate further across the crossing, and the ray misses. On the vertices of
   five coarse figures (quadric-decimated to 1500-3200 vertices), front and azimuth-60
   views at 512 x 512: holes 0.143% -> 0.078% at worst, median PSNR 30.84 -> 30.83 dB
   (benchmarks/scan_fidelity.py --vertices --methods mls). Bracketing every step instead
   gains 0.07 dB more there but takes up to 17 fits where 4 did (kernels spanning gaps on
   a thin part, which converge slowly but surely).

Colour is the last fit's weighted mean of the neighbours' colours, the normal the gradient
(n - g_u e1 - g_v e2) of one more fit at the hit, for the last polynomial's normal there,
under the wider shading weights (surface.py: shading normal), else of the last polynomial
where that fit fails. Parameters (`MlsParams`):
    h_scale (1.1)       kernel width h_i = h_scale * local spacing s_i (surface.MlsKernel)
    domain (2.0)        domain test / sphere radius in units of s_i (surface.MlsKernel)
    normal_sigma (0.6)  width of the normal-agreement weight (surface.MlsKernel)
    residual_sigma (0.25) width of the residual weight, in units of h_i (surface.MlsKernel)
    boundary (0.7)      half-disc test bound, in units of the local width l (surface.MlsKernel)
    shading_normal_sigma (1.2), shading_residual_sigma (0.5)
                        the shading normal's fit's widths (surface.MlsKernel)
    tolerance (1e-3)    eps, as a fraction of the local kernel width l
    max_iterations (8)  fits per candidate sphere before giving up on it
    shadows (False)     a shadow ray to the directional key light of shading.py (eye space
                        (-0.4, 0.6, 0.8)); shadowed pixels keep only the ambient 0.2 albedo
    reflect (False)     one mirror bounce traced against the surface, or else a sky/ground
                        gradient environment, mixed in with `reflectivity` (0.3)
Supersampling defaults to 2x2 rays per pixel (box filtered like every method), traced
adaptively (adaptive.py): each pixel's corner first, then every sample of the pixels whose
corners do not see one smooth surface; the others are interpolated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numba
import numpy as np

from ..options import at_least, between, check_cpu_samples, positive, setting
from ..result import RenderResult
from ..shading import KEY_LIGHT, shade
from .adaptive import interpolate, smooth_pixels
from .edges import past_edge
from .polynomial import P_COLOR, P_N, P_SCALE, POLY_SIZE, poly_normal, poly_project, poly_ray
from .surface import (
    BLOCK,
    DEFAULT_KERNEL,
    EMPTY,
    FIT_OK,
    LEAF,
    REFERENCE_UPDATES,
    SUPPORT,
    MlsKernel,
    MLSSurface,
    build_surface,
    fit,
    leaf_tree,
    new_scratch,
    point_polynomials,
)

DEFAULT_SUPERSAMPLE = 2  # rays per pixel side, box filtered like every method
TOLERANCE = 1e-3  # a projection has converged within this fraction of the local kernel width
QUEUE = 4096  # entries of a ray's traversal queue (nodes and spheres not yet visited)
SKY = np.array([0.55, 0.7, 0.95])
GROUND = np.array([0.25, 0.22, 0.2])


@dataclass(frozen=True)
class MlsParams(MlsKernel):
    tolerance: float = setting(TOLERANCE, positive)  # eps, as a fraction of the local kernel width
    max_iterations: int = setting(8, at_least(1))  # fits per candidate sphere before giving up on it
    shadows: bool = False  # a shadow ray to the key light
    reflect: bool = False  # one mirror bounce
    reflectivity: float = setting(0.3, between(0, 1))  # weight of the mirror bounce
    adaptive: bool = True  # interpolate the samples of smooth pixels between their corners (adaptive.py)


@dataclass(frozen=True, eq=False)
class MLSScene:
    """A cloud ready to ray trace: surface, per-sample polynomials and the sphere hierarchy
    (all in the surface's Morton order)."""

    surface: MLSSurface
    polys: np.ndarray   # (N, POLY_SIZE)
    valid: np.ndarray   # (N,) bool: the sample's own fit succeeded
    radius: np.ndarray  # (N,) bounding sphere radius domain * s_i, 0 where not valid
    boxes: np.ndarray   # (2L - 1, 2, 3) node boxes of the spheres, over the surface's leaves


def prepare_scene(cloud, kernel: MlsKernel = DEFAULT_KERNEL) -> MLSScene:
    """The ray tracing scene of `cloud`."""
    surface = build_surface(cloud, kernel)
    polys, status = point_polynomials(surface)
    valid = status == FIT_OK
    # a sample whose own fit failed starts no intersection: no sphere, left out of the tree
    radius = np.where(valid, kernel.domain * surface.samples.spacing, 0.0)
    boxes = leaf_tree(surface.points, np.where(valid, radius, -EMPTY))
    return MLSScene(surface, polys, valid, radius, boxes)


def scene_kernel(params: MlsKernel) -> MlsKernel:
    """The surface's part of a method's parameters: what a scene is made from (and keyed by)."""
    return MlsKernel(**{name: getattr(params, name) for name in MlsKernel.names()})


def cached_scene(cloud, params: MlsKernel, renderer) -> MLSScene:
    """The scene, made once per cloud and kernel by the Renderer (both MLS methods share it)."""
    kernel = scene_kernel(params)
    return renderer.cached(cloud, ("mls scene", kernel), lambda: prepare_scene(cloud, kernel))


@numba.njit(cache=True, fastmath=True)
def box_entry(boxes, node, o, inv_d, t_max):
    """Entry parameter of the ray into the node's box, or -1 if it misses within [0, t_max]
    (no infinities anywhere: fastmath lets the compiler assume there are none). An empty
    box (lower corner above the upper) is missed: the slab test alone would swap it into a
    box that holds everything."""
    if boxes[node, 0, 0] > boxes[node, 1, 0]:
        return -1.0
    t0, t1 = 0.0, t_max
    for a in range(3):
        ta = (boxes[node, 0, a] - o[a]) * inv_d[a]
        tb = (boxes[node, 1, a] - o[a]) * inv_d[a]
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    return t0 if t0 <= t1 else -1.0


@numba.njit(cache=True, fastmath=True)
def queue_push(keys, items, size, key, item):
    """Insert into the binary min-heap (keys, items) of `size` entries; returns the new size
    (a full queue drops the entry)."""
    if size >= keys.shape[0]:
        return size
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if keys[parent] <= key:
            break
        keys[i] = keys[parent]
        items[i] = items[parent]
        i = parent
    keys[i] = key
    items[i] = item
    return size + 1


@numba.njit(cache=True, fastmath=True)
def queue_pop(keys, items, size):
    """Remove the smallest entry (read keys[0], items[0] first); returns the new size."""
    size -= 1
    key, item = keys[size], items[size]
    i = 0
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        if child + 1 < size and keys[child + 1] < keys[child]:
            child += 1
        if keys[child] >= key:
            break
        keys[i] = keys[child]
        items[i] = items[child]
        i = child
    keys[i] = key
    items[i] = item
    return size


@numba.njit(cache=True, fastmath=True)
def trace_ray(o, d, t_min, t_max, samples, polys, radius, boxes, tolerance, max_iter,
              keys, items, scratch, poly, x, y, nref, normal, color, shading, shade):
    """Nearest intersection of o + t d (|d| = 1) with the MLS surface in [t_min, t_max].

    The bounding spheres are visited in order of the ray's entry into them, lazily: a queue
    ordered by entry parameter holds tree nodes (item >= 0) and spheres (item = -1 - sample),
    and a node is opened only when it comes first. Returns (t, fits); t < 0 when the ray
    misses. On a hit `normal` (with `shade`, of the fit under the `shading` weights, where it
    succeeds) and `color` are set; a shadow ray, which needs only whether it hits, skips that fit.
    """
    points, normals = samples.points, samples.normals
    inv_d = np.empty(3)
    for a in range(3):
        inv_d[a] = 1.0 / d[a] if d[a] != 0.0 else 1e30
    first_leaf = (boxes.shape[0] + 1) // 2 - 1
    n = points.shape[0]
    fits = 0
    size = 0
    entry = box_entry(boxes, 0, o, inv_d, t_max)
    if entry >= 0.0:
        size = queue_push(keys, items, size, entry, 0)
    while size > 0:
        t_in = keys[0]
        item = items[0]
        size = queue_pop(keys, items, size)
        if item >= 0:
            if item < first_leaf:
                for child in (2 * item + 1, 2 * item + 2):
                    entry = box_entry(boxes, child, o, inv_d, t_max)
                    if entry >= 0.0:
                        size = queue_push(keys, items, size, max(entry, t_min), child)
                continue
            start = (item - first_leaf) * LEAF
            for i in range(start, min(start + LEAF, n)):
                if radius[i] <= 0.0:
                    continue
                ox, oy, oz = o[0] - points[i, 0], o[1] - points[i, 1], o[2] - points[i, 2]
                b = ox * d[0] + oy * d[1] + oz * d[2]
                disc = b * b - (ox * ox + oy * oy + oz * oz - radius[i] * radius[i])
                if disc < 0.0:
                    continue
                root = math.sqrt(disc)
                if -b + root < t_min or -b - root > t_max:
                    continue
                size = queue_push(keys, items, size, max(-b - root, t_min), -1 - i)
            continue
        # a sphere, nearest entry first: its polynomial, then iterated projection
        i = -1 - item
        ox, oy, oz = o[0] - points[i, 0], o[1] - points[i, 1], o[2] - points[i, 2]
        b = ox * d[0] + oy * d[1] + oz * d[2]
        c = ox * ox + oy * oy + oz * oz - radius[i] * radius[i]
        t_out = min(-b + math.sqrt(max(b * b - c, 0.0)), t_max)
        t = poly_ray(polys[i], o, d, t_in, t_out)
        if t < 0.0:
            continue
        for a in range(3):
            nref[a] = normals[i, a]
        t_above, t_below, r_above, r_below, last = -1.0, -1.0, 0.0, 0.0, math.inf
        for it in range(max_iter):
            for a in range(3):
                x[a] = o[a] + t * d[a]
            fits += 1
            if fit(x, nref, samples, poly, scratch) != FIT_OK:
                break
            if poly_project(poly, x, y) < (tolerance * poly[P_SCALE]) ** 2:
                if past_edge(poly, samples, scratch):
                    break  # converged past the edge of the sheet
                poly_normal(poly, x, normal)
                for a in range(3):
                    color[a] = poly[P_COLOR + a]
                if shade and fit(x, normal, shading, poly, scratch) == FIT_OK:  # for the sheet the hit lies on
                    poly_normal(poly, x, normal)
                return t, fits
            # x's height over its fit: the ray crosses the surface between an iterate above
            # and one below (false position, with the Illinois weight, which halves an end
            # kept twice lest the search creep in from one side)
            height = (x[0] - y[0]) * poly[P_N] + (x[1] - y[1]) * poly[P_N + 1] + (x[2] - y[2]) * poly[P_N + 2]
            if height > 0.0:
                if last > 0.0:
                    r_below *= 0.5
                t_above, r_above = t, height
            else:
                if last <= 0.0:
                    r_above *= 0.5
                t_below, r_below = t, height
            stalled = abs(height) >= abs(last)
            last = height
            window = SUPPORT * poly[P_SCALE]
            t = poly_ray(poly, o, d, max(t - window, t_min), min(t + window, t_max))
            if t_above >= 0.0 and t_below >= 0.0 and (t < 0.0 or stalled) and \
                    not (min(t_above, t_below) < t < max(t_above, t_below)):
                # a grazing ray overshoots the crossing, further each time: false position
                t = t_above + (t_below - t_above) * r_above / (r_above - r_below)
            if t < 0.0:
                break
            if it < REFERENCE_UPDATES:
                for a in range(3):
                    x[a] = o[a] + t * d[a]
                poly_normal(poly, x, nref)
    return -1.0, fits


@numba.njit(cache=True, parallel=True, fastmath=True)
def trace_rays(origins, directions, t_min, t_max, samples, polys, radius, boxes, tolerance, max_iter,
               out_t, out_normal, out_color, out_fits, shading, shade):
    """trace_ray for every ray, in parallel blocks that each own their scratch buffers."""
    n = len(origins)
    for block in numba.prange((n + BLOCK - 1) // BLOCK):
        keys = np.empty(QUEUE)
        items = np.empty(QUEUE, np.int64)
        scratch = new_scratch()  # its candidate cache serves neighbouring rays
        poly = np.empty(POLY_SIZE)
        x = np.empty(3)
        y = np.empty(3)
        nref = np.empty(3)
        for r in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
            t, fits = trace_ray(origins[r], directions[r], t_min, t_max, samples, polys, radius, boxes,
                                tolerance, max_iter, keys, items, scratch, poly, x, y, nref,
                                out_normal[r], out_color[r], shading, shade)
            out_t[r] = t
            out_fits[r] = fits


@numba.njit(cache=True, parallel=True)
def sphere_footprints(centres, radius, intrinsics, ortho_scale, height, width):  # pragma: no cover
    """(height, width) mask of the pixels whose centre ray may meet a sphere (eye-space
    centres, radii; radius 0: no sphere): each sphere marks the pixel centres in the screen
    box of its bounding cube's corners, grown by a pixel. `intrinsics` fx, fy, cx, cy;
    `ortho_scale` world units a pixel (0: perspective, where no sphere may cross the eye's
    plane: `primary_candidates` marks every pixel then)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    mask = np.zeros((height, width), np.bool_)
    for i in numba.prange(centres.shape[0]):
        r = radius[i]
        x, y, z = centres[i, 0], centres[i, 1], centres[i, 2]
        if r <= 0.0 or z - r > 0.0:  # no sphere, or wholly behind the rays' start
            continue
        if ortho_scale > 0.0:
            u0, u1 = cx + (x - r) / ortho_scale, cx + (x + r) / ortho_scale
            v0, v1 = cy - (y + r) / ortho_scale, cy - (y - r) / ortho_scale
        else:
            u0 = v0 = np.inf
            u1 = v1 = -np.inf
            for corner in range(4):  # X / -Z and Y / -Z are extreme at the cube's corners
                depth = -(z + (r if corner < 2 else -r))
                a = (x + (r if corner % 2 == 0 else -r)) / depth
                b = (y + (r if corner % 2 == 0 else -r)) / depth
                u0, u1 = min(u0, cx + fx * a), max(u1, cx + fx * a)
                v0, v1 = min(v0, cy - fy * b), max(v1, cy - fy * b)
        # pixel column j's centre ray lies at u = j + 0.5
        j0, j1 = max(int(math.floor(u0 - 1.5)), 0), min(int(math.ceil(u1 + 0.5)), width - 1)
        k0, k1 = max(int(math.floor(v0 - 1.5)), 0), min(int(math.ceil(v1 + 0.5)), height - 1)
        for k in range(k0, k1 + 1):  # threads marking the same pixel all write True
            for j in range(j0, j1 + 1):
                mask[k, j] = True
    return mask


def primary_candidates(scene: MLSScene, view: np.ndarray, camera) -> np.ndarray:
    """The indices (row-major) of `camera`'s pixels whose centre ray may meet the surface:
    those in a sphere's footprint (module docstring), or all of them where a sphere crosses
    the plane of a perspective camera's eye (any ray may meet it). `view` maps the surface's
    local coordinates to eye space."""
    centres = scene.surface.points @ view[:3, :3].T + view[:3, 3]
    ortho = camera.ortho_height / camera.height if camera.ortho_height is not None else 0.0
    if not ortho and (np.abs(centres[:, 2]) <= scene.radius)[scene.radius > 0].any():
        return np.arange(camera.width * camera.height)
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], np.float64)
    mask = sphere_footprints(centres, scene.radius, intrinsics, float(ortho), camera.height, camera.width)
    return np.flatnonzero(mask.ravel())


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
          tolerance: float = 1e-3, max_iter: int = 8, shade: bool = True) -> Hits:
    """Trace rays given in the surface's local coordinates (directions unit length); without
    `shade` the hits' normals are the last fit's (enough to know whether a ray is blocked)."""
    n = len(origins)
    hits = Hits(np.empty(n), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n, np.int64))
    trace_rays(np.ascontiguousarray(origins, np.float64), np.ascontiguousarray(directions, np.float64),
               float(t_min), float(t_max), scene.surface.samples, scene.polys,
               scene.radius, scene.boxes, float(tolerance), int(max_iter),
               hits.t, hits.normals, hits.colors, hits.fits, scene.surface.shading, shade)
    return hits


def supersampled(camera, ss: int):
    """The same view with ss x ss rays per pixel (intrinsics scaled, pixel centres kept)."""
    return camera.with_(width=camera.width * ss, height=camera.height * ss, fx=camera.fx * ss,
                        fy=camera.fy * ss, cx=camera.cx * ss, cy=camera.cy * ss)


def environment(directions_eye: np.ndarray) -> np.ndarray:
    """A sky/ground gradient seen along eye-space directions (image up is sky)."""
    k = (0.5 + 0.5 * directions_eye[:, 1:2]) ** 0.7
    return GROUND * (1 - k) + SKY * k


@dataclass
class SampleHits:
    """The samples of a frame that meet the surface: flat indices into the supersampled image,
    local-space points, eye depths, eye-space normals (facing the viewer), albedos, and the fits
    each traced sample took (interpolated samples take none)."""

    idx: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    fits: np.ndarray

    @staticmethod
    def concatenate(parts: list[SampleHits]) -> SampleHits:
        return SampleHits(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(SampleHits)))


class FrameTracer:
    """Traces camera samples of one frame: `cam` the supersampled camera, `view` the surface's
    local coordinates to eye space."""

    def __init__(self, scene: MLSScene, cam, view: np.ndarray, params: MlsParams, t_max: float):
        self.scene, self.cam, self.view, self.params, self.t_max = scene, cam, view, params, t_max
        self.to_local = np.linalg.inv(view)
        self.traced = 0

    def rays(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local-space origins and directions, and eye-space directions, of samples `idx`."""
        o_eye, d_eye = self.cam.rays_at(*np.divmod(idx, self.cam.width))
        return o_eye @ self.to_local[:3, :3].T + self.to_local[:3, 3], d_eye @ self.view[:3, :3], d_eye

    def trace(self, idx: np.ndarray) -> SampleHits:
        """Trace samples `idx`; those that hit."""
        origins, dirs, d_eye = self.rays(idx)
        hits = trace(self.scene, origins, dirs, 0.0, self.t_max, self.params.tolerance, self.params.max_iterations)
        self.traced += len(idx)
        found = np.flatnonzero(hits.hit)
        points = origins[found] + hits.t[found, None] * dirs[found]
        normals = hits.normals[found] @ self.view[:3, :3].T
        normals *= np.where(np.sum(normals * d_eye[found], axis=1) > 0, -1.0, 1.0)[:, None]  # face the viewer
        return SampleHits(idx[found], points, -(points @ self.view[2, :3] + self.view[2, 3]), normals,
                          hits.colors[found], hits.fits[found])

    def adaptive(self, candidates: np.ndarray, ss: int) -> tuple[SampleHits, int]:
        """The hits of the candidate samples, adaptively (adaptive.py): the pixels' corners
        traced, then the samples of the pixels that are not smooth; the smooth pixels' samples
        interpolated. Returns the hits and the number interpolated."""
        w = self.cam.width
        height, width = self.cam.height // ss, w // ss
        rows, cols = np.divmod(candidates, w)
        corner = (rows % ss == 0) & (cols % ss == 0)
        first = self.trace(candidates[corner])
        # the corners' eye-space points, normals and albedos
        corners = np.zeros((height * width, 9))
        at = (first.idx // w // ss) * width + first.idx % w // ss
        corners[at] = np.column_stack([first.points @ self.view[:3, :3].T + self.view[:3, 3], first.normals,
                                       first.albedo])
        hit = np.zeros(height * width, bool)
        hit[at] = True
        corners = corners.reshape(height, width, 9)
        eye_points, normals, albedo = corners[..., :3], corners[..., 3:6], corners[..., 6:]
        smooth = smooth_pixels(hit.reshape(height, width), eye_points, normals, albedo, self.scene.surface.scale)
        second = self.trace(candidates[~corner & ~smooth.ravel()[(rows // ss) * width + cols // ss]])
        # every sample of a smooth pixel but its corner, whether its ray lies in a footprint or not
        pi, pj = np.nonzero(smooth)
        a, b = np.divmod(np.arange(1, ss * ss), ss)
        points, normals, albedo = interpolate(eye_points, normals, albedo, pi, pj, ss)
        filled = SampleHits(((pi[:, None] * ss + a) * w + pj[:, None] * ss + b).ravel(),
                            points @ self.to_local[:3, :3].T + self.to_local[:3, 3], -points[:, 2], normals, albedo,
                            np.zeros(len(points), np.int64))
        return SampleHits.concatenate([first, second, filled]), len(points)


def render_mls_cpu(cloud, camera, options, params: MlsParams, renderer) -> RenderResult:
    ss = options.supersample or DEFAULT_SUPERSAMPLE
    check_cpu_samples(camera.width * ss, camera.height * ss)
    tolerance, max_iter = params.tolerance, params.max_iterations
    scene = cached_scene(cloud, params, renderer)
    surface = scene.surface
    cam = supersampled(camera, ss)
    h, w = cam.height, cam.width
    view = camera.view_matrix(surface.origin)  # eye = view (local)
    rot = view[:3, :3]  # local (and world) directions to eye space, as FrameTracer turns them
    candidates = primary_candidates(scene, view, cam)
    tracer = FrameTracer(scene, cam, view, params, 2.0 * (camera.far + np.linalg.norm(view[:3, 3])))
    if params.adaptive and ss > 1:
        samples, interpolated = tracer.adaptive(candidates, ss)
    else:
        samples, interpolated = tracer.trace(candidates), 0
    idx, x_local, n_hit, albedo = samples.idx, samples.points, samples.normals, samples.albedo
    depth = np.full(h * w, np.inf)
    depth[idx] = samples.depth
    n_eye = np.zeros((h * w, 3))
    n_eye[idx] = n_hit
    t_max = tracer.t_max
    traced_fits = samples.fits[samples.fits > 0]
    indices = None
    coloring = options.coloring
    colors_of = renderer.surface_colors(cloud, cam, options)
    if colors_of is not None:  # the surface's own elevation, the nearest sample's category (never a blend)
        surface_albedo, indices = colors_of(depth.reshape(h, w))
        albedo = surface_albedo.reshape(-1, 3)[idx]
    elif coloring is not None:
        albedo = coloring.decode(albedo)
    shaded_hit = shade(options.surface_shading, albedo, n_hit, depth[idx], camera.near, camera.far)
    stats = {"splats": len(cloud), "rays": int(h * w), "candidates": int(candidates.size),
             "traced": tracer.traced, "interpolated": interpolated, "hits": int(idx.size),
             "iterations_mean": round(float(traced_fits.mean()), 3) if traced_fits.size else 0.0,
             "iterations_max": int(traced_fits.max()) if traced_fits.size else 0,
             "point_fit_failures": int((~scene.valid).sum()), "supersample": ss,
             "kernel_width": surface.scale}
    offset = 2.0 * tolerance * surface.scale + 0.25 * surface.scale
    n_world = n_hit @ rot  # flipped towards the viewer
    if params.shadows and idx.size:
        light = KEY_LIGHT @ rot  # eye-space key light to world
        facing = n_world @ light > 0
        start = x_local + offset * np.where(facing[:, None], n_world, -n_world)
        blocked = trace(scene, start, np.broadcast_to(light, start.shape), 0.0, t_max, tolerance, max_iter,
                        shade=False).hit
        shadowed = blocked | ~facing
        shaded_hit[shadowed] = 0.2 * albedo[shadowed]
        stats["shadowed"] = int(shadowed.sum())
    if params.reflect and idx.size:
        reflectivity = params.reflectivity
        dv = tracer.rays(idx)[1]
        refl = dv - 2 * np.sum(dv * n_world, axis=1)[:, None] * n_world
        bounce = trace(scene, x_local + offset * n_world, refl, 0.0, t_max, tolerance, max_iter)
        seen = environment(refl @ rot.T)
        if bounce.hit.any():
            b = bounce.hit
            bn = bounce.normals[b] @ rot.T
            bd = refl[b] @ rot.T
            bn *= np.where(np.sum(bn * bd, axis=1) > 0, -1.0, 1.0)[:, None]
            bounce_albedo = bounce.colors[b] if coloring is None else coloring.decode(bounce.colors[b])
            seen[b] = shade(options.surface_shading, bounce_albedo, bn, depth[idx][b], camera.near, camera.far)
        shaded_hit = (1 - reflectivity) * shaded_hit + reflectivity * seen
        stats["reflected_hits"] = int(bounce.hit.sum())
    shaded = np.zeros((h * w, 3), np.float32)  # misses: no coverage, their colour never shows
    shaded[idx] = shaded_hit
    coverage = np.zeros(h * w, np.float32)
    coverage[idx] = 1.0
    return RenderResult.from_samples(shaded.reshape(h, w, 3), coverage.reshape(h, w),
                                     depth.reshape(h, w), n_eye.reshape(h, w, 3), supersample=ss,
                                     options=options, stats=stats, indices=indices)
