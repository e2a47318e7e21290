"""Eye-dome lighting (`--shading edl`): shading from the depth buffer alone.

Boucheny 2009, "Interactive scientific visualization of large datasets: towards a
perceptive-based approach" (PhD thesis, Université Joseph Fourier), chapter 4, in the form
Potree and CloudCompare use: each covered sample p compares its log depth with neighbours
q_i(R) at N_DIRECTIONS angles on a circle of R pixels around it, so that the term depends on
neither the scene's scale nor its distance, and darkens where neighbours are nearer. Potree
sums max(0, log2 z(p) - log2 z(q_i)) over the neighbours; a plane seen obliquely, whose log
depth rises steadily across the image, then darkens too (by a fifth at a typical oblique
view of a tile, more at the larger radii below). Here each pair of opposite neighbours is
compared with its mean, which that steady trend cancels, with twice the weight, so that a
step (one neighbour nearer by d, its opposite level with p) reads as in Potree, d:

    response(p, R) = 1/N sum_{i < N/2} max(0, 2 log2 z(p) - log2 z(q_i) - log2 z(q_{i+N/2}))

A pair with an empty end (nothing drawn there) falls back to Potree's one-sided term, and
empty neighbours count for nothing, so a silhouette against the background is not darkened.
z is the eye-space distance along the viewing axis, read bilinearly over covered samples.
CloudCompare shades at three scales, R = r, 2r, 4r, so that the shadow a raised edge casts
is a few pixels wide, not one; their responses are summed with weights 2^(-k/2), which
keeps a band 3 to 5 pixels wide beside a step of 1% of the viewing distance at about half
its brightness (weights 1/2^k would leave it at 0.7):

    edl(p) = exp(-RESPONSE_SCALE * strength * sum_k 2^(-k/2) response(p, 2^k r)),  k = 0..SCALES-1

Flat areas keep edl = 1, oblique or not; a surface just behind a nearer one (the ground
beside a building, a crown's underside) darkens, and a concave crease a little. The `edl`
shading model shows the unlit colour times edl(p) (result.RenderResult.from_samples applies
it to the samples of every method, r in pixels of the output image times the
supersampling). gl/edl.glsl is the GLSL twin the browser page runs; this is the reference.
"""

from __future__ import annotations

import math

import numba
import numpy as np

N_DIRECTIONS = 8
SCALES = 3
RESPONSE_SCALE = 300.0  # Potree's: log2 depth differences are small numbers
DEFAULT_STRENGTH = 1.0
DEFAULT_RADIUS = 1.4    # pixels of the output image (Potree's)


@numba.njit(cache=True)  # no fastmath: it would assume away the NaNs that mark empty texels
def _log_depth_at(log_depth, fx, fy):  # pragma: no cover - compiled
    """Bilinear log depth at continuous texel position (fx, fy) (texel centres on integers),
    over the covered texels only; nan where none is."""
    h, w = log_depth.shape
    x0 = int(math.floor(fx))
    y0 = int(math.floor(fy))
    ax, ay = fx - x0, fy - y0
    total = 0.0
    weight = 0.0
    for dy in range(2):
        for dx in range(2):
            xx, yy = x0 + dx, y0 + dy
            if xx < 0 or yy < 0 or xx >= w or yy >= h:
                continue
            value = log_depth[yy, xx]
            if value != value:  # empty
                continue
            wq = (ax if dx else 1.0 - ax) * (ay if dy else 1.0 - ay)
            total += wq * value
            weight += wq
    return total / weight if weight > 1e-6 else math.nan


@numba.njit(parallel=True, cache=True)
def _edl(depth, radius, strength):  # pragma: no cover - compiled
    h, w = depth.shape
    log_depth = np.full((h, w), np.nan, np.float32)
    for y in numba.prange(h):
        for x in range(w):
            z = depth[y, x]
            if z > 0.0 and z < np.inf:
                log_depth[y, x] = math.log2(z)
    out = np.ones((h, w), np.float32)
    for y in numba.prange(h):
        for x in range(w):
            here = log_depth[y, x]
            if here != here:
                continue
            total = 0.0
            for k in range(SCALES):
                r = radius * 2.0 ** k
                response = 0.0
                for i in range(N_DIRECTIONS // 2):
                    angle = 2.0 * math.pi * i / N_DIRECTIONS
                    dx, dy = r * math.cos(angle), r * math.sin(angle)
                    one = _log_depth_at(log_depth, x + dx, y + dy)
                    other = _log_depth_at(log_depth, x - dx, y - dy)
                    if one == one and other == other:
                        response += max(0.0, 2.0 * here - one - other)
                    elif one == one:
                        response += max(0.0, here - one)
                    elif other == other:
                        response += max(0.0, here - other)
                total += response / N_DIRECTIONS / 2.0 ** (0.5 * k)
            out[y, x] = math.exp(-RESPONSE_SCALE * strength * total)
    return out


def eye_dome_lighting(depth: np.ndarray, radius: float = DEFAULT_RADIUS,
                      strength: float = DEFAULT_STRENGTH) -> np.ndarray:
    """The EDL term (H, W) float32 in (0, 1] of a depth buffer (H, W): eye distance along the
    viewing axis, inf (or 0) where empty; `radius` in pixels of this buffer."""
    return _edl(np.ascontiguousarray(depth, np.float32), float(radius), float(strength))


__all__ = ["eye_dome_lighting", "DEFAULT_RADIUS", "DEFAULT_STRENGTH", "N_DIRECTIONS", "SCALES", "RESPONSE_SCALE"]
