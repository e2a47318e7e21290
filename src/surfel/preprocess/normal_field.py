"""Phong splatting's linear normal fields (Botsch, Spernat & Kobbelt 2004; survey eq. 8).

    N_j(u, v) = n_j + u alpha_j û_j + v beta_j v̂_j,

where û_j, v̂_j are the UNIT axis directions and (u, v) = (u_j . (q - c_j) / |u_j|^2,
v_j . (q - c_j) / |v_j|^2) are local coordinates that reach 1 on the ellipse's rim, so alpha and
beta are dimensionless (the tangent of the normal's tilt at the rim). Fitted by weighted least
squares over the FIELD_NEIGHBOURS - 1 nearest neighbours' normals, each slope a 1-D problem
with a closed form: with (u_q, v_q) the neighbour's coordinates, tilt_q = n_q . û_j / (n_q . n_j)
the tangential part of its normal scaled to component 1 along n_j (the model's normal has that
component) and w_q = exp(-(u_q^2 + v_q^2)),

    alpha_j = sum_q w_q u_q tilt_q / sum_q w_q u_q^2,   beta_j alike along v.

The field is only read inside the rim, so the weights, a Gaussian of the splat's own
coordinates (0.37 on the rim), fit it to the normals there, as an MLS fit weights its
neighbours (Alexa et al. 2003): unweighted, the neighbours beyond the rim, which weigh u_q^2,
decided the slope (13 models' mesh vertices, two views each: `phong` median 33.6 -> 34.1 dB,
`deferred`, whose splats the fields curve, 32.6 -> 33.1 dB, the CAD part +0.7 to +1.4 dB).

Fitted are the neighbours on p's own sheet. Not fitted:
  * those across a crease, |n_q . n_j| < ACROSS_COS;
  * the far side of a thin part (a tail, an ear, a lip), as borders.py tells it: facing away,
    n_q . n_j < SHEET_COS, and off p's plane, ((q - p) . n_j)^2 > FLAT_SIN2 |q - p|^2. Taken as
    the same sheet seen from behind, its normals, nearly opposite n_j and so barely tilted at
    small offsets, flattened the field across a tube sampled as rings, whose splats stood out
    as beads along it (13 models' vertices: `phong` median 34.5 -> 35.1 dB, `deferred` 33.5 ->
    33.6 dB, cheburashka +1.8 dB, cow +1.4 dB, teapot -0.5 dB; their raw scans within 0.05 dB).
A neighbour facing away in p's plane is the same surface seen from behind (a shell scanned
from inside and out) and is fitted, its tilt's sign following its normal's.

Two fields are fitted (attributes.FIELD_SLOPES): the one above, phong_alpha and phong_beta,
shades the splats of `phong` and `deferred`; the second, curve_alpha and curve_beta, shapes
their curved splats (splatting.py) and leaves out the rims: the neighbours in p's plane
(within FLAT_SIN2) whose normals lie more than SHARP_ANGLE off, a face's edge vertices with
normals averaged over the face and what meets it. A mesh's shading rounds its edges so, and so
does the first field; but the face itself is flat up to its edge, and a splat bent down towards
it ended short of the edge, a face seen edge-on then a pixel short of its outline (casting.obj
at azimuth 130, elevation -20: holes 0.137 -> 0.056%). `phong` over 13 models' vertices, six
views each at 512 x 512: worst holes 0.137 -> 0.083%, mean PSNR 36.88 -> 36.99 dB (fandisk,
casting.obj, cheburashka, ogre up to +0.6 to +0.9 dB; rocker-arm from above -0.75 dB, the
bunny from above -0.21 dB). On a noisy cloud a normal far off in p's plane is noise, not a
rim: the two fields are the same there (raw scans as before).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..attributes import FIELD_SLOPES
from ..cloud import PointCloud
from ..threads import over_rows
from .chunked import map_chunks
from .frames import unit
from .neighbourhood import Neighbourhood
from .sharp_features import FLAT_SIN2, SHARP_COS, SHEET_COS

FIELD_NEIGHBOURS = 16  # neighbours whose normals fit a splat's normal field
ACROSS_COS = 0.5       # neighbours' normals more than 60 degrees off lie across a crease: not fitted
NO_RIMS = -2.0         # a rim cosine no neighbour's falls below


@numba.njit(cache=True, inline="always")
def _along_axis(points, normals, axes, i, p, q, t, along):  # pragma: no cover - compiled
    """Neighbour q's coordinate along splat p's axis t (1 on the ellipse's rim) and the tilt of
    its normal along that axis's unit direction, scaled to component 1 along n_p; (0, 0) for a
    zero axis."""
    length2 = 0.0
    offset = 0.0
    tilt = 0.0
    for a in range(3):
        axis = axes[i, t, a]
        length2 += axis * axis
        offset += (points[q, a] - points[p, a]) * axis
        tilt += normals[q, a] * axis
    if length2 == 0.0:
        return 0.0, 0.0
    return offset / length2, tilt / (math.sqrt(length2) * along)


@numba.njit(cache=True, inline="always")
def _off_plane(points, normals, p, q, flat_sin2):  # pragma: no cover - compiled
    """Whether neighbour q lies off p's tangent plane: ((q - p) . n_p)^2 > flat_sin2 |q - p|^2."""
    height = 0.0
    distance2 = 0.0
    for a in range(3):
        offset = points[q, a] - points[p, a]
        height += offset * normals[p, a]
        distance2 += offset * offset
    return height * height > flat_sin2 * distance2


def _slopes(points, index, start, normals, axes, sheet_cos, flat_sin2, rim_cos):
    """Weighted least-squares slopes (m, 4) of each splat start + i over its neighbours on its
    own sheet (module docstring: sheet_cos, flat_sin2 tell the far side of a thin part): the
    shading field's (alpha, beta), then the surface's, without the neighbours in p's plane whose
    normals lie more than acos(rim_cos) off."""
    m = len(index)
    slopes = np.zeros((m, 4))
    over_rows(_slopes_rows, m, points, index, start, normals, axes, sheet_cos, flat_sin2, rim_cos, slopes)
    return slopes


@numba.njit(cache=True, nogil=True)
def _slopes_rows(first, stop, points, index, start, normals, axes, sheet_cos, flat_sin2, rim_cos,
                 slopes):  # pragma: no cover - compiled
    """Rows first:stop of `_slopes`."""
    k = index.shape[1]
    sums = np.empty(10)  # (u t_u, u^2, v t_v, v^2, weights) for the shading field, then the surface's
    for i in range(first, stop):
        p = start + i
        sums[:] = 0.0
        for j in range(k):
            q = index[i, j]
            if q == p:
                continue
            along = 0.0
            for a in range(3):
                along += normals[q, a] * normals[p, a]
            # Neighbours across a crease or on the far side of a thin part would only bend the fit
            if abs(along) < ACROSS_COS or (along < sheet_cos and _off_plane(points, normals, p, q, flat_sin2)):
                continue
            u, tilt_u = _along_axis(points, normals, axes, i, p, q, 0, along)
            v, tilt_v = _along_axis(points, normals, axes, i, p, q, 1, along)
            weight = math.exp(-(u * u + v * v))
            # a rim point in p's plane: its normal, averaged over the face and what meets it, tilts
            # the shading as a mesh's does, but the face itself is flat up to it
            rim = along < rim_cos and not _off_plane(points, normals, p, q, flat_sin2)
            for fit in range(1 if rim else 2):
                sums[5 * fit] += weight * u * tilt_u
                sums[5 * fit + 1] += weight * u * u
                sums[5 * fit + 2] += weight * v * tilt_v
                sums[5 * fit + 3] += weight * v * v
                sums[5 * fit + 4] += weight
        for fit in range(2):
            # no slope where the neighbours barely spread along the axis (their weighted mean u^2)
            if sums[5 * fit + 1] > 1e-12 * sums[5 * fit + 4]:
                slopes[i, 2 * fit] = sums[5 * fit] / sums[5 * fit + 1]
            if sums[5 * fit + 3] > 1e-12 * sums[5 * fit + 4]:
                slopes[i, 2 * fit + 1] = sums[5 * fit + 2] / sums[5 * fit + 3]


def field_slopes(nbh: Neighbourhood, normals: np.ndarray, axes: np.ndarray, progress: bool | None,
                 k: int = FIELD_NEIGHBOURS, rims: bool = True) -> np.ndarray:
    """Slopes (N, 4) float32 of the splats (normals, axes) in the neighbourhood's order: the
    shading field's (alpha, beta) and the surface's, which leaves out the rims (module
    docstring) unless `rims` is false (normals estimated on a noisy cloud: a neighbour's normal
    far off in p's plane is its noise), when the two are the same."""
    index = nbh.first(k)
    normals = unit(normals)

    def chunk(start: int, stop: int) -> np.ndarray:
        axes_chunk = np.asarray(axes[start:stop], np.float64)
        return _slopes(nbh.points, index[start:stop], start, normals, axes_chunk, SHEET_COS,
                       FLAT_SIN2, SHARP_COS if rims else NO_RIMS).astype(np.float32)

    return map_chunks(chunk, len(nbh.points), progress, "normal field")


def fit_normal_field(positions: np.ndarray, normals: np.ndarray, axes: np.ndarray, k: int = FIELD_NEIGHBOURS,
                     workers: int = -1, progress: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Phong splatting's linear normal field (alpha, beta), each (N,) float32:
    N_j(u, v) = n_j + u alpha_j û_j + v beta_j v̂_j with unit axis directions û_j, v̂_j and
    (u, v) in semi-axis units, weighted least squares over the k - 1 nearest neighbours' normals
    (module docstring)."""
    nbh = Neighbourhood.build(positions, k, workers, progress)
    slopes = nbh.unsort(field_slopes(nbh, nbh.sort(normals), nbh.sort(axes), progress, k))
    return slopes[:, 0].copy(), slopes[:, 1].copy()


def has_normal_field(cloud: PointCloud) -> bool:
    """Whether the cloud carries a normal field: at least the shading field's slopes."""
    return {"phong_alpha", "phong_beta"} <= cloud.attributes.keys()


def splat_slopes(cloud: PointCloud, start: int = 0, stop: int | None = None) -> np.ndarray | None:
    """(n, 4) float32 normal-field slopes of points start:stop as the renderers take them, in
    FIELD_SLOPES order: the shading field's, then the surface's, which a cloud fitted without
    them (by an earlier surfel) takes from the shading field; None without a normal field."""
    if not has_normal_field(cloud):
        return None
    a = cloud.attributes
    keys = FIELD_SLOPES if {"curve_alpha", "curve_beta"} <= a.keys() else FIELD_SLOPES[:2] * 2
    return np.stack([a[key][start:stop] for key in keys], 1).astype(np.float32)
