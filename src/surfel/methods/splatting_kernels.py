"""Numba kernels of the CPU backends of `gaussian`, `deferred` and `phong` (splatting_cpu.py
states the equations; splatting.glsl is the GPU program they reproduce).

1. binning (splatting_bins.py): each splat's pixel box, and per TILE x TILE screen tile
   the list of the splats that meet it, in draw order.
2. `rasterize_tiles` (parallel over tiles): each tile owns its pixels, so threads never write
   the same memory. A tile copies its splats' packed inputs (one column of 16 values each) into its
   thread's tables (splatting_tiles.py), those facing the camera into one, the others into a
   second; then, table by table:
   - setup (`_setup_tile`, SIMD over a table block): what the vertex shader computes, once per
     splat: the eye-space splat, its back-face flip, the EWA weight, and the coefficients
     that make every per-pixel quantity of the fragment shader a ratio of affine functions of
     the pixel offset (dx, dy) from the splat's projected centre;
   - the visibility pass (MIN of depth + z_t, MAX of coverage), splatting_tiles.py: first of
     the splats facing the camera; then of those seen from their backs, which are copied only
     where they leave a pixel to change (`_hidden`): on a closed surface the far side is
     passed by, which the depth test would discard fragment by fragment (the bunny's 35k
     splats at 1024x1024, `deferred`: about 28 ms a frame against 33);
   - the attribute pass (sums of w rgb, w, w n, w z of the fragments not behind it), of both;
   - normalization, the colour mode and deferred shading straight into the output images.
3. `finish_surrounded` (parallel over rows): whether a pixel is `surrounded` needs its four
   neighbours; a tile decides it for its own pixels and leaves to this pass the few on its
   border whose neighbour lies in another tile.

Colour modes (surfel.colors): a continuous attribute is splatted as its encoded colour and
mapped through the colour map per pixel in `_normalize` (per splat, before shading, for
`gaussian`); in a categorical one the pixel shows the palette entry of its heaviest splat
(splatting_tiles.attribute_tile), shaded per pixel, never a blend.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..colors import continuous_pixel
from ..shading import shade_pixel
from ..threads import IMAGE_GRAIN, over_rows
from .ewa_kernels import FAR, TILE, layer_offset
from .splatting_bins import camera_scalars, eye_space, rotate, to_pixels
from .splatting_tiles import (
    A1X,
    A1Y,
    A10,
    B1X,
    B1Y,
    B10,
    BLOCK,
    C0A,
    C0B,
    C0C,
    C1A,
    C1B,
    C1C,
    CURVE_VALUES,
    CZ,
    EA0,
    EA1,
    EALPHA,
    EB0,
    EB1,
    EBETA,
    EC0,
    EC1,
    ECURVE_ALPHA,
    ECURVE_BETA,
    EX,
    EY,
    EZ,
    FLAT_FIELD,
    FT,
    FUX,
    FUY,
    FUZ,
    FVX,
    FVY,
    FVZ,
    KU,
    KV,
    LU,
    LV,
    MX,
    MY,
    NO_LOWPASS,
    NX,
    NY,
    NZ,
    PACKED,
    PB,
    PG,
    PNX,
    PNY,
    PNZ,
    PR,
    PT,
    PUX,
    PUY,
    PUZ,
    PVX,
    PVY,
    PVZ,
    PX,
    PY,
    PZ,
    RAD,
    ROW,
    STRIDE,
    TABLE_ROWS,
    TEMP,
    U0,
    UX,
    UY,
    V0,
    VX,
    VY,
    W0,
    WT,
    WX,
    WY,
    Z0,
    ZT,
    ZX,
    ZY,
    B,
    G,
    R,
    attributes_of_splats,
    face_camera,
    table_slot,
    visible_splats,
)

COLOR_RGB, COLOR_CONTINUOUS, COLOR_CATEGORICAL = 0, 1, 2  # gl/colors.glsl's colour modes
BACK_SPLAT_WEIGHT = np.float32(1.0 / 256.0)  # splatting.glsl's: a back-facing splat's weight beside front ones
BACK_SPLAT_BEHIND = np.float32(1.0)  # splatting.glsl's: radii a back splat's visibility depth lies further back
FULL_FOOTPRINT_AXIS = 0.5  # splatting.glsl's: pixels of semi-major axis below which a splat's footprint is whole
# A pixel counts as reached by splats when one covers its centre: coverage at least HALF (its
# edge distance >= 0). The low-pass's weight alone reaches a pixel beyond an outline.
HALF = np.float32(0.5)
COVERED, UNDECIDED = 1, 2  # the bits of `present`: reached, as above; left to `finish_surrounded`
MAX_RIM_TILT = np.float32(1.0)  # splatting.glsl's: a curved splat's field turns by at most this at its rim


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _reach(e, curved, radius_scale):
    """splatting.glsl's reach of a curved splat with extras e, drawn radius_scale times its
    size: the divisors of its axes u and v that end it where its surface (the field that shapes
    it) has turned by MAX_RIM_TILT (1 where it turns less, or is flat)."""
    one = np.float32(1.0)
    return (max(abs(e[ECURVE_ALPHA]) * radius_scale / MAX_RIM_TILT, one) if curved else one,
            max(abs(e[ECURVE_BETA]) * radius_scale / MAX_RIM_TILT, one) if curved else one)


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _line_within_reach(a, b, c, reach_u, reach_v):
    """splatting.glsl line_within_reach: the clip line a u + b v <= c (unit (a, b)) in the
    coordinates of the axes divided by (reach_u, reach_v), unit again."""
    a, b = a / reach_u, b / reach_v
    norm = math.sqrt(a * a + b * b)
    inv = np.float32(1.0) / norm if norm > 0 else np.float32(1.0)
    return a * inv, b * inv, c * inv


@nb.njit(forceinline=True, fastmath=True, error_model="numpy")
def _setup(p, e, m, radius_scale, lowpass2, depth_offset, ewa_filter, curved, back_light, reach_u, reach_v):
    """The record of one splat from its staged inputs p (PACKED values) and extras e (EXTRAS
    values), without branches (the vertex stage of splatting.glsl): (record values MX..NZ, field
    values KU..EZ). `back_light`: a back-facing splat weighs BACK_SPLAT_WEIGHT (the methods
    that blend normals, not shaded colours). (reach_u, reach_v): `_reach` of its extras."""
    one, zero, tiny = np.float32(1.0), np.float32(0.0), np.float32(1e-30)
    fx, fy, cx, cy, ortho, near = m[12], m[13], m[14], m[15], m[16], m[17]
    ex, ey, ez = eye_space(m, p[PX], p[PY], p[PZ])
    nx, ny, nz = rotate(m, p[PNX], p[PNY], p[PNZ])
    scale_u, scale_v = radius_scale / reach_u, radius_scale / reach_v
    ux, uy, uz = rotate(m, p[PUX] * scale_u, p[PUY] * scale_u, p[PUZ] * scale_u)
    vx, vy, vz = rotate(m, p[PVX] * scale_v, p[PVY] * scale_v, p[PVZ] * scale_v)
    nx, ny, nz, ux, uy, uz, vx, vy, vz = face_camera(ex, ey, ez, nx, ny, nz, ux, uy, uz, vx, vy, vz, ortho)
    inv_n = one / max(math.sqrt(nx * nx + ny * ny + nz * nz), tiny)
    facing = nz if ortho > 0 else -(nx * ex + ny * ey + nz * ez)
    flip = -one if facing < 0 else one  # every method shows the side that faces the camera
    nx, ny, nz = nx * inv_n * flip, ny * inv_n * flip, nz * inv_n * flip
    lu, lv = math.sqrt(ux * ux + uy * uy + uz * uz), math.sqrt(vx * vx + vy * vy + vz * vz)
    depth = -ez
    perspective = ortho <= 0
    # z_t, capped by the layer's thickness along the ray (gl/common.glsl layer_offset)
    to_eye = one / max(math.sqrt(ex * ex + ey * ey + ez * ez), tiny)
    offset = depth_offset + (BACK_SPLAT_BEHIND if back_light and flip < 0 else zero)  # splatting.glsl's
    zt = layer_offset(offset * max(lu, lv), p[PT], abs(facing) * inv_n * (one if not perspective else to_eye))
    # a corner of the bounding square behind the near plane: the GPU's quad covers the whole
    # viewport and its EWA weight is 1
    crosses_near = perspective and (depth - abs(uz) - abs(vz) < near)
    behind_eye = perspective and depth <= 1e-30  # no projected centre: use the principal point
    mx, my = to_pixels(ex, ey, ez, m)
    mx, my = (cx if behind_eye else mx), (cy if behind_eye else my)
    # EWA's normalization: the resampling kernel's amplitude relative to the reconstruction
    # kernel, sqrt(det S / det(S + r^2 I)), S = J Jᵀ of the projected splat
    jux, juy = to_pixels(ex + ux, ey + uy, ez + uz, m)
    jvx, jvy = to_pixels(ex + vx, ey + vy, ez + vz, m)
    jux, juy, jvx, jvy = jux - mx, juy - my, jvx - mx, jvy - my
    det = jux * jvy - juy * jvx
    det_s = det * det
    trace_s = jux * jux + juy * juy + jvx * jvx + jvy * jvy
    weight = math.sqrt(det_s / max(det_s + lowpass2 * trace_s + lowpass2 * lowpass2, tiny))
    # the low-pass's pixel-wide footprint, whole for a sub-pixel splat, none past a pixel more
    # (splatting.glsl footprint_edge): S's larger eigenvalue is the squared semi-major axis
    major = math.sqrt(np.float32(0.5) * (trace_s + math.sqrt(max(trace_s * trace_s - np.float32(4.0) * det_s, zero))))
    footprint = zero if crosses_near else min(max(np.float32(FULL_FOOTPRINT_AXIS + 1.0) - major, zero), one)
    weight = weight if ewa_filter and not crosses_near else one
    # Two-sided splats (splatting.glsl): where a closed surface's outline blends front and
    # back splats, a back one's normal, turned to the camera, would brighten the rim; it
    # weighs BACK_SPLAT_WEIGHT there, fully where it alone covers a pixel (the normalization)
    weight = weight * (BACK_SPLAT_WEIGHT if back_light and flip < 0 else one)
    # The ray through the pixel at offset (dx, dy): d = d_ref + (dx / fx, -dy / fy, 0) from the eye
    # (perspective), or o = o_ref + (dx, -dy) / ortho along (0, 0, -1). With W = d.n it meets the
    # plane at eye depth ((c - o).n) / W and local coordinates u = ((q - c).u_j) / |u_j|^2.
    iu, iv = one / max(lu * lu, tiny), one / max(lv * lv, tiny)
    aux, auy, auz = ux * iu, uy * iu, uz * iu  # u_j / |u_j|^2
    avx, avy, avz = vx * iv, vy * iv, vz * iv
    inv_fx, inv_fy, inv_o = one / fx, one / fy, one / max(ortho, tiny)
    safe_depth = max(depth, tiny)
    rx = (mx - cx) * inv_fx if behind_eye else ex / safe_depth
    ry = (cy - my) * inv_fy if behind_eye else ey / safe_depth
    rz = -one
    cn = ex * nx + ey * ny + ez * nz
    cu, cv = ex * aux + ey * auy + ez * auz, ex * avx + ey * avy + ez * avz
    # u W = d.(c.n u_j/|u_j|^2 - c.u_j/|u_j|^2 n): zero on the centre's own ray
    gx, gy, gz = cn * aux - cu * nx, cn * auy - cu * ny, cn * auz - cu * nz
    hx, hy, hz = cn * avx - cv * nx, cn * avy - cv * ny, cn * avz - cv * nz
    u0 = rx * gx + ry * gy + rz * gz if behind_eye else zero
    v0 = rx * hx + ry * hy + rz * hz if behind_eye else zero
    w_ortho = -nz
    record = (mx, my,
              w_ortho if not perspective else rx * nx + ry * ny + rz * nz,
              zero if not perspective else nx * inv_fx,
              zero if not perspective else -ny * inv_fy,
              ez * nz if not perspective else cn,
              -nx * inv_o if not perspective else zero,
              ny * inv_o if not perspective else zero,
              zero if not perspective else u0,
              (aux * w_ortho + nx * auz) * inv_o if not perspective else gx * inv_fx,
              -(auy * w_ortho + ny * auz) * inv_o if not perspective else -gy * inv_fy,
              zero if not perspective else v0,
              (avx * w_ortho + nx * avz) * inv_o if not perspective else hx * inv_fx,
              -(avy * w_ortho + ny * avz) * inv_o if not perspective else -hy * inv_fy,
              depth, max(lu, lv), weight, zt, footprint, p[PR], p[PG], p[PB], nx, ny, nz)
    field = FLAT_FIELD
    if curved:
        # the fields' tilts at the drawn rim, radius_scale times as far as the fitted one
        turn_u, turn_v = flip * radius_scale / reach_u, flip * radius_scale / reach_v
        alpha, beta = e[EALPHA] * turn_u, e[EBETA] * turn_v  # the shading's
        bend_u, bend_v = e[ECURVE_ALPHA] * turn_u, e[ECURVE_BETA] * turn_v  # the surface's
        ilu, ilv = one / max(lu, tiny), one / max(lv, tiny)
        eux, euy, euz = ux * ilu, uy * ilu, uz * ilu
        evx, evy, evz = vx * ilv, vy * ilv, vz * ilv
        field = (bend_u * ilu, bend_v * ilv, lu, lv,
                 -euz if not perspective else rx * eux + ry * euy + rz * euz,
                 zero if not perspective else eux * inv_fx,
                 zero if not perspective else -euy * inv_fy,
                 -evz if not perspective else rx * evx + ry * evy + rz * evz,
                 zero if not perspective else evx * inv_fx,
                 zero if not perspective else -evy * inv_fy,
                 alpha * eux, alpha * euy, alpha * euz, beta * evx, beta * evy, beta * evz,
                 zero if not perspective else -ex * to_eye,
                 zero if not perspective else -ey * to_eye,
                 one if not perspective else -ez * to_eye)
    return record, field


@nb.njit(inline="always")
def _staged(table, j):
    """The staged inputs of the splat at table slot j: (PACKED values, EXTRAS values)."""
    p = (table[j + ROW[PX]], table[j + ROW[PY]], table[j + ROW[PZ]], table[j + ROW[PNX]], table[j + ROW[PNY]],
         table[j + ROW[PNZ]], table[j + ROW[PUX]], table[j + ROW[PUY]], table[j + ROW[PUZ]], table[j + ROW[PVX]],
         table[j + ROW[PVY]], table[j + ROW[PVZ]], table[j + ROW[PR]], table[j + ROW[PG]], table[j + ROW[PB]],
         table[j + ROW[PT]])
    e = (table[j + ROW[PACKED + EA0]], table[j + ROW[PACKED + EB0]], table[j + ROW[PACKED + EC0]],
         table[j + ROW[PACKED + EA1]], table[j + ROW[PACKED + EB1]], table[j + ROW[PACKED + EC1]],
         table[j + ROW[PACKED + EALPHA]], table[j + ROW[PACKED + EBETA]], table[j + ROW[PACKED + ECURVE_ALPHA]],
         table[j + ROW[PACKED + ECURVE_BETA]])
    return p, e


@nb.njit(inline="always")
def _stage(table, ibox, slot, i, packed, staged_rows, extras, box, clip_src, field_src):
    """Copy splat i's packed column, the extras the kernel reads and its box into table slot `slot`."""
    j, jb = table_slot(slot, TABLE_ROWS), table_slot(slot, 4)
    for row in range(staged_rows.shape[0]):
        col = np.uint64(staged_rows[row])
        table[j + col * np.uint64(BLOCK)] = packed[col, i]
    if clip_src is not None:  # only the extras this kernel reads
        for col in range(EA0, EC1 + 1):
            table[j + np.uint64((PACKED + col) * BLOCK)] = extras[np.uint64(col), i]
    if field_src is not None:  # the shading's slopes and the surface's, which shape it
        for col in range(EALPHA, ECURVE_BETA + 1):
            table[j + np.uint64((PACKED + col) * BLOCK)] = extras[np.uint64(col), i]
    for col in range(4):
        ibox[jb + np.uint64(col * BLOCK)] = box[np.uint64(col), i]


@nb.njit(inline="always")
def _hidden(box, i, ox, oy, tw, th, nearest, zb, cov):
    """Whether splat i can change nothing in the tile at (ox, oy) of tw x th pixels, drawn after
    the splats whose visibility pass made zb and cov: every pixel of its box in the tile has a
    visibility depth in front of `nearest`, so none of its fragments passes the visibility pass
    or the attribute pass; and a coverage that no fragment of it can change the pixel's alpha
    with: 1, or at least HALF with its four neighbours (in the tile) at least HALF too, which
    makes the pixel whole whatever its own coverage (the `surrounded` test below)."""
    x0, x1 = max(box[0, i] - ox, 0), min(box[1, i] - ox, tw - 1)
    y0, y1 = max(box[2, i] - oy, 0), min(box[3, i] - oy, th - 1)
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            p = y * STRIDE + x
            if zb[p] >= nearest or cov[p] < HALF:
                return False
            if cov[p] < 1 and not (0 < x < tw - 1 and 0 < y < th - 1 and cov[p - 1] >= HALF and cov[p + 1] >= HALF
                                   and cov[p - STRIDE] >= HALF and cov[p + STRIDE] >= HALF):
                return False
    return True


@nb.njit(fastmath=True, error_model="numpy")
def _setup_tile(table, ibox, count, ox, oy, m, radius_scale, lowpass2, depth_offset, ewa_filter, clip_src,
                field_src, normal_src, back_light):
    """The records of a tile's `count` staged splats, block by block (SIMD), with each box made
    tile-local and clipped to the tile. `clip_src`, `field_src`, `normal_src`: the extras, or
    None where the cloud has no clip lines, no normal field curves the splats, or none shades
    them (`rasterize_tiles`; then their rows are left alone)."""
    curved = field_src is not None
    scale = np.float32(1.0) / radius_scale
    cam = camera_scalars(m)
    for first in range(0, count, BLOCK):
        base = table_slot(first, TABLE_ROWS)
        box_base = table_slot(first, 4)
        for q in range(min(BLOCK, count - first)):
            j, jb = base + np.uint64(q), box_base + np.uint64(q)
            p, e = _staged(table, j)
            reach_u, reach_v = _reach(e, curved, radius_scale)
            record, field = _setup(p, e, cam, radius_scale, lowpass2, depth_offset, ewa_filter, curved,
                                   back_light, reach_u, reach_v)
            (table[j + ROW[MX]], table[j + ROW[MY]], table[j + ROW[W0]], table[j + ROW[WX]], table[j + ROW[WY]],
             table[j + ROW[Z0]], table[j + ROW[ZX]], table[j + ROW[ZY]], table[j + ROW[U0]], table[j + ROW[UX]],
             table[j + ROW[UY]], table[j + ROW[V0]], table[j + ROW[VX]], table[j + ROW[VY]], table[j + ROW[CZ]],
             table[j + ROW[RAD]], table[j + ROW[WT]], table[j + ROW[ZT]], table[j + ROW[FT]], table[j + ROW[R]],
             table[j + ROW[G]], table[j + ROW[B]], table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]) = record
            if clip_src is not None:
                table[j + ROW[C0A]], table[j + ROW[C0B]], table[j + ROW[C0C]] = _line_within_reach(
                    e[EA0], e[EB0], e[EC0] * scale, reach_u, reach_v)
                table[j + ROW[C1A]], table[j + ROW[C1B]], table[j + ROW[C1C]] = _line_within_reach(
                    e[EA1], e[EB1], e[EC1] * scale, reach_u, reach_v)
            if field_src is not None:  # the curved splat
                (table[j + ROW[KU]], table[j + ROW[KV]], table[j + ROW[LU]], table[j + ROW[LV]],
                 table[j + ROW[A10]], table[j + ROW[A1X]], table[j + ROW[A1Y]], table[j + ROW[B10]],
                 table[j + ROW[B1X]], table[j + ROW[B1Y]]) = field[:CURVE_VALUES]
            if field_src is not None and normal_src is not None:  # and its normals (`phong`, `deferred`)
                (table[j + ROW[FUX]], table[j + ROW[FUY]], table[j + ROW[FUZ]], table[j + ROW[FVX]],
                 table[j + ROW[FVY]], table[j + ROW[FVZ]], table[j + ROW[EX]], table[j + ROW[EY]],
                 table[j + ROW[EZ]]) = field[CURVE_VALUES:]
            # the box in tile-local pixels, clipped to the tile
            ibox[jb + TEMP[0]] = max(ibox[jb + TEMP[0]] - ox, 0)
            ibox[jb + TEMP[1]] = min(ibox[jb + TEMP[1]] - ox, TILE - 1)
            ibox[jb + TEMP[2]] = max(ibox[jb + TEMP[2]] - oy, 0)
            ibox[jb + TEMP[3]] = min(ibox[jb + TEMP[3]] - oy, TILE - 1)


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _normalize(acc, p, model, near, far, color_mode, table, index):
    """Normalization of pixel p's sums: rgb, unit normal, depth; with `model` >= 0, the albedo
    (the colour mode's: the normalized rgb, the colour map's entry of the normalized
    encoded value, or the palette entry `index` of the winning category) shaded per pixel."""
    inv = np.float32(1.0) / acc[p, 3]
    # the mean normal, not the sum: a pixel that only the faint low-pass of an edge-on splat
    # reaches sums to ~1e-20, whose squares are subnormal, and fastmath's reciprocal square
    # root of those is infinite: its colour came out NaN (the GPU's sums flush to zero there)
    sx, sy, sz = acc[p, 4] * inv, acc[p, 5] * inv, acc[p, 6] * inv
    length = math.sqrt(sx * sx + sy * sy + sz * sz)
    if length > 0:
        nx, ny, nz = sx / length, sy / length, sz / length
    else:
        nx, ny, nz = np.float32(0.0), np.float32(0.0), np.float32(1.0)
    depth = acc[p, 7] * inv
    r, g, b = acc[p, 0] * inv, acc[p, 1] * inv, acc[p, 2] * inv
    if color_mode == COLOR_CATEGORICAL:
        r, g, b = table[index, 0], table[index, 1], table[index, 2]
    elif color_mode == COLOR_CONTINUOUS and model >= 0:
        r, g, b = continuous_pixel(r, g, table)
    if model >= 0:
        r, g, b = shade_pixel(model, r, g, b, nx, ny, nz, depth, near, far)
    return r, g, b, nx, ny, nz, depth


@nb.njit(inline="always")
def _write(color, alpha, depth, normals, y, x, r, g, b, a, z, nx, ny, nz, background, composite):
    """One output pixel: composited over the background (the final image), or the raw sample
    that RenderResult.from_samples filters down (supersampling)."""
    if composite:
        keep = np.float32(1.0) - a
        color[y, x, 0] = min(max(r * a + keep * background[0], np.float32(0.0)), np.float32(1.0))
        color[y, x, 1] = min(max(g * a + keep * background[1], np.float32(0.0)), np.float32(1.0))
        color[y, x, 2] = min(max(b * a + keep * background[2], np.float32(0.0)), np.float32(1.0))
    else:
        color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
    alpha[y, x] = a
    if a > 0:
        depth[y, x] = z
        normals[y, x, 0], normals[y, x, 1], normals[y, x, 2] = nx, ny, nz
    else:
        depth[y, x] = np.inf
        normals[y, x, 0], normals[y, x, 1], normals[y, x, 2] = 0, 0, 0


@nb.njit(inline="always")
def _write_empty(color, alpha, depth, normals, present, indices, y, x, background, composite, categorical):
    """One output pixel that no splat reaches: the background, and no category."""
    zero = np.float32(0.0)
    present[y, x] = 0
    _write(color, alpha, depth, normals, y, x, zero, zero, zero, zero, zero, zero, zero, zero, background, composite)
    if categorical:
        indices[y, x] = -1


@nb.njit(parallel=True, fastmath=True, error_model="numpy", cache=True)
def rasterize_tiles(packed, staged_rows, extras, box, nearest, index, tile_start, tile_count, tile_front, tile_drawn,
                    order, tiles_x, width, height, m, radius_scale, lowpass, depth_offset, depth_clamp, clip_src,
                    field_src, normal_src, per_splat_model, deferred_model, color_mode, palette, levels, background,
                    composite, tables, boxes, temp, kept, split, split_box, split_kept, zbuf, cover, accum, best,
                    present, color, alpha, depth, normals, indices):
    """Every tile of `order`, written into color (H, W, 3), alpha, depth (H, W) and normals
    (H, W, 3). A tile draws the splats that face the camera first (the first tile_front[t] of
    its list, bins.tile_offsets), then, in a second table, those of the others that `_hidden`
    cannot rule out; tile_drawn (tiles,) gets how many it drew. Its attribute pass sums the
    second table's first, which moves the sums by float rounding only. Of the packed rows only
    `staged_rows` are copied into the tables: the others, the same for every splat (no
    colours, no layers), each table holds already (CpuSplatBuffers). `present` (H, W) uint8
    gets, per pixel, the bit COVERED where a splat covers its centre and the bit UNDECIDED
    where `finish_surrounded` must still decide whether its neighbours in other tiles make it
    whole (the pixel then holds its raw colour and its own coverage). Each thread's scratch:
    tables (2 threads, table_size(largest tile)), boxes (2 threads, 4 x that), temp (threads,
    TEMP_ROWS x BLOCK), kept (2 threads, table_size(largest tile, KEPT_ROWS)), split,
    split_box, split_kept (threads, those of SPLIT_BLOCKS splats), zbuf,
    cover (threads, STRIDE²), accum (threads, STRIDE², LAYER).
    clip_src, field_src, normal_src: the extras where splats are clipped, where they are curved
    by their normal fields, where they are shaded with them too (`phong`, `deferred`); else
    None, which compiles a kernel without that arithmetic, and stages only the extras it reads. The renderer
    clips where the cloud has clip lines, as the GPU's CLIP_LINES variant: clipping by inactive
    lines (which cut nothing) and staging rows that nothing reads made the `deferred` and `phong`
    frames of a curved cloud without clip lines a tenth longer (1M splats, `surfel bench`), which
    outweighs the 30 s that their own signature takes to compile, once.
    per_splat_model / deferred_model: the shading.MODEL_IDS value applied per splat
    (`gaussian`) or per pixel (`deferred`, `phong`, and every method in a categorical colour
    mode), -1 for the other. color_mode: COLOR_RGB, COLOR_CONTINUOUS (`palette` the colour map's
    LUT) or COLOR_CATEGORICAL (the palette, `levels` the packed values' code levels,
    `best` (threads, STRIDE²) each thread's scratch of packed categories, `indices` (H, W)
    int32 gets each pixel's palette index, -1 where empty; else a (1, 1) placeholder)."""
    zero = np.float32(0.0)
    near, far = m[17], m[18]
    lowpass2 = lowpass * lowpass
    ewa_filter = lowpass > 0
    params = (np.float32(1.0) / max(lowpass2, np.float32(1e-30)), zero if ewa_filter else NO_LOWPASS, depth_clamp)
    categorical = color_mode == COLOR_CATEGORICAL
    threads = zbuf.shape[0]
    for k in nb.prange(order.shape[0]):
        t = order[k]
        if t < 0:  # padding (ewa.balanced_tile_order)
            continue
        ox, oy = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        tw, th = min(TILE, width - ox), min(TILE, height - oy)
        count = tile_count[t]
        tile_drawn[t] = 0
        if count == 0:
            for y in range(oy, oy + th):
                for x in range(ox, ox + tw):
                    _write_empty(color, alpha, depth, normals, present, indices, y, x, background, composite,
                                 categorical)
            continue
        thread = nb.get_thread_id()
        tmp, zb, cov, acc = temp[thread], zbuf[thread], cover[thread], accum[thread]
        sp, sb, sk = split[thread], split_box[thread], split_kept[thread]
        zb[:] = FAR
        cov[:] = 0
        acc[:] = 0
        category = best[thread]
        if categorical:
            category[:] = -1
        # Phase 0 draws the splats that face the camera (the first tile_front[t] of the list);
        # phase 1, into a second table, the others that `_hidden` cannot rule out: where the
        # first cover a back splat's box in front of its `nearest`, none of its fragments passes
        # either pass, and it is never staged (the far side of a closed surface). A loop over
        # the phases, not two copies of its body: LLVM inlined the set-up and the visibility
        # pass at each call site, which took 20 s more to compile.
        start, front = tile_start[t], tile_front[t]
        staged = (0, 0)
        splits = (0, 0, 0, 0)  # each phase's rounds of copies, and copies in its last round
        for phase in range(2):
            own = phase * threads + thread  # a row of a 2D array: C-contiguous as the split table, one signature
            table, ibox, store = tables[own], boxes[own], kept[own]
            drawn = np.int64(0)  # not the literal 0: numba would compile the callees a second time for it
            for slot in range(0 if phase == 0 else front, front if phase == 0 else count):
                # unsigned indices: numba tests a signed one for wraparound, which keeps loads scalar
                i = np.uint64(index[start + slot])
                if phase == 0 or not _hidden(box, i, ox, oy, tw, th, nearest[i], zb, cov):
                    _stage(table, ibox, drawn, i, packed, staged_rows, extras, box, clip_src, field_src)
                    drawn += 1
            _setup_tile(table, ibox, drawn, ox, oy, m, radius_scale, lowpass2, depth_offset, ewa_filter, clip_src,
                        field_src, normal_src, per_splat_model < 0)
            if per_splat_model >= 0:  # Botsch & Kobbelt 2003: each splat's colour shaded, then blended
                for slot in range(drawn):
                    j = table_slot(slot, TABLE_ROWS)
                    r, g, b = table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]]
                    if color_mode == COLOR_CONTINUOUS:  # gl/colors.glsl splat_albedo
                        r, g, b = continuous_pixel(r, g, palette)
                    table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]] = shade_pixel(
                        per_splat_model, r, g, b, table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]],
                        table[j + ROW[CZ]], near, far)
            rounds, copies = visible_splats(table, ibox, drawn, ox, oy, params, clip_src, field_src, normal_src, tmp,
                                            store, sp, sb, sk, zb, cov)
            staged = (drawn, staged[1]) if phase == 0 else (staged[0], drawn)
            splits = (rounds, copies, 0, 0) if phase == 0 else (splits[0], splits[1], rounds, copies)
        tile_drawn[t] = staged[0] + staged[1]
        # the attribute pass, back splats first: `split` still holds the last copies made, the
        # back splats' where they made any (rounds 2 makes the front splats' again)
        for phase in range(1, -1, -1):
            rounds = splits[2] if phase == 1 else (2 if splits[0] > 0 and splits[2] > 0 else splits[0])
            own = phase * threads + thread
            attributes_of_splats(tables[own], boxes[own], staged[phase], rounds, splits[2 * phase + 1], ox, oy,
                                 params, clip_src, field_src, normal_src, tmp, kept[own], sp, sb, sk, zb, cov, acc,
                                 levels if categorical else 0, category)
        # normalization and deferred shading, straight into the output
        for ly in range(th):
            y = oy + ly
            for lx in range(tw):
                x = ox + lx
                p = np.uint64(ly * STRIDE + lx)  # unsigned: no wraparound test
                if acc[p, 3] <= 0:
                    _write_empty(color, alpha, depth, normals, present, indices, y, x, background, composite,
                                 categorical)
                    continue
                winner = 0
                if categorical:  # colors.category_unpack: every fragment packed, so the pixel has one
                    winner = int(category[p]) % levels
                    indices[y, x] = winner
                r, g, b, nx, ny, nz, z = _normalize(acc, p, deferred_model, near, far, color_mode, palette, winner)
                a = cov[p]
                state = 1
                if a < 1:
                    # surrounded (gl/passes.glsl): splats reach all four neighbours (the image's
                    # edge counts as reached); those in other tiles are checked afterwards
                    whole = True
                    for step in range(4):
                        qx = min(max(x + (1 if step == 0 else -1 if step == 1 else 0), 0), width - 1)
                        qy = min(max(y + (1 if step == 2 else -1 if step == 3 else 0), 0), height - 1)
                        if ox <= qx < ox + tw and oy <= qy < oy + th:
                            whole = whole and cov[(qy - oy) * STRIDE + qx - ox] >= HALF
                        else:
                            state = 2
                    if not whole:
                        state = 1
                    elif state == 1:
                        a = np.float32(1.0)
                present[y, x] = (UNDECIDED if state == 2 else 0) | (COVERED if cov[p] >= HALF else 0)
                if state == 2:  # the raw sample, for finish_surrounded
                    color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
                    alpha[y, x], depth[y, x] = a, z
                    normals[y, x, 0], normals[y, x, 1], normals[y, x, 2] = nx, ny, nz
                else:
                    _write(color, alpha, depth, normals, y, x, r, g, b, a, z, nx, ny, nz, background, composite)


def finish_surrounded(present, color, alpha, depth, normals, background, composite):
    """The pixels `rasterize_tiles` left undecided: whole where splats cover all four
    neighbours' centres, else their own coverage; then written as every other pixel."""
    over_rows(_finish_rows, present.shape[0], present, color, alpha, depth, normals, background, composite,
              grain=IMAGE_GRAIN)


@nb.njit(cache=True, nogil=True)
def _finish_rows(first, stop, present, color, alpha, depth, normals, background, composite):  # pragma: no cover
    """Rows first:stop of `finish_surrounded`. Only a pixel on the border of its tile has a
    neighbour in another tile, so only those are read: whole rows at the tiles' top and bottom,
    the first and last column of each tile in the others."""
    height, width = present.shape
    for y in range(first, stop):
        whole_row = y % TILE == 0 or y % TILE == TILE - 1
        x = 0
        while x < width:
            if present[y, x] & UNDECIDED:
                whole = (present[y, min(x + 1, width - 1)] & COVERED and present[y, max(x - 1, 0)] & COVERED
                         and present[min(y + 1, height - 1), x] & COVERED and present[max(y - 1, 0), x] & COVERED)
                a = np.float32(1.0) if whole else alpha[y, x]
                _write(color, alpha, depth, normals, y, x, color[y, x, 0], color[y, x, 1], color[y, x, 2], a,
                       depth[y, x], normals[y, x, 0], normals[y, x, 1], normals[y, x, 2], background, composite)
            # from a tile's first column to its last, from its last to the next tile's first
            x += TILE - 1 if not whole_row and x % TILE == 0 else 1
