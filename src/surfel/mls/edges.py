"""Where an MLS sheet ends: the edge tests that surface.py's projection and the ray tracer
apply where a projection converges (the GPU caster sums the same tests in gpu.glsl).

A sheet that the normal weight of surface.py separates from its neighbour would run on past the
crease or rim where it ends, so where a projection converges the half-disc test of Bendels,
Schnabel & Klein ("Detecting holes in point set surfaces", 2006) applies too: the mean of the
samples, weighted by a_i exp(-|p_i - r|^2 / l^2 - |n_i - n_r|^2 / sigma_n^2) (a_i the area a
sample stands for: its local spacing m_i of widths.py, squared, relative), may lie at most
`boundary * l` from r across the tangent plane (at the edge of a half-plane it lies
l / sqrt(pi) = 0.56 l away). The areas and the one width l keep a jump in sampling density from
reading as an edge. That bound leaves a sheet running on by a tenth of l or so past its last samples, which a
LiDAR canopy's ragged edge needs and a crease does not; so at a crease a second test cuts the
sheet at its outermost sample. With m the weighted mean of the samples about x (the fit's q - x)
and u = -(m - (m . n) n) the direction away from it along the plane, x lies past the edge of its
sheet when no sample of the sheet (n_i . n > cos 60 degrees) lies beyond x, (p_i - x) . u >= 0,
while a sample of another sheet turning away across the edge lies near the edge or past it,
(p_i - x) . u >= -EDGE_REACH l |u| with n_i . u > cos 60 degrees |u|: the sheet ends there at a
convex crease or a rim (Bendels et al.'s extent criterion). At an open boundary (a LiDAR
canopy's edge, a flat cut-out's outline) the sheet may run on by OPEN_REACH l past its outermost
sample, no further: x lies past the edge when no sample of the sheet lies beyond x or within
that reach behind it, (p_i - x) . u >= -OPEN_REACH l |u|. The half-disc bound alone let a sparse
sheet run on by 0.3 l and more where its outline is densely sampled (a gingerbread figure's
outline spilled by 5 pixels at 512 x 512).

Both tests read the neighbours of the last fit (surface.fit), still in the thread's scratch.
"""

from __future__ import annotations

import math

import numba

from .polynomial import P_N, P_SCALE

EDGE_SHEET_COS = 0.5   # crease test: a sheet's samples have normals within 60 degrees of the fit's
EDGE_TURN_COS = 0.5    # ... another sheet across a crease turns its normals within 60 degrees of u
EDGE_REACH = 0.25      # ... and count from this many l behind x
OPEN_REACH = 0.1       # an open boundary: the sheet runs on at most this many l past its outermost sample


@numba.njit(cache=True, fastmath=True)
def past_edge(poly, samples, scratch):
    """The half-disc test of the last fit (its neighbours still in `scratch`), made where a
    projection converges: past the edge of a sheet the mean of the samples about x, each
    counted for its area under one Gaussian of the local width, lies off to one side of x
    (a jump in sampling density does not: the areas even it out)."""
    nb, area = scratch.nb, samples.area
    inv_l2 = 1.0 / (poly[P_SCALE] * poly[P_SCALE])
    sa = ax = ay = az = 0.0
    for k in range(scratch.found[0]):
        dx, dy, dz = nb[k, 0], nb[k, 1], nb[k, 2]
        # w with the sample's width h_i replaced by l: the normal-agreement factor stays
        wa = area[int(nb[k, 5])] * nb[k, 3] * math.exp((dx * dx + dy * dy + dz * dz) * (1.0 / (nb[k, 4] * nb[k, 4])
                                                                                        - inv_l2))
        sa += wa
        ax += wa * dx
        ay += wa * dy
        az += wa * dz
    ax, ay, az = ax / sa, ay / sa, az / sa
    along = ax * poly[P_N] + ay * poly[P_N + 1] + az * poly[P_N + 2]
    if ax * ax + ay * ay + az * az - along * along > (samples.boundary * poly[P_SCALE]) ** 2:
        return True
    return not sample_beyond(poly, samples, scratch)


@numba.njit(cache=True, fastmath=True)
def sample_beyond(poly, samples, scratch):
    """The crease and open-boundary tests of the last fit (module docstring): False where x
    lies past the outermost sample of its sheet (normals within 60 degrees of the fit's) in the
    direction u away from the weighted mean of the samples about x, while a sample of another
    sheet whose normal turns towards u lies within EDGE_REACH l of x or beyond it along u (the
    sheet has ended at a convex crease or a rim), or while no sample of the sheet lies within
    OPEN_REACH l behind x (an open boundary: the sheet ends there, a little way past its last
    samples)."""
    nb, normals = scratch.nb, samples.normals
    n0, n1, n2 = poly[P_N], poly[P_N + 1], poly[P_N + 2]
    sw = mx = my = mz = 0.0
    for k in range(scratch.found[0]):
        w = nb[k, 3]
        sw += w
        mx += w * nb[k, 0]
        my += w * nb[k, 1]
        mz += w * nb[k, 2]
    along = (mx * n0 + my * n1 + mz * n2)
    ux, uy, uz = along * n0 - mx, along * n1 - my, along * n2 - mz  # -(tangential part of the mean) * sw
    if ux * ux + uy * uy + uz * uz <= (1e-6 * sw * poly[P_SCALE]) ** 2:
        return True  # the mean lies at x: samples all around
    norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    reach = -EDGE_REACH * poly[P_SCALE] * norm
    open_reach = -OPEN_REACH * poly[P_SCALE] * norm
    other = near_edge = False
    for k in range(scratch.found[0]):
        i = int(nb[k, 5])
        out = nb[k, 0] * ux + nb[k, 1] * uy + nb[k, 2] * uz
        if normals[i, 0] * n0 + normals[i, 1] * n1 + normals[i, 2] * n2 > EDGE_SHEET_COS:
            if out >= 0.0:
                return True
            near_edge = near_edge or out >= open_reach
        elif out >= reach and normals[i, 0] * ux + normals[i, 1] * uy + normals[i, 2] * uz > EDGE_TURN_COS * norm:
            other = True
    return near_edge and not other
