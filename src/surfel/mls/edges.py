"""Where an MLS sheet ends: the edge tests that surface.py's projection and the ray tracer
apply where a projection converges (the GPU caster sums the same tests in gpu.glsl).

A sheet that the normal weight of surface.py separates from its neighbour would run on past the
crease or rim where it ends, so where a projection converges the half-disc test of Bendels,
Schnabel & Klein ("Detecting holes in point set surfaces", 2006) applies too: the mean of the
samples, weighted by a_i exp(-|p_i - r|^2 / l^2 - |n_i - n_r|^2 / sigma_n^2) (a_i the area a
sample stands for: its spacing s_i of widths.py squared, or h_i^2 = (h_scale s_i)^2, the same
weights up to a factor that the mean divides out), may lie at most
`boundary * l` from r across the tangent plane (at the edge of a half-plane it lies
l / sqrt(pi) = 0.56 l away). The areas and the one width l keep a jump in sampling density from
reading as an edge. That bound lets a sheet run on past its last samples by a tenth of l or
so, by 0.3 l and more where a sparse sheet's outline is densely sampled (a gingerbread
figure's outline spilled by 5 pixels at 512 x 512), and rounds a crease's rim; so a second
test, Bendels et al.'s extent criterion, ends the sheet at its outermost sample. With m the
weighted mean of the samples about x (the fit's q - x) and u = -(m - (m . n) n) the direction
away from it along the plane, x lies past the edge of its sheet when no sample of the sheet
(n_i . n > cos 60 degrees) lies beyond x, (p_i - x) . u >= 0, within one local width l of the
line x + s u: at a convex crease, where the other sheet turns away, and at an open boundary (a
LiDAR canopy's ragged edge, a flat cut-out's outline) alike. The line keeps a concave corner
of an outline open: in the empty quadrant of an L the samples of both arms lie forward of x,
off to either side of the line, and counting them filled the corner in a wedge (woody's neck
and armpits; woody and alligator, flat cut-outs at 512 x 512, front and oblique, gained 3-4 dB,
cheburashka and nefertiti up to 1 dB, the others moved within 0.2 dB; a width of 0.75 l
opened holes in rocker-arm's coarse sampling).
A gap between two parallel edges stays filled: u points across it at the far edge's samples.
Letting an open boundary run on by a tenth of l past its last sample cost flat cut-outs 0.8 dB
(closed models within 0.03 dB).

The area is s_i squared, not the local spacing m_i squared: a sample on a row of samples close
together, with the next row far off, stands for the strip between the rows, which s_i measures
(its tangent gap) and m_i does not. Where a car body's sparse rows meet the dense lip of its
sill at a crease (beetle-alt), the last sparse row's samples have their nearest neighbours on
the lip; weighed by m_i squared they counted a tenth of the rows above them, the mean moved
up, and the band between the two rows read as past the edge of both sheets (0.56% holes at
512 x 512, oblique; 0.02% weighed by s_i squared, +4.6 dB; the other models' vertices and raw
scans within 0.1 dB but ogre's, +1 and +2 dB).

Both tests read the neighbours of the last fit (surface.fit), still in the thread's scratch.
"""

from __future__ import annotations

import math

import numba

from .polynomial import P_N, P_SCALE

EDGE_SHEET_COS = 0.5   # extent test: a sheet's samples have normals within 60 degrees of the fit's
EDGE_LATERAL = 1.0     # ... and lie within this many local widths l of the line from x along u


@numba.njit(cache=True, fastmath=True)
def past_edge(poly, samples, scratch):
    """The half-disc test of the last fit (its neighbours still in `scratch`), made where a
    projection converges: past the edge of a sheet the mean of the samples about x, each
    counted for its area under one Gaussian of the local width, lies off to one side of x
    (a jump in sampling density does not: the areas even it out)."""
    nb = scratch.nb
    inv_l2 = 1.0 / (poly[P_SCALE] * poly[P_SCALE])
    sa = ax = ay = az = 0.0
    for k in range(scratch.found[0]):
        dx, dy, dz = nb[k, 0], nb[k, 1], nb[k, 2]
        # the area h_i^2 times w with the sample's width h_i replaced by l: the normal-agreement
        # factor stays
        hi2 = nb[k, 4] * nb[k, 4]
        wa = hi2 * nb[k, 3] * math.exp((dx * dx + dy * dy + dz * dz) * (1.0 / hi2 - inv_l2))
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
    """The extent test of the last fit (module docstring): whether a sample of x's sheet
    (normal within 60 degrees of the fit's) lies beyond x in the direction u away from the
    weighted mean of the samples about x, within EDGE_LATERAL l of the line x + s u, or that
    mean lies at x (samples all around)."""
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
    inv_u = 1.0 / math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux * inv_u, uy * inv_u, uz * inv_u
    lateral2 = (EDGE_LATERAL * poly[P_SCALE]) ** 2
    for k in range(scratch.found[0]):
        i = int(nb[k, 5])
        dx, dy, dz = nb[k, 0], nb[k, 1], nb[k, 2]
        forward = dx * ux + dy * uy + dz * uz
        across = dx * n0 + dy * n1 + dz * n2
        if (normals[i, 0] * n0 + normals[i, 1] * n1 + normals[i, 2] * n2 > EDGE_SHEET_COS and forward >= 0.0
                and dx * dx + dy * dy + dz * dz - forward * forward - across * across <= lateral2):
            return True
    return False
