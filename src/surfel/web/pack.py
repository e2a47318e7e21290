"""The page's point data: every per-point column quantized, laid end to end in one blob.

Positions: 16 bits per axis over the bounding box (relative to the cloud's local origin), so
a position is off by at most half a step, extent / 131070. Normals: octahedral (Meyer et al.
2010, "On floating-point normal vectors"; Cigolle et al. 2014, "A survey of efficient
representations for independent unit vectors"), n -> (x, y) / (|x| + |y| + |z|) with the
lower hemisphere folded over the diagonals, 16 bits per component. Ellipses (axis_u, axis_v):
the semi-axis lengths as half floats in units of the bounding box's longest side or the
largest splat's radius, whichever is longer (11 bits of precision whatever the data's units,
and in range even for coincident points, whose box has no extent), and axis_u's angle phi in
the tangent frame (t1, t2) of the decoded normal (Duff et al. 2017, "Building an orthonormal
basis, revisited"):

    s = sign(n_z), a = -1 / (s + n_z), b = n_x n_y a
    t1 = (1 + s n_x^2 a, s b, -s n_x),   t2 = (b, s + n_y^2 a, -n_y)
    axis_u = |u| (cos phi t1 + sin phi t2),   axis_v = |v| (cos phi t2 - sin phi t1)

(web/splat_attributes.glsl decodes the same way). Where the cloud's axis_v points the other
way, the clip lines' v coefficients change sign instead, so that splats still end where they
did. A splat that faces the camera (surfel.preprocess.structure) has its first radius negated:
the page gives it the zero normal the desktop's splat buffers give it. Normal-field slopes
(alpha, beta; `phong` and `deferred` curve their splats by them) are half floats, and so are
the layers' thicknesses (z_t's cap, surfel.preprocess.thickness) in the length unit, rounded down.
Sequential point tree errors (e_g, the parent's e_g, the distance to the parent) are half
floats in the same unit, rounded outwards (e_g down, the others up), so the page's vertex test
passes a superset of surfel.lod's selection: overlaps, never holes. Attributes: 16-bit codes
(categorical) or 16-bit steps over their range (continuous).
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from ..preprocess import facing_mask, splat_slopes, splat_thickness

POSITION_STEPS = 65535
LOD_SEARCH_STRIDE = 64  # the CPU's prefix search reads every 64th node's bounds


def oct_encode(normals: np.ndarray) -> np.ndarray:
    """Unit vectors (N, 3) to octahedral uint16 pairs (N, 2)."""
    n = np.asarray(normals, np.float64)
    p = n[:, :2] / np.abs(n).sum(axis=1, keepdims=True)
    lower = n[:, 2] < 0
    folded = (1 - np.abs(p[:, ::-1])) * np.where(p >= 0, 1.0, -1.0)
    p[lower] = folded[lower]
    return np.round((p * 0.5 + 0.5) * 65535).astype(np.uint16)


def oct_decode(codes: np.ndarray) -> np.ndarray:
    """The page's decoding of oct_encode, float64 unit vectors (N, 3)."""
    e = codes.astype(np.float64) / 65535 * 2 - 1
    n = np.stack([e[:, 0], e[:, 1], 1 - np.abs(e[:, 0]) - np.abs(e[:, 1])], axis=1)
    t = np.maximum(-n[:, 2], 0)
    n[:, :2] -= np.where(n[:, :2] >= 0, 1.0, -1.0) * t[:, None]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def tangent_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Duff et al.'s orthonormal tangents (t1, t2) of unit normals (N, 3)."""
    s = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1 / (s + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1 + s * n[:, 0] ** 2 * a, s * b, -s * n[:, 0]], axis=1)
    t2 = np.stack([b, s + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t1, t2


def half_outwards(values: np.ndarray, direction: float) -> np.ndarray:
    """float32 values as float16, rounded towards +inf (direction > 0) or -inf."""
    values = np.asarray(values, np.float32)
    with np.errstate(over="ignore"):  # beyond float16: inf, which the tests treat as FLT_MAX
        half = values.astype(np.float16)
    wrong = half.astype(np.float32) < values if direction > 0 else half.astype(np.float32) > values
    half[wrong] = np.nextafter(half[wrong], np.float16(np.inf if direction > 0 else -np.inf))
    return half


def bucket_ceilings(emax: np.ndarray) -> np.ndarray:
    """surfel.lod.sequential's r_max bucket ceilings: lod_emax rounded up to 8 mantissa bits."""
    from ..lod.sequential import BUCKET_SHIFT, r_max_bucket

    return (r_max_bucket(emax).astype(np.uint32) << BUCKET_SHIFT).view(np.float32)


def pack_cloud(cloud: PointCloud, values: dict[str, np.ndarray]) -> tuple[dict, bytes]:
    """Quantize a completed cloud (normals and axes present) and its colour-mode `values`
    (name -> uint16 per point). Returns (layout, blob): layout names each column's dtype,
    width, byte offset and length in blob, plus the bounding box and the LOD search table."""
    origin = cloud.local_origin
    local = cloud.positions - origin
    lo, hi = local.min(axis=0), local.max(axis=0)
    size = np.maximum(hi - lo, 1e-30)
    columns: dict[str, np.ndarray] = {
        "position": np.round((local - lo) / size * POSITION_STEPS).astype(np.uint16)}
    normal_codes = oct_encode(cloud.normals)
    columns["normal"] = normal_codes
    normals = oct_decode(normal_codes)
    t1, t2 = tangent_frame(normals)
    u = cloud.axes[:, 0].astype(np.float64)
    v = cloud.axes[:, 1].astype(np.float64)
    phi = np.arctan2(np.einsum("ij,ij->i", u, t2), np.einsum("ij,ij->i", u, t1))
    columns["angle"] = np.round(np.mod(phi / (2 * np.pi), 1.0) * 65535).astype(np.uint16)
    unit = float(max((hi - lo).max(), cloud.max_splat_radius, 1e-30))
    lengths = np.stack([np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)], axis=1)
    facing = facing_mask(cloud)
    if facing is not None:  # the flag of a splat that faces the camera: a negative first radius
        lengths[facing, 0] *= -1
    columns["radii"] = (lengths / unit).astype(np.float16)
    if cloud.colors is not None:
        columns["color"] = np.round(cloud.colors * 255).astype(np.uint8)
    slopes = splat_slopes(cloud)
    if slopes is not None:  # dimensionless slopes, which a flipped axis_v leaves as they are
        columns["field"] = slopes.astype(np.float16)
    if "clip_lines" in cloud.attributes:
        v_decoded = np.cos(phi)[:, None] * t2 - np.sin(phi)[:, None] * t1
        flip = np.einsum("ij,ij->i", v, v_decoded) < 0
        lines = cloud.attributes["clip_lines"].astype(np.float32).copy()
        lines[flip, :, 1] *= -1
        columns["clip"] = lines.reshape(len(cloud), 6).astype(np.float16)
    thickness = splat_thickness(cloud)
    if thickness.any():  # z_t's cap where layers lie close, rounded down: never past the next layer
        columns["thickness"] = half_outwards(thickness / unit, -1)
    layout: dict = {"count": len(cloud), "box_lo": lo.tolist(), "box_size": size.tolist(), "origin": origin.tolist(),
                    "max_radius": cloud.max_splat_radius, "length_unit": unit}
    if "lod_emax" in cloud.attributes:
        a = cloud.attributes
        columns["lod"] = np.stack([half_outwards(a["lod_emin"] / unit, -1), half_outwards(a["lod_emax"] / unit, 1),
                                   half_outwards(a["lod_dparent"] / unit, 1)], axis=1)
        sample = np.arange(0, len(cloud), LOD_SEARCH_STRIDE)
        ceiling = bucket_ceilings(a["lod_emax"][sample])
        layout["lod_search"] = {"stride": LOD_SEARCH_STRIDE,
                                "bound": np.minimum(ceiling, np.finfo(np.float32).max).astype(float).tolist(),
                                "dsuffix": a["lod_dsuffix"][sample].astype(float).tolist()}
    for name, codes in values.items():
        columns[f"value:{name}"] = codes
    blob = bytearray()
    layout["columns"] = {}
    for name, array in columns.items():
        array = np.ascontiguousarray(array)
        blob += b"\0" * (-len(blob) % 4)
        layout["columns"][name] = {"dtype": array.dtype.str.lstrip("<|"), "offset": len(blob), "bytes": array.nbytes,
                                   "width": 1 if array.ndim == 1 else array.shape[1]}
        blob += array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes()
    return layout, bytes(blob)
