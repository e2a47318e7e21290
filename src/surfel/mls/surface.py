"""The moving least squares (MLS) point set surface and its projection operator.

Adamson & Alexa, "Ray tracing point set surfaces", SMI 2003 (survey section 2.3.1, Fig. 14),
with kernel widths that follow the local sampling and weights on normal agreement and on the
residual of each sample's tangent plane.
The surface S is the set of points that the projection operator maps onto themselves.
Projecting a point r for the sheet facing a reference normal n_r, over the samples p_i (unit,
oriented normals n_i) whose support |p_i - r| < 2.5 h_i holds r:

    w_i  = exp(-|p_i - r|^2 / h_i^2 - |n_i - n_r|^2 / sigma_n^2 - (n_i . (r - p_i))^2 / (sigma_r h_i)^2)
    l    = sum w_i h_i / sum w_i                          local kernel width: the unit of the fit
    q    = sum w_i p_i / sum w_i                          origin of the reference plane H
    n    = sum w_i n_i / |sum w_i n_i|                    normal of H (e1, e2 span H)
    g    = argmin sum w_i (g(u_i, v_i) - f_i)^2           bivariate quadratic over H,
           g(u, v) = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2,
           (u_i, v_i, f_i) = coordinates of (p_i - q) / l in (e1, e2, n)
    P(r) = q + l (u_r e1 + v_r e2 + g(u_r, v_r) n)        (u_r, v_r) = coordinates of (r - q) / l in H

H's normal is the samples' weighted mean normal (Adamson & Alexa, "Approximating and intersecting
surfaces from points", SGP 2003), not the covariance's smallest eigenvector: on a coarse thin
part (a tail sampled as rings far apart along it) a support may hold one ring, a planar curve
whose plane lies across the part, and a quadratic over that plane misses the ray. The quadratic
is undetermined there too (one ring, or two: v^2 is then a combination of 1 and v); where its
normal equations are singular it is the smoothest that fits (Tikhonov), minimising
sum w_i (g(u_i, v_i) - f_i)^2 + RIDGE sum w_i (c1^2 + ... + c5^2): it leans to H.
A projection starts with its first sample's normal as n_r; the normal of the first
REFERENCE_UPDATES fits at their projected points becomes the next n_r, then n_r is kept (the
iteration converges to a fixed point of one operator).

Kernel width (adaptive MLS): h_i = h_scale * s_i, s_i the sample's spacing (widths.py): the
mean distance to its 8 nearest neighbours, median-smoothed, or more where the sampling leaves
a gap in its tangent plane (rings of vertices far apart along a thin part). Dense parts (a
face) keep a narrow kernel and their detail, sparse parts (a body) a wide one and no holes.
Where dense and sparse sampling meet, a narrow kernel next to a wide one would leave the gap
between them to the wide kernels alone; so, as the feature-size-proportional widths of Dey &
Sun ("An adaptive MLS surface for reconstruction with guarantees", 2005) are Lipschitz, the
widths are limited in slope along a sheet: h_i >= h_j - WIDTH_SLOPE |p_i - p_j| for every
sample j whose support reaches p_i and whose normal lies within 45 degrees of n_i.

Normal weight (Oztireli, Guennebaud & Gross, "Feature preserving point set surfaces based on
non-linear kernel regression", 2009): samples whose oriented normal disagrees with n_r (the
other side of a thin finger, the facing side of a gap, the far face across a crease) get little
weight: thin parts keep both sides, gaps stay open, creases stay sharp.

Residual weight (the same paper's robust weight on residuals): r's distance from sample i's
tangent plane, n_i . (r - p_i), over sigma_r h_i. The paper weighs the residual f(r) -
n_i . (r - p_i), f the implicit function; at a fixed point of the projection, r on S, f(r) = 0,
which is what a ray's iterates approach from its first candidate on, so f = 0 here and the
weight costs no iteration of its own. A layer of samples that faces the same way as the one r
lies on but lies behind it (a coarse cow's tail lying on its rump, a sheet on a body) is then
left out of r's fit instead of pulling the surface into the space between the two, where it
showed neither; the far face across a crease weighs less too. With it, the kernels can be
narrower (h_scale 1.1, was 1.2) and keep more detail without opening holes in thin parts.
Measured on the vertices of twelve meshes (figures, a bust, CAD parts), front and side views
at 512 x 512 against the mesh: median PSNR 37.8 -> 39.2 dB, each render -0.1 to +4.0 dB
(the coarse cow's front view 26.8 -> 28.0 dB, its holes 0.09% -> 0.04%). On raw range scans,
whose noise is about a fifth of a kernel width, the narrower weight and kernels average less
of it: on scans of three of those meshes (benchmarks/scan_fidelity.py), median 37.9 -> 37.0 dB,
their holes fewer. Denoising first (`surfel prepare --smooth`) suits such scans better. A LiDAR
canopy, no surface at all, keeps fewer of its crowns' scattered returns in each fit: at 384 x 384
more of lidR's MixedConifer tile shows through (pinholes 3.3% -> 6.0% of its covered area).

Shading normal. A hit is shaded with the gradient of one more fit at it, for the sheet it lies
on (n_r = the surface's normal there), under wider weights (sigma_n = shading_normal_sigma 1.2,
sigma_r = shading_residual_sigma 0.5; the surface's own fits keep 0.6 and 0.25). Where the
sampling is coarse against the curvature (a decimated figure's face, a CAD part's fillets),
neighbouring samples' normals differ by 30 degrees and more, the narrow weights keep few samples
in each fit, and neighbouring pixels' fits keep different ones: the shading broke into specks
and facets. The surface itself stays where the narrow weights put it: widening those (0.8 and
0.35) gained as much but rounded creases (the extent test no longer ended a cube's face at its
crease) and shrank convex silhouettes by a pixel or two (the decimated ogre's holes 0.084% ->
0.147% at worst over 18 views). The reference normal of that fit is the hit's normal rather than
the projection's n_r, which the CPU tracer and the GPU caster reach by different numbers of
steps: their shading of a coarse tube then agrees to 56 dB instead of 34 (one sample a pixel).
Measured on the vertices of 13 meshes (five coarse or decimated figures, a cow, CAD parts, a
teapot, dense figures), six views each at 512 x 512 against the mesh (lambert): median PSNR
31.77 -> 33.24 dB, holes the same; fandisk 30.1 -> 35.9 dB, the decimated bunny 28.4 -> 30.0,
the decimated ogre 28.1 -> 29.1, cow 30.8 -> 31.4; dense models lose a little detail (homer 42.8
-> 42.5, teapot 35.1 -> 34.8 dB), and a large face sampled only along its rim takes in some of
its side faces' normals (a decimated bust's base seen from below, 27.2 -> 25.7 dB).

Limits. A small flat face sampled only along its rim, at right angles to the faces beside it,
has few samples that carry its normal (a rim vertex's normal averages the faces that meet
there): no fit both reaches into the face and keeps to it, and the surface stops short of the
rim or leaves it open. A horse's hoof soles are such faces (in a close-up, even the
48,485-vertex mesh's); decimated to 2,500, 4,000 and 6,000 vertices, they leave more than 0.1%
of the outline uncovered in 13, 10 and 3 of 18 views (at most 0.48%; 512 x 512,
benchmarks/scan_fidelity.py --vertices --oblique). Filling such rays from a second projection
under the shading weights, or from the nearest sample's own polynomial within a spacing of it,
covered most of those pixels but spread the hooves past their outline as much (-0.5 to -1.3 dB
on those horses, down to -0.7 dB on other decimated figures), so neither was kept.

Domain. A fit needs MIN_NEIGHBOURS = 3 samples facing n_r (n_i . n_r > 0) in its support (a plane:
inside a coarse part's large flat triangles only the corners' supports reach; below six the ridge
makes the quadratic lean to H), and one within `domain * s_i` of r (Adamson & Alexa's domain
test). Where a projection converges, the edge tests of edges.py cut a sheet where it ends.
Failures are statuses (FIT_*), never exceptions.

Neighbour search: a bounding volume hierarchy over the supports. The samples are stored in
Morton order; each leaf holds LEAF consecutive samples, each node the box of its samples'
support boxes (an implicit complete binary tree in heap order). A query descends into the
boxes that hold r and reads the leaves' samples from contiguous memory (the ray tracer's tree
of bounding spheres has the same leaves). A fitted polynomial is a float64 row of POLY_SIZE
values (polynomial.py's P_* offsets).
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..cloud import PointCloud
from ..lod.build import morton_codes
from ..options import Settings, positive, setting
from ..preprocess import estimate_normals
from .edges import past_edge
from .polynomial import (
    P_C,
    P_COLOR,
    P_E1,
    P_E2,
    P_N,
    P_Q,
    P_SCALE,
    POLY_SIZE,
    poly_project,
    solve_spd,
    tangent_frame,
)
from .widths import sample_spacing

# Fit statuses.
FIT_OK = 0
FIT_TOO_FEW = 1        # fewer than MIN_NEIGHBOURS samples facing n_r in the support
FIT_DEGENERATE = 2     # the samples' normals cancel out, or the system is singular
FIT_OUTSIDE = 3        # the domain test failed: no sample near enough (a hole or past the boundary)
FIT_NOT_CONVERGED = 4  # projection did not reach the tolerance in the allowed iterations

MIN_NEIGHBOURS = 3     # a plane; with fewer than 6 the quadratic is singular and leans to it (RIDGE)
SUPPORT = 2.5          # Gaussian truncated at SUPPORT * h (weight exp(-6.25) = 0.002)
MAX_NEIGHBOURS = 512   # neighbour buffer of one fit (a support holds ~50 on even sampling)
CACHE = 2048           # candidate cache of a thread's fits (see `gather`)
CACHE_REACH = 0.5      # ... valid within this many median kernel widths of where it was filled
BLOCK = 256            # queries of one thread in a row: samples, or rays of one image row
WIDTH_SLOPE = 0.5      # kernel widths fall by at most this per unit distance along a sheet
WIDTH_SHEET_COS = 0.7  # ... a sheet: samples whose normals lie within 45 degrees
WIDTH_PASSES = 2       # passes of that limit (each reaches one support further)
RESIDUAL = 0.25        # sigma_r of the residual weight, in units of h_i (MlsKernel.residual_sigma)
SHADING_NORMAL = 1.2   # sigma_n of the fit whose gradient shades a hit (MlsKernel.shading_normal_sigma)
SHADING_RESIDUAL = 0.5  # ... and its sigma_r, in units of h_i (MlsKernel.shading_residual_sigma)
RIDGE = 1e-3           # weight of the quadratic's regularisation where its fit is singular (of sum w)
REFERENCE_UPDATES = 2  # fits whose normal becomes the next fit's reference normal; later fits keep it
LEAF = 8               # samples per leaf of the hierarchies
STACK = 64             # traversal stack: twice the depth of any tree that fits in memory
EMPTY = 1e30           # bounds of an empty box (finite: fastmath assumes no infinities)


@dataclass(frozen=True)
class MlsKernel(Settings):
    """The surface's definition, shared by the `mls` and `mls-gpu` parameters."""

    h_scale: float = setting(1.1, positive)  # kernel width h_i = h_scale * local spacing s_i
    domain: float = setting(2.0, positive)  # domain test (and bounding sphere) radius, in units of s_i
    normal_sigma: float = setting(0.6, positive)  # width sigma_n of the normal-agreement weight
    boundary: float = setting(0.7, positive)  # half-disc test: tangential offset of the mean, in l (edge: 0.56)
    residual_sigma: float = setting(RESIDUAL, positive)  # width sigma_r of the residual weight, in h_i
    shading_normal_sigma: float = setting(SHADING_NORMAL, positive)  # sigma_n of the shading normal's fit
    shading_residual_sigma: float = setting(SHADING_RESIDUAL, positive)  # sigma_r of the shading normal's fit


DEFAULT_KERNEL = MlsKernel()

# What the compiled kernels read, in Morton order (numba takes a namedtuple of arrays whole):
# points (N, 3), normals (N, 3) unit and oriented, h (N,) kernel widths, spacing (N,) s_i,
# colors (N, 3), boxes (2L - 1, 2, 3) support boxes of the tree's nodes, domain, normal_weight
# (1 / sigma_n^2), residual_weight (1 / sigma_r^2), boundary (the half-disc bound), reach (of
# the candidate cache, CACHE_REACH h).
Samples = namedtuple("Samples", "points normals h spacing colors boxes domain normal_weight residual_weight "
                                 "boundary reach")
# One thread's scratch for `fit`: nb (MAX_NEIGHBOURS, 6) neighbour rows (found[0] of them
# written by the last fit), stack (STACK,) of the
# traversal, cache (CACHE + 1,) candidate count then indices, centre (4,) where the cache was
# filled and how far from there it holds (0: empty), work (7, 7) the normal equations.
Scratch = namedtuple("Scratch", "nb found stack cache centre work")


@dataclass(frozen=True, eq=False)
class MLSSurface:
    """A point set prepared for MLS projection (positions relative to `origin`, in Morton
    order: `order[k]` is the cloud's index of sample k). `density_width` (N,): h_scale m_i, the
    kernel width each sample's sampling density alone gives (m_i: widths.py), which the GPU
    caster's retries step by (gpu.glsl RETRY_GAP)."""

    origin: np.ndarray
    order: np.ndarray
    samples: Samples
    density_width: np.ndarray
    shading: Samples  # the same samples under the shading normal's weights (module docstring)

    @property
    def points(self) -> np.ndarray:
        return self.samples.points

    @property
    def normals(self) -> np.ndarray:
        return self.samples.normals

    @property
    def domain(self) -> float:
        return self.samples.domain

    @property
    def scale(self) -> float:
        """Typical kernel width (the median): a unit for tolerances reported in stats."""
        return float(np.median(self.samples.h))


def leaf_tree(centers: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(2L - 1, 2, 3) boxes of the implicit complete binary tree whose leaves hold LEAF
    consecutive spheres (centres in Morton order): each node bounds its spheres."""
    n = len(centers)
    leaves = 1 << max(0, math.ceil(math.log2(max(1, math.ceil(n / LEAF)))))
    lo = np.full((leaves * LEAF, 3), EMPTY)
    hi = np.full((leaves * LEAF, 3), -EMPTY)
    lo[:n] = centers - radius[:, None]
    hi[:n] = centers + radius[:, None]
    level_lo = lo.reshape(leaves, LEAF, 3).min(axis=1)
    level_hi = hi.reshape(leaves, LEAF, 3).max(axis=1)
    boxes = np.empty((2 * leaves - 1, 2, 3))
    first = leaves - 1
    while True:
        boxes[first: first + len(level_lo), 0] = level_lo
        boxes[first: first + len(level_lo), 1] = level_hi
        if first == 0:
            return boxes
        level_lo = np.minimum(level_lo[0::2], level_lo[1::2])
        level_hi = np.maximum(level_hi[0::2], level_hi[1::2])
        first = (first - 1) // 2


def oriented_normals(cloud: PointCloud) -> np.ndarray:
    """The cloud's unit normals, estimated (and oriented) where it has none."""
    if cloud.normals is not None:
        normals = cloud.normals.astype(np.float64)
    else:
        normals = np.asarray(estimate_normals(cloud.positions)[0], np.float64)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.where(length > 0, normals / np.maximum(length, 1e-300), 0.0)


def build_surface(cloud: PointCloud, kernel: MlsKernel = DEFAULT_KERNEL) -> MLSSurface:
    """Spacing, kernel widths, Morton order and the support hierarchy of `cloud`."""
    origin = cloud.local_origin
    order = np.argsort(morton_codes(cloud.positions), kind="stable")
    points = np.ascontiguousarray(cloud.positions[order] - origin)
    normals = np.ascontiguousarray(oriented_normals(cloud)[order])
    sampled, local = sample_spacing(points, normals)
    h = kernel.h_scale * sampled
    unit = np.ones((len(points), 3))
    for _ in range(WIDTH_PASSES):
        provisional = Samples(points, normals, h, h / kernel.h_scale, unit,
                              leaf_tree(points, SUPPORT * h), 0.0, 0.0, 0.0, 0.0, CACHE_REACH * float(np.median(h)))
        h = limited_widths(provisional, WIDTH_SLOPE)
    spacing = h / kernel.h_scale
    colors = np.ones((len(points), 3)) if cloud.colors is None else cloud.colors[order].astype(np.float64)
    boxes = leaf_tree(points, SUPPORT * h)
    samples = Samples(points, normals, h, spacing, np.ascontiguousarray(colors), boxes, float(kernel.domain),
                      1.0 / kernel.normal_sigma**2, 1.0 / kernel.residual_sigma**2, float(kernel.boundary),
                      CACHE_REACH * float(np.median(h)))
    shading = samples._replace(normal_weight=1.0 / kernel.shading_normal_sigma**2,
                               residual_weight=1.0 / kernel.shading_residual_sigma**2)
    return MLSSurface(origin, order, samples, kernel.h_scale * local, shading)


@numba.njit(cache=True)
def new_scratch():
    """One thread's `Scratch`, its candidate cache empty."""
    return Scratch(np.empty((MAX_NEIGHBOURS, 6)), np.zeros(1, np.int64), np.empty(STACK, np.int64),
                   np.zeros(CACHE + 1, np.int64),
                   np.zeros(4), np.empty((7, 7)))


@numba.njit(cache=True, fastmath=True)
def collect(x, reach, samples, stack, cache):
    """Through the support hierarchy, the samples whose support grown by `reach` holds x:
    their indices into cache[1:], their count into cache[0]. False when more than CACHE."""
    points, h, boxes = samples.points, samples.h, samples.boxes
    n = points.shape[0]
    first_leaf = (boxes.shape[0] + 1) // 2 - 1
    x0, x1, x2 = x[0], x[1], x[2]
    count = 0
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        if (x0 < boxes[node, 0, 0] - reach or x0 > boxes[node, 1, 0] + reach or x1 < boxes[node, 0, 1] - reach
                or x1 > boxes[node, 1, 1] + reach or x2 < boxes[node, 0, 2] - reach
                or x2 > boxes[node, 1, 2] + reach):
            continue
        if node < first_leaf:
            stack[top] = 2 * node + 2
            stack[top + 1] = 2 * node + 1
            top += 2
            continue
        start = (node - first_leaf) * LEAF
        for i in range(start, min(start + LEAF, n)):
            dx, dy, dz = points[i, 0] - x0, points[i, 1] - x1, points[i, 2] - x2
            grown = SUPPORT * h[i] + reach
            if dx * dx + dy * dy + dz * dz < grown * grown:
                if count == CACHE:
                    cache[0] = count
                    return False
                count += 1
                cache[count] = i
    cache[0] = count
    return True


@numba.njit(cache=True, fastmath=True)
def gather(x, nref, samples, scratch):
    """The samples whose support holds x: rows of scratch.nb get (p_i - x, w_i, h_i, index).
    Returns (count, facing, inside): the rows written, the samples facing nref, and whether
    one of those passes the domain test.

    Candidates come from a cache: the samples whose support grown by samples.reach holds the
    cache's centre c include every sample whose support holds an x with |x - c| < reach
    (triangle inequality). Successive queries nearby -- a ray's iterations, neighbouring rays,
    consecutive samples in Morton order -- skip the hierarchy; the result is the same."""
    points, normals, h, spacing = samples.points, samples.normals, samples.h, samples.spacing
    normal_weight, residual_weight = samples.normal_weight, samples.residual_weight
    domain2 = samples.domain * samples.domain
    nb, cache, centre = scratch.nb, scratch.cache, scratch.centre
    x0, x1, x2 = x[0], x[1], x[2]
    cx, cy, cz = x0 - centre[0], x1 - centre[1], x2 - centre[2]
    if centre[3] <= 0.0 or cx * cx + cy * cy + cz * cz >= centre[3] * centre[3]:
        centre[0], centre[1], centre[2], centre[3] = x0, x1, x2, samples.reach
        if not collect(x, samples.reach, samples, scratch.stack, cache):
            collect(x, 0.0, samples, scratch.stack, cache)  # crowded: exactly the supports holding x,
            centre[3] = 0.0  # valid for x alone
    count = 0
    facing = 0
    inside = False
    for k in range(1, cache[0] + 1):
        i = cache[k]
        dx, dy, dz = points[i, 0] - x0, points[i, 1] - x1, points[i, 2] - x2
        d2 = dx * dx + dy * dy + dz * dz
        hi2 = h[i] * h[i]
        if d2 >= SUPPORT * SUPPORT * hi2 or count >= nb.shape[0]:
            continue
        cos = normals[i, 0] * nref[0] + normals[i, 1] * nref[1] + normals[i, 2] * nref[2]
        residual = normals[i, 0] * dx + normals[i, 1] * dy + normals[i, 2] * dz  # n_i . (p_i - x)
        # |n_i - n_r|^2 = 2 (1 - cos) for unit normals
        nb[count, 0], nb[count, 1], nb[count, 2] = dx, dy, dz
        nb[count, 3] = math.exp(-(d2 + residual * residual * residual_weight) / hi2 - 2.0 * (1.0 - cos) * normal_weight)
        nb[count, 4] = h[i]
        nb[count, 5] = i
        count += 1
        if cos > 0.0:
            facing += 1
            if d2 < domain2 * spacing[i] * spacing[i]:
                inside = True
    return count, facing, inside


@numba.njit(cache=True, parallel=True)
def limited_widths(samples, slope):
    """Kernel widths raised so that none falls faster than `slope` per unit distance from the
    width of a sample of the same sheet whose support reaches it: h_i >= h_j - slope |p_i - p_j|."""
    points, normals, h = samples.points, samples.normals, samples.h
    out = h.copy()
    n = points.shape[0]
    for block in numba.prange((n + BLOCK - 1) // BLOCK):
        scratch = new_scratch()  # per block of consecutive (nearby) samples: its cache is reused
        nb = scratch.nb
        for i in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
            count, _, _ = gather(points[i], normals[i], samples, scratch)
            for k in range(count):
                j = int(nb[k, 5])
                cos = normals[i, 0] * normals[j, 0] + normals[i, 1] * normals[j, 1] + normals[i, 2] * normals[j, 2]
                if cos > WIDTH_SHEET_COS:
                    distance = math.sqrt(nb[k, 0] ** 2 + nb[k, 1] ** 2 + nb[k, 2] ** 2)
                    out[i] = max(out[i], h[j] - slope * distance)
    return out


@numba.njit(cache=True, fastmath=True)
def fit(x, nref, samples, poly, scratch):
    """Fit the local MLS polynomial at x, for the sheet facing nref, into `poly` (POLY_SIZE);
    returns a FIT_* status. `scratch` is the thread's `Scratch`.

    Coordinates over H are in units of the local kernel width l so that the normal equations
    stay well conditioned at any sampling density. Two passes over the neighbours: the
    weighted sums of offsets, normals, widths and colours, then the 15 moments w u^a v^b
    (a + b <= 4) and 6 sums w f u^a v^b (a + b <= 2) that make the quadratic's normal
    equations, as the GPU caster sums them.
    """
    count, facing, inside = gather(x, nref, samples, scratch)
    if facing < MIN_NEIGHBOURS:
        return FIT_TOO_FEW
    if not inside:
        return FIT_OUTSIDE
    scratch.found[0] = count
    nb, work, colors = scratch.nb, scratch.work, samples.colors
    sw = sh = mx = my = mz = cr = cg = cb = 0.0
    snx = sny = snz = 0.0
    normals = samples.normals
    for k in range(count):
        w = nb[k, 3]
        i = int(nb[k, 5])
        dx, dy, dz = nb[k, 0], nb[k, 1], nb[k, 2]
        sw += w
        sh += w * nb[k, 4]
        mx += w * dx
        my += w * dy
        mz += w * dz
        snx += w * normals[i, 0]
        sny += w * normals[i, 1]
        snz += w * normals[i, 2]
        cr += w * colors[i, 0]
        cg += w * colors[i, 1]
        cb += w * colors[i, 2]
    if sw <= 0.0:
        return FIT_TOO_FEW
    mx /= sw
    my /= sw
    mz /= sw
    scale = sh / sw
    inv_s = 1.0 / scale
    length = math.sqrt(snx * snx + sny * sny + snz * snz)
    if snx * nref[0] + sny * nref[1] + snz * nref[2] <= 1e-9 * sw:
        return FIT_DEGENERATE  # the normals cancel out, or the other sheet outweighs n_r's
    nrm = poly[P_N:P_N + 3]
    nrm[0], nrm[1], nrm[2] = snx / length, sny / length, snz / length
    e1 = poly[P_E1:P_E1 + 3]
    e2 = poly[P_E2:P_E2 + 3]
    tangent_frame(nrm, e1, e2)
    # frame axes scaled by 1 / l, so (u, v, f) come from p - x directly
    e1x, e1y, e1z = e1[0] * inv_s, e1[1] * inv_s, e1[2] * inv_s
    e2x, e2y, e2z = e2[0] * inv_s, e2[1] * inv_s, e2[2] * inv_s
    nx, ny, nz = nrm[0] * inv_s, nrm[1] * inv_s, nrm[2] * inv_s
    m10 = m01 = m20 = m11 = m02 = m30 = m21 = m12 = m03 = m40 = m31 = m22 = m13 = m04 = 0.0
    f00 = f10 = f01 = f20 = f11 = f02 = 0.0
    for k in range(count):
        w = nb[k, 3]
        px, py, pz = nb[k, 0] - mx, nb[k, 1] - my, nb[k, 2] - mz
        u = px * e1x + py * e1y + pz * e1z
        v = px * e2x + py * e2y + pz * e2z
        wf = w * (px * nx + py * ny + pz * nz)
        wu, wv = w * u, w * v
        wuu, wuv, wvv = wu * u, wu * v, wv * v
        m10 += wu
        m01 += wv
        m20 += wuu
        m11 += wuv
        m02 += wvv
        m30 += wuu * u
        m21 += wuu * v
        m12 += wuv * v
        m03 += wvv * v
        m40 += wuu * u * u
        m31 += wuu * u * v
        m22 += wuu * v * v
        m13 += wuv * v * v
        m04 += wvv * v * v
        f00 += wf
        f10 += wf * u
        f01 += wf * v
        f20 += wf * u * u
        f11 += wf * u * v
        f02 += wf * v * v
    for ridge in (0.0, RIDGE * sw):  # the least squares fit; where it is singular, the smoothest
        # normal equations of the basis (1, u, v, u^2, u v, v^2): lower triangle, rhs in row 6
        work[0, 0] = sw
        work[1, 0], work[1, 1] = m10, m20 + ridge
        work[2, 0], work[2, 1], work[2, 2] = m01, m11, m02 + ridge
        work[3, 0], work[3, 1], work[3, 2], work[3, 3] = m20, m30, m21, m40 + ridge
        work[4, 0], work[4, 1], work[4, 2], work[4, 3], work[4, 4] = m11, m21, m12, m31, m22 + ridge
        work[5, 0], work[5, 1], work[5, 2], work[5, 3], work[5, 4], work[5, 5] = m02, m12, m03, m22, m13, m04 + ridge
        work[6, 0], work[6, 1], work[6, 2], work[6, 3], work[6, 4], work[6, 5] = f00, f10, f01, f20, f11, f02
        if solve_spd(work, work[6, :6], 6):
            break
    else:
        return FIT_DEGENERATE
    coef = work[6, :6]
    poly[P_Q] = x[0] + mx
    poly[P_Q + 1] = x[1] + my
    poly[P_Q + 2] = x[2] + mz
    for a in range(6):
        poly[P_C + a] = coef[a]
    poly[P_COLOR] = cr / sw
    poly[P_COLOR + 1] = cg / sw
    poly[P_COLOR + 2] = cb / sw
    poly[P_SCALE] = scale
    return FIT_OK


@numba.njit(cache=True)
def project_points(xs, nrefs, samples, tolerance, max_iter, out, status, iterations):
    """Iterate r <- P(r) for every row of xs (reference normal: the row of nrefs, then each
    fit's normal at the projected point) until the step is below tolerance * l."""
    poly = np.empty(POLY_SIZE)
    scratch = new_scratch()
    x = np.empty(3)
    y = np.empty(3)
    nref = np.empty(3)
    for k in range(len(xs)):
        x[:] = xs[k]
        nref[:] = nrefs[k]
        status[k] = FIT_NOT_CONVERGED
        for it in range(max_iter):
            st = fit(x, nref, samples, poly, scratch)
            iterations[k] = it + 1
            if st != FIT_OK:
                status[k] = st
                break
            step2 = poly_project(poly, x, y)
            x[:] = y
            if step2 < (tolerance * poly[P_SCALE]) ** 2:
                status[k] = FIT_OUTSIDE if past_edge(poly, samples, scratch) else FIT_OK
                break
        out[k] = x


@numba.njit(cache=True, parallel=True)
def fit_points(samples, polys, status):
    """The polynomial of every sample point, fitted for its own normal (the per-point pre-pass
    of both ray tracers)."""
    n = samples.points.shape[0]
    for block in numba.prange((n + BLOCK - 1) // BLOCK):
        scratch = new_scratch()  # per block of consecutive (nearby) samples: its cache is reused
        for k in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
            status[k] = fit(samples.points[k], samples.normals[k], samples, polys[k], scratch)


@dataclass(frozen=True)
class Projection:
    """Result of `project`: projected points, FIT_* status and iteration count per point."""

    points: np.ndarray
    status: np.ndarray
    iterations: np.ndarray


def project(surface: MLSSurface, xs: np.ndarray, tolerance: float = 1e-4, max_iter: int = 20,
            normals: np.ndarray | None = None) -> Projection:
    """Project points (in the surface's local coordinates) onto the MLS surface: onto the
    sheet facing `normals` (one per point), by default the normal of each point's nearest sample."""
    xs = np.ascontiguousarray(np.atleast_2d(xs), dtype=np.float64)
    if normals is None:
        normals = surface.normals[cKDTree(surface.points).query(xs)[1]]
    nrefs = np.ascontiguousarray(np.broadcast_to(normals, xs.shape), dtype=np.float64)
    out = np.empty_like(xs)
    status = np.empty(len(xs), np.int64)
    iterations = np.zeros(len(xs), np.int64)
    project_points(xs, nrefs, surface.samples, float(tolerance), int(max_iter), out, status, iterations)
    return Projection(out, status, iterations)


def point_polynomials(surface: MLSSurface) -> tuple[np.ndarray, np.ndarray]:
    """(N, POLY_SIZE) polynomial of each sample (in Morton order) and its FIT_* status."""
    n = len(surface.points)
    polys = np.zeros((n, POLY_SIZE))
    status = np.empty(n, np.int64)
    fit_points(surface.samples, polys, status)
    return polys, status
