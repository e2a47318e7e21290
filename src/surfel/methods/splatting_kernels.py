"""Numba kernels of the CPU backends of `gaussian`, `deferred` and `phong` (splatting_cpu.py
states the equations; splatting.glsl is the GPU program they reproduce).

1. `bound_splats` (parallel over chunks of splats): each splat's pixel box, as the GPU's quad
   (the projected corners of its disk's bounding square, and the low-pass disk), and culling
   (conservative: the fragment tests decide which pixels it covers), for BOUND_BLOCK splats at
   a time in one SIMD loop (`bound_block`); then how many splats of the chunk meet each
   TILE x TILE screen tile.
2. `tile_offsets` (serial over tiles) and `place_splats` (parallel over chunks): an index
   list per tile of the splats meeting it, in draw order.
3. `rasterize_tiles` (parallel over tiles): each tile owns its pixels, so threads never write
   the same memory. A tile copies its splats' packed inputs (one 64-byte row each) into its
   thread's table (splatting_tiles.py), then, in that table:
   - setup (`_setup_tile`, SIMD over a table block): what the vertex shader computes, once per
     splat: the eye-space splat, its back-face flip, the EWA weight, and the coefficients
     that make every per-pixel quantity of the fragment shader a ratio of affine functions of
     the pixel offset (dx, dy) from the splat's projected centre;
   - the visibility pass (MIN of depth + z_t, MAX of coverage) and the attribute pass (sums of
     w rgb, w, w n, w z of the fragments not behind it), splatting_tiles.py;
   - normalization, the colour mode and deferred shading straight into the output images.
4. `finish_surrounded` (parallel over rows): whether a pixel is `surrounded` needs its four
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
from .ewa_kernels import FAR, TILE, layer_offset
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
    CZ,
    EA0,
    EA1,
    EALPHA,
    EB0,
    EB1,
    EBETA,
    EC0,
    EC1,
    EX,
    EXTRAS,
    EY,
    EZ,
    FLAT_FIELD,
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
    TILE_BITS,
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
    attribute_tile,
    face_camera,
    table_slot,
    visibility_tile,
)

COLOR_RGB, COLOR_CONTINUOUS, COLOR_CATEGORICAL = 0, 1, 2  # gl/colors.glsl's colour modes
BOUND_BLOCK = 1024  # splats whose boxes bound_splats computes before counting them (in cache)
BACK_SPLAT_WEIGHT = np.float32(1.0 / 256.0)  # splatting.glsl's: a back-facing splat's weight beside front ones


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _eye(m, x, y, z):
    """Rotate (m[0..8] row-major), then translate (m[9..11])."""
    return (m[0] * x + m[1] * y + m[2] * z + m[9], m[3] * x + m[4] * y + m[5] * z + m[10],
            m[6] * x + m[7] * y + m[8] * z + m[11])


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _turn(m, x, y, z):
    """Rotate only (m[0..8] row-major)."""
    return m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z, m[6] * x + m[7] * y + m[8] * z


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _to_pixels(x, y, z, m):
    """Image position of an eye-space point (splatting.glsl to_pixels); m[12..16] = fx, fy, cx,
    cy, pixels per unit of an orthographic camera (0: perspective). A point at or behind the
    eye gets a finite stand-in (no splat uses it)."""
    fx, fy, cx, cy, ortho = m[12], m[13], m[14], m[15], m[16]
    inv = np.float32(-1.0) / min(z, np.float32(-1e-30))
    px, py = cx + fx * x * inv, cy - fy * y * inv
    return (cx + ortho * x if ortho > 0 else px), (cy - ortho * y if ortho > 0 else py)


@nb.njit(inline="always")
def _scalars(m):
    """The frame's camera array as a tuple: scalars for the SIMD loops (see the module docstring)."""
    return (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10], m[11], m[12], m[13], m[14], m[15],
            m[16], m[17], m[18])


@nb.njit(parallel=True, fastmath=True, error_model="numpy", cache=True)
def bound_splats(packed, extras, m, radius_scale, lowpass, backface, width, height, box, tiles_x, counts, scratch):
    """Each splat's pixel box in `box` (N, 4) int32, as the GPU's quad (splatting.glsl): the
    pixel centres inside the projected corners of the disk's bounding square and, with the EWA
    filter, the low-pass disk of `lowpass` pixels around the projected centre (x0, x1, y0, y1
    inclusive; x0 > x1 marks a culled splat). A splat with a corner behind the near plane gets
    the whole image. m: the frame's camera (splatting_cpu._camera). In the same pass, binning's
    count: counts (chunks, tiles) gets how many splats of each chunk of the cloud (one thread
    each) meet each TILE x TILE tile. scratch (chunks, 4 BOUND_BLOCK) int32: each chunk's boxes
    of BOUND_BLOCK splats, computed in one SIMD loop before they are counted."""
    n = packed.shape[0]
    cam = _scalars(m)
    chunks = counts.shape[0]
    step = (n + chunks - 1) // chunks
    for chunk in nb.prange(chunks):
        row = counts[chunk]
        row[:] = 0
        bounds = scratch[chunk]
        end = min(chunk * step + step, n)
        for first in range(chunk * step, end, BOUND_BLOCK):
            last = min(first + BOUND_BLOCK, end)
            bound_block(packed, extras, cam, radius_scale, lowpass, backface, width, height, bounds, first, last)
            for i in range(first, last):
                slot = i - first
                x0, x1 = bounds[slot], bounds[slot + BOUND_BLOCK]
                y0, y1 = bounds[slot + 2 * BOUND_BLOCK], bounds[slot + 3 * BOUND_BLOCK]
                box[i, 0], box[i, 1], box[i, 2], box[i, 3] = x0, x1, y0, y1
                if x0 > x1:
                    continue
                for ty in range(y0 >> TILE_BITS, (y1 >> TILE_BITS) + 1):
                    for tx in range(x0 >> TILE_BITS, (x1 >> TILE_BITS) + 1):
                        row[ty * tiles_x + tx] += 1


@nb.njit(fastmath=True, error_model="numpy")
def bound_block(packed, extras, cam, radius_scale, lowpass, backface, width, height, bounds, first, last):
    """bound_splats' boxes of splats first..last-1, without branches (a SIMD loop)."""
    ortho, near = cam[16], cam[17]
    one = np.float32(1.0)
    for i in range(first, last):
        # the packed row read element by element: a row view would bring reference counting,
        # an atomic shared by every thread, into the loop
        ex, ey, ez = _eye(cam, packed[i, PX], packed[i, PY], packed[i, PZ])
        nx, ny, nz = _turn(cam, packed[i, PNX], packed[i, PNY], packed[i, PNZ])
        ux, uy, uz = _turn(cam, packed[i, PUX] * radius_scale, packed[i, PUY] * radius_scale,
                           packed[i, PUZ] * radius_scale)
        vx, vy, vz = _turn(cam, packed[i, PVX] * radius_scale, packed[i, PVY] * radius_scale,
                           packed[i, PVZ] * radius_scale)
        nx, ny, nz, ux, uy, uz, vx, vy, vz = face_camera(ex, ey, ez, nx, ny, nz, ux, uy, uz, vx, vy, vz, ortho)
        depth = -ez
        perspective = ortho <= 0
        reach = math.sqrt(ux * ux + uy * uy + uz * uz) + math.sqrt(vx * vx + vy * vy + vz * vz)
        culled = (backface & ((nz if ortho > 0 else -(nx * ex + ny * ey + nz * ez)) < 0)) \
            | (perspective & (depth + reach < near))  # facing away, or wholly behind the near plane
        if extras is not None:  # cut away whole (a point on a crease)
            culled |= (extras[i, EC0] < -1) | (extras[i, EC1] < -1)
        whole = perspective & (depth - abs(uz) - abs(vz) < near)  # a corner behind it: the whole image
        lo_x = lo_y = np.float32(1e30)
        hi_x = hi_y = np.float32(-1e30)
        for corner in range(4):
            su = -one if corner & 1 == 0 else one
            sv = -one if corner < 2 else one
            sx, sy = _to_pixels(ex + su * ux + sv * vx, ey + su * uy + sv * vy, ez + su * uz + sv * vz, cam)
            lo_x, lo_y, hi_x, hi_y = min(lo_x, sx), min(lo_y, sy), max(hi_x, sx), max(hi_y, sy)
        if lowpass > 0:
            mx, my = _to_pixels(ex, ey, ez, cam)
            lo_x, lo_y = min(lo_x, mx - lowpass), min(lo_y, my - lowpass)
            hi_x, hi_y = max(hi_x, mx + lowpass), max(hi_y, my + lowpass)
        # pixel centres x + 0.5 in [lo, hi)
        x0 = max(int(np.ceil(max(lo_x, -one) - np.float32(0.5))), 0)
        x1 = min(int(np.ceil(min(hi_x, np.float32(width + 1)) - np.float32(0.5))) - 1, width - 1)
        y0 = max(int(np.ceil(max(lo_y, -one) - np.float32(0.5))), 0)
        y1 = min(int(np.ceil(min(hi_y, np.float32(height + 1)) - np.float32(0.5))) - 1, height - 1)
        x0, x1 = (0 if whole else x0), (width - 1 if whole else x1)
        y0, y1 = (0 if whole else y0), (height - 1 if whole else y1)
        empty = culled | (x0 > x1) | (y0 > y1)
        slot = i - first
        bounds[slot] = 1 if empty else x0
        bounds[slot + BOUND_BLOCK] = 0 if empty else x1
        bounds[slot + 2 * BOUND_BLOCK] = 1 if empty else y0
        bounds[slot + 3 * BOUND_BLOCK] = 0 if empty else y1


@nb.njit(cache=True)
def tile_offsets(counts, tile_start, tile_count):
    """Binning's prefix sum, tile-major and chunk-minor so that each tile's splats stay in draw
    order: counts (chunks, tiles) becomes each chunk's first place in the index list of each
    tile, tile t's list being index[tile_start[t]:tile_start[t] + tile_count[t]]. Returns
    (tile-splat pairs, largest tile count)."""
    chunks, tiles = counts.shape
    total, largest = 0, 0
    for t in range(tiles):
        tile_start[t] = total
        for chunk in range(chunks):
            count = counts[chunk, t]
            counts[chunk, t] = total
            total += count
        tile_count[t] = total - tile_start[t]
        largest = max(largest, tile_count[t])
    return total, largest


@nb.njit(parallel=True, cache=True)
def place_splats(box, tiles_x, places, index):
    """Binning's scatter: each chunk's splats (one thread each) into the index lists of the
    tiles they meet, from `places` (chunks, tiles), which tile_offsets made."""
    n = box.shape[0]
    chunks = places.shape[0]
    step = (n + chunks - 1) // chunks
    for chunk in nb.prange(chunks):
        row = places[chunk]
        for i in range(chunk * step, min(chunk * step + step, n)):
            if box[i, 0] > box[i, 1]:
                continue
            tx0, tx1 = box[i, 0] >> TILE_BITS, box[i, 1] >> TILE_BITS
            for ty in range(box[i, 2] >> TILE_BITS, (box[i, 3] >> TILE_BITS) + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    index[row[t]] = i
                    row[t] += 1


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _setup(p, e, m, radius_scale, lowpass2, depth_offset, ewa_filter, curved, back_light):
    """The record of one splat from its staged inputs p (PACKED values) and extras e (EXTRAS
    values), without branches (the vertex stage of splatting.glsl): (record values MX..NZ, field
    values KU..EZ). `back_light`: a back-facing splat weighs BACK_SPLAT_WEIGHT (the methods
    that blend normals, not shaded colours)."""
    one, zero, tiny = np.float32(1.0), np.float32(0.0), np.float32(1e-30)
    fx, fy, cx, cy, ortho, near = m[12], m[13], m[14], m[15], m[16], m[17]
    ex, ey, ez = _eye(m, p[PX], p[PY], p[PZ])
    nx, ny, nz = _turn(m, p[PNX], p[PNY], p[PNZ])
    ux, uy, uz = _turn(m, p[PUX] * radius_scale, p[PUY] * radius_scale, p[PUZ] * radius_scale)
    vx, vy, vz = _turn(m, p[PVX] * radius_scale, p[PVY] * radius_scale, p[PVZ] * radius_scale)
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
    zt = layer_offset(depth_offset * max(lu, lv), p[PT], abs(facing) * inv_n * (one if not perspective else to_eye))
    # a corner of the bounding square behind the near plane: the GPU's quad covers the whole
    # viewport and its EWA weight is 1
    crosses_near = perspective and (depth - abs(uz) - abs(vz) < near)
    behind_eye = perspective and depth <= 1e-30  # no projected centre: use the principal point
    mx, my = _to_pixels(ex, ey, ez, m)
    mx, my = (cx if behind_eye else mx), (cy if behind_eye else my)
    # EWA's normalization: the resampling kernel's amplitude relative to the reconstruction
    # kernel, sqrt(det S / det(S + r^2 I)), S = J Jᵀ of the projected splat
    jux, juy = _to_pixels(ex + ux, ey + uy, ez + uz, m)
    jvx, jvy = _to_pixels(ex + vx, ey + vy, ez + vz, m)
    jux, juy, jvx, jvy = jux - mx, juy - my, jvx - mx, jvy - my
    det = jux * jvy - juy * jvx
    det_s = det * det
    trace_s = jux * jux + juy * juy + jvx * jvx + jvy * jvy
    weight = math.sqrt(det_s / max(det_s + lowpass2 * trace_s + lowpass2 * lowpass2, tiny))
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
              depth, max(lu, lv), weight, zt, p[PR], p[PG], p[PB], nx, ny, nz)
    field = FLAT_FIELD
    if curved:
        alpha, beta = flip * e[EALPHA], flip * e[EBETA]
        ilu, ilv = one / max(lu, tiny), one / max(lv, tiny)
        eux, euy, euz = ux * ilu, uy * ilu, uz * ilu
        evx, evy, evz = vx * ilv, vy * ilv, vz * ilv
        field = (alpha * ilu, beta * ilv, lu, lv,
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
         table[j + ROW[PACKED + EALPHA]], table[j + ROW[PACKED + EBETA]])
    return p, e


@nb.njit(fastmath=True, error_model="numpy")
def _setup_tile(table, ibox, count, ox, oy, m, radius_scale, lowpass2, depth_offset, ewa_filter, clip_src,
                field_src, back_light):
    """The records of a tile's `count` staged splats, block by block (SIMD), with each box made
    tile-local and clipped to the tile. `clip_src`, `field_src`: the extras, or None where the
    cloud has no clip lines or no normal field is drawn (then their rows are left alone)."""
    curved = field_src is not None
    scale = np.float32(1.0) / radius_scale
    cam = _scalars(m)
    for first in range(0, count, BLOCK):
        base = table_slot(first, TABLE_ROWS)
        box_base = table_slot(first, 4)
        for q in range(min(BLOCK, count - first)):
            j, jb = base + np.uint64(q), box_base + np.uint64(q)
            p, e = _staged(table, j)
            record, field = _setup(p, e, cam, radius_scale, lowpass2, depth_offset, ewa_filter, curved, back_light)
            (table[j + ROW[MX]], table[j + ROW[MY]], table[j + ROW[W0]], table[j + ROW[WX]], table[j + ROW[WY]],
             table[j + ROW[Z0]], table[j + ROW[ZX]], table[j + ROW[ZY]], table[j + ROW[U0]], table[j + ROW[UX]],
             table[j + ROW[UY]], table[j + ROW[V0]], table[j + ROW[VX]], table[j + ROW[VY]], table[j + ROW[CZ]],
             table[j + ROW[RAD]], table[j + ROW[WT]], table[j + ROW[ZT]], table[j + ROW[R]], table[j + ROW[G]],
             table[j + ROW[B]], table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]) = record
            if clip_src is not None:
                (table[j + ROW[C0A]], table[j + ROW[C0B]], table[j + ROW[C0C]], table[j + ROW[C1A]],
                 table[j + ROW[C1B]], table[j + ROW[C1C]]) = (e[EA0], e[EB0], e[EC0] * scale, e[EA1], e[EB1],
                                                              e[EC1] * scale)
            if field_src is not None:
                (table[j + ROW[KU]], table[j + ROW[KV]], table[j + ROW[LU]], table[j + ROW[LV]],
                 table[j + ROW[A10]], table[j + ROW[A1X]], table[j + ROW[A1Y]], table[j + ROW[B10]],
                 table[j + ROW[B1X]], table[j + ROW[B1Y]], table[j + ROW[FUX]], table[j + ROW[FUY]],
                 table[j + ROW[FUZ]], table[j + ROW[FVX]], table[j + ROW[FVY]], table[j + ROW[FVZ]],
                 table[j + ROW[EX]], table[j + ROW[EY]], table[j + ROW[EZ]]) = field
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
    inv = np.float32(1.0) / acc[3, p]
    sx, sy, sz = acc[4, p], acc[5, p], acc[6, p]
    length = math.sqrt(sx * sx + sy * sy + sz * sz)
    if length > 0:
        nx, ny, nz = sx / length, sy / length, sz / length
    else:
        nx, ny, nz = np.float32(0.0), np.float32(0.0), np.float32(1.0)
    depth = acc[7, p] * inv
    r, g, b = acc[0, p] * inv, acc[1, p] * inv, acc[2, p] * inv
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
def rasterize_tiles(packed, extras, box, index, tile_start, tile_count, order, tiles_x, width, height, m,
                    radius_scale, lowpass, depth_offset, depth_clamp, clip_src, field_src, normal_src,
                    per_splat_model, deferred_model, color_mode, palette, levels, background, composite, tables, boxes,
                    temp, kept, zbuf, cover, accum, best, present, color, alpha, depth, normals, indices):
    """Every tile of `order`, written into color (H, W, 3), alpha, depth (H, W) and normals
    (H, W, 3). `present` (H, W) uint8 gets, per pixel, 0 (no splat), 1, or 2 where
    `finish_surrounded` must still decide whether its neighbours in other tiles make it whole
    (the pixel then holds its raw colour and its own coverage). Each thread's scratch: tables
    (threads, table_size(largest tile)), boxes (threads, 4 x that), temp (threads,
    TEMP_ROWS x BLOCK), kept (threads, table_size(largest tile, KEPT_ROWS)), zbuf, cover
    (threads, STRIDE²), accum (threads, LAYER, STRIDE²).
    clip_src, field_src, normal_src: the extras where the cloud has clip lines, where splats are
    curved by their normal fields, where they are shaded with them too (`phong`); else None.
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
    for k in nb.prange(order.shape[0]):
        t = order[k]
        ox, oy = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        tw, th = min(TILE, width - ox), min(TILE, height - oy)
        count = tile_count[t]
        if count == 0:
            for y in range(oy, oy + th):
                for x in range(ox, ox + tw):
                    _write_empty(color, alpha, depth, normals, present, indices, y, x, background, composite,
                                 categorical)
            continue
        thread = nb.get_thread_id()
        table, ibox, tmp, store = tables[thread], boxes[thread], temp[thread], kept[thread]
        zb, cov, acc = zbuf[thread], cover[thread], accum[thread]
        # stage the tile's splats: one packed row each, its extras and its box
        start = tile_start[t]
        for slot in range(count):
            i = index[start + slot]
            j, jb = table_slot(slot, TABLE_ROWS), table_slot(slot, 4)
            for col in range(PACKED):
                table[j + np.uint64(col * BLOCK)] = packed[i, col]
            if extras is not None:
                for col in range(EXTRAS):
                    table[j + np.uint64((PACKED + col) * BLOCK)] = extras[i, col]
            for col in range(4):
                ibox[jb + np.uint64(col * BLOCK)] = box[i, col]
        _setup_tile(table, ibox, count, ox, oy, m, radius_scale, lowpass2, depth_offset, ewa_filter, clip_src,
                    field_src, per_splat_model < 0)
        if per_splat_model >= 0:  # Botsch & Kobbelt 2003: each splat's colour shaded, then blended
            for slot in range(count):
                j = table_slot(slot, TABLE_ROWS)
                r, g, b = table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]]
                if color_mode == COLOR_CONTINUOUS:  # gl/colors.glsl splat_albedo
                    r, g, b = continuous_pixel(r, g, palette)
                table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]] = shade_pixel(
                    per_splat_model, r, g, b, table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]],
                    table[j + ROW[CZ]], near, far)
        zb[:] = FAR
        cov[:] = 0
        acc[:] = 0
        category = best[thread]
        if categorical:
            category[:] = -1
        visibility_tile(table, ibox, count, ox, oy, params, clip_src, field_src, normal_src, tmp, store, zb, cov)
        attribute_tile(table, ibox, count, ox, oy, params, clip_src, field_src, normal_src, store, zb, acc,
                        levels if categorical else 0, category)
        # normalization and deferred shading, straight into the output
        for ly in range(th):
            y = oy + ly
            for lx in range(tw):
                x = ox + lx
                p = ly * STRIDE + lx
                if acc[3, p] <= 0:
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
                            whole = whole and acc[3, (qy - oy) * STRIDE + qx - ox] > 0
                        else:
                            state = 2
                    if not whole:
                        state = 1
                    elif state == 1:
                        a = np.float32(1.0)
                present[y, x] = state
                if state == 2:  # the raw sample, for finish_surrounded
                    color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
                    alpha[y, x], depth[y, x] = a, z
                    normals[y, x, 0], normals[y, x, 1], normals[y, x, 2] = nx, ny, nz
                else:
                    _write(color, alpha, depth, normals, y, x, r, g, b, a, z, nx, ny, nz, background, composite)


@nb.njit(parallel=True, cache=True)
def finish_surrounded(present, color, alpha, depth, normals, background, composite):
    """The pixels `rasterize_tiles` left undecided: whole where splats reach all four
    neighbours, else their own coverage; then written as every other pixel."""
    height, width = present.shape
    for y in nb.prange(height):
        for x in range(width):
            if present[y, x] != 2:
                continue
            whole = (present[y, min(x + 1, width - 1)] > 0 and present[y, max(x - 1, 0)] > 0
                     and present[min(y + 1, height - 1), x] > 0 and present[max(y - 1, 0), x] > 0)
            a = np.float32(1.0) if whole else alpha[y, x]
            _write(color, alpha, depth, normals, y, x, color[y, x, 0], color[y, x, 1], color[y, x, 2], a,
                   depth[y, x], normals[y, x, 0], normals[y, x, 1], normals[y, x, 2], background, composite)
