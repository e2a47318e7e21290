"""Numba kernels of the CPU backends of `gaussian`, `deferred` and `phong` (splatting_cpu.py
states the equations; splatting.glsl is the GPU program they reproduce).

1. `bound_splats` (parallel over splats): each splat's pixel box, from a bounding sphere of
   its disk (conservative: the fragment tests decide which pixels it covers), and culling.
2. `bin_splats` (parallel over chunks of splats): the splats meeting each TILE x TILE screen
   tile, an index list per tile in draw order.
3. `rasterize_tiles` (parallel over tiles): each tile owns its pixels, so threads never write
   the same memory. A tile copies its splats' packed inputs (one 64-byte row each) into its
   thread's table, then, in that table:
   - setup: what the vertex shader computes, once per splat: the eye-space splat, its
     back-face flip, the EWA weight, and the coefficients that make every per-pixel quantity
     of the fragment shader a ratio of affine functions of the pixel offset (dx, dy) from the
     splat's projected centre;
   - the visibility pass (MIN of depth + z_t, MAX of coverage), the attribute pass (sums of
     w rgb, w, w n, w z of the fragments not behind it), then normalization and deferred
     shading straight into the output images.
   Each step takes the tile's splats a table block at a time: the setup, and the 2x2 pixels
   at the top-left of each splat's box (all of a splat smaller than the low-pass, the common
   case of a dense cloud), are computed for the whole block in one loop without branches,
   which the compiler turns into SIMD code; the results are then blended into the tile one
   splat after another, and the rest of a larger box follows pixel by pixel.
4. `finish_surrounded` (parallel over rows): whether a pixel is `surrounded` needs its four
   neighbours; a tile decides it for its own pixels and leaves to this pass the few on its
   border whose neighbour lies in another tile.

The table holds BLOCK splats at a time, row after row (an array of structures of arrays): a
row of a block is contiguous and the rows lie at fixed distances, so that a loop over a
block's splats loads and stores each row as a vector, with no aliasing check for the compiler
to add. Per-fragment arithmetic is float32 under fastmath, with error_model="numpy" (no
division checks, which would keep the loops scalar); masked lanes select finite values, so no
infinity or NaN is computed ("no depth yet" is the finite FAR). Helpers called inside the SIMD
loops take scalars only: an array argument brings reference counting into the loop, which
keeps it scalar.

A further attribute channel joins in `_blend`: a continuous one (a scalar to colour by) is
one more weighted sum and one more division in `_normalize`; a categorical one keeps per
pixel the code of the fragment of largest weight (two more scratch planes: that weight and
its code, replaced when a fragment outweighs it), never a blend.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.polynomial import chebyshev

from ..colors import CODE_SCALE, category_pack, continuous_pixel
from ..shading import shade_pixel
from .ewa_kernels import FAR, TILE
from .splatting import GAUSSIAN_SHARPNESS, KERNEL_SIZE

# Columns of a cloud's packed inputs (splatting_cpu.pack_splats): one 64-byte row per splat.
(PX, PY, PZ, PNX, PNY, PNZ, PUX, PUY, PUZ, PVX, PVY, PVZ, PR, PG, PB) = range(15)
PACKED = 16
# Columns of its extras: two clip lines a u + b v <= c (surfel.preprocess) and the normal
# field's slopes alpha, beta (Phong splatting).
(EA0, EB0, EC0, EA1, EB1, EC1, EALPHA, EBETA) = range(8)
EXTRAS = 8
# Rows of a tile's table. The first PACKED + EXTRAS rows are the staged inputs. Then the
# setup's record: the projected centre (MX, MY); with (dx, dy) a pixel centre's offset from
# it, W = W0 + WX dx + WY dy, depth W = Z0 + ZX dx + ZY dy, u W = U0 + UX dx + UY dy and
# v W likewise; the centre's eye depth CZ; the largest semi-axis RAD; the EWA weight WT; the
# albedo (or per-splat shaded colour); the eye normal, turned to face the camera.
STAGED = PACKED + EXTRAS
(MX, MY, W0, WX, WY, Z0, ZX, ZY, U0, UX, UY, V0, VX, VY, CZ, RAD, WT, R, G, B, NX, NY, NZ) = range(STAGED,
                                                                                                 STAGED + 23)
# The clip lines (c over radius_scale: the scaled splat's coordinates).
(C0A, C0B, C0C, C1A, C1B, C1C) = range(NZ + 1, NZ + 7)
# Phong splatting's normal field: the curvatures KU = alpha / |u_j|, KV; the semi-axes LU, LV;
# d.e_u = A10 + A1X dx + A1Y dy and d.e_v (B1*) along the unit axes; the field's eye-space
# slopes alpha e_u (FU*) and beta e_v (FV*); the unit direction to the eye (E*).
(KU, KV, LU, LV, A10, A1X, A1Y, B10, B1X, B1Y, FUX, FUY, FUZ, FVX, FVY, FVZ, EX, EY, EZ) = range(C1C + 1,
                                                                                                 C1C + 20)
TABLE_ROWS = EZ + 1
BLOCK_BITS = 6
BLOCK = 1 << BLOCK_BITS
ROW = tuple(np.uint64(row * BLOCK) for row in range(TABLE_ROWS))  # a row's offset inside a block
TILE_BITS = TILE.bit_length() - 1  # TILE is a power of two: a pixel's tile is pixel >> TILE_BITS
STRIDE = TILE + 2  # row stride of the tile scratch: a splat's 2x2 block may reach one past the tile
LAYER = 8  # accumulator planes, the GL attribute pass's two targets: w r, w g, w b, w, w n, w depth
TEMP_ROWS = 20  # block results: 4 lanes each of depth and coverage, or of w, depth and 3 normal components
TEMP = tuple(np.uint64(row * BLOCK) for row in range(TEMP_ROWS))
COLOR_RGB, COLOR_CONTINUOUS, COLOR_CATEGORICAL = 0, 1, 2  # gl/colors.glsl's colour modes
MISS = np.float32(1e30)  # the squared kernel distance of a ray that misses the splat
NO_CLIP = np.float32(-1e30)
NO_LOWPASS = np.float32(2.0)  # added to the low-pass distance when the EWA filter is off: never <= 1
INACTIVE_LINES = tuple(np.float32(c) for c in (0, 0, 1, 0, 0, 1))  # clip lines that cut nothing
FLAT_FIELD = tuple(np.float32(0) for _ in range(19))  # no normal field
# exp(-t) on [0, GAUSSIAN_SHARPNESS] as a polynomial in s = 2 t / GAUSSIAN_SHARPNESS - 1 (Chebyshev
# interpolation, relative error below 1e-6): the weight in SIMD code, where math.exp stays scalar
EXP_POLY = tuple(np.float32(c) for c in chebyshev.cheb2poly(chebyshev.chebinterpolate(
    lambda s: np.exp(-0.5 * GAUSSIAN_SHARPNESS * (s + 1)), 9)))


def table_size(count: int) -> int:
    """Entries of a table for `count` splats (whole blocks)."""
    return -(-count // BLOCK) * BLOCK * TABLE_ROWS


@nb.njit(inline="always")
def _slot(k, rows):
    """Where the splat at slot k lies in a table of `rows` rows (unsigned: no negative-index
    wrap, which would keep loads from being vectors)."""
    return np.uint64((k >> BLOCK_BITS) * (rows * BLOCK) + (k & (BLOCK - 1)))


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
def bound_splats(packed, extras, m, radius_scale, lowpass, backface, width, height, box):
    """Each splat's pixel box in `box` (N, 4) int32, as the GPU's quad (splatting.glsl): the
    pixel centres inside the projected corners of the disk's bounding square and, with the EWA
    filter, the low-pass disk of `lowpass` pixels around the projected centre (x0, x1, y0, y1
    inclusive; x0 > x1 marks a culled splat). A splat with a corner behind the near plane gets
    the whole image. m: the frame's camera (splatting_cpu._camera)."""
    n = packed.shape[0]
    cam = _scalars(m)
    ortho, near = cam[16], cam[17]
    one = np.float32(1.0)
    for i in nb.prange(n):
        p = packed[i]
        box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 1, 0, 1, 0
        if extras is not None:
            if extras[i, EC0] < -1 or extras[i, EC1] < -1:
                continue  # cut away whole (a point on a crease)
        ex, ey, ez = _eye(cam, p[PX], p[PY], p[PZ])
        nx, ny, nz = _turn(cam, p[PNX], p[PNY], p[PNZ])
        if backface and (nz if ortho > 0 else -(nx * ex + ny * ey + nz * ez)) < 0:
            continue
        ux, uy, uz = _turn(cam, p[PUX] * radius_scale, p[PUY] * radius_scale, p[PUZ] * radius_scale)
        vx, vy, vz = _turn(cam, p[PVX] * radius_scale, p[PVY] * radius_scale, p[PVZ] * radius_scale)
        depth = -ez
        reach = math.sqrt(ux * ux + uy * uy + uz * uz) + math.sqrt(vx * vx + vy * vy + vz * vz)
        if ortho <= 0 and depth + reach < near:
            continue  # wholly behind the near plane
        if ortho <= 0 and depth - abs(uz) - abs(vz) < near:  # a corner behind it: the whole image
            box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 0, width - 1, 0, height - 1
            continue
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
        x0 = max(int(math.ceil(max(lo_x, -one) - np.float32(0.5))), 0)
        x1 = min(int(math.ceil(min(hi_x, np.float32(width + 1)) - np.float32(0.5))) - 1, width - 1)
        y0 = max(int(math.ceil(max(lo_y, -one) - np.float32(0.5))), 0)
        y1 = min(int(math.ceil(min(hi_y, np.float32(height + 1)) - np.float32(0.5))) - 1, height - 1)
        if x0 <= x1 and y0 <= y1:
            box[i, 0], box[i, 1], box[i, 2], box[i, 3] = x0, x1, y0, y1


@nb.njit(parallel=True, cache=True)
def bin_splats(box, tiles_x, tiles_y, counts, tile_start, tile_count, index):
    """The splats meeting each tile, tile after tile, in draw order: index[tile_start[t]:
    tile_start[t] + tile_count[t]]. counts (chunks, tiles) is scratch: each chunk of splats is
    counted and placed by one thread. Returns (pairs, largest tile count); when the pairs
    exceed len(index), nothing is placed (grow it and call again)."""
    n = box.shape[0]
    chunks, tiles = counts.shape[0], tiles_x * tiles_y
    step = (n + chunks - 1) // chunks
    for chunk in nb.prange(chunks):
        row = counts[chunk]
        row[:] = 0
        for i in range(chunk * step, min(chunk * step + step, n)):
            if box[i, 0] > box[i, 1]:
                continue
            tx0, tx1 = box[i, 0] >> TILE_BITS, box[i, 1] >> TILE_BITS
            for ty in range(box[i, 2] >> TILE_BITS, (box[i, 3] >> TILE_BITS) + 1):
                for tx in range(tx0, tx1 + 1):
                    row[ty * tiles_x + tx] += 1
    total, largest = 0, 0
    for t in range(tiles):  # tile-major, chunk-minor: each tile's splats stay in draw order
        tile_start[t] = total
        for chunk in range(chunks):
            count = counts[chunk, t]
            counts[chunk, t] = total
            total += count
        tile_count[t] = total - tile_start[t]
        largest = max(largest, tile_count[t])
    if total > index.shape[0]:
        return total, largest
    for chunk in nb.prange(chunks):
        row = counts[chunk]
        for i in range(chunk * step, min(chunk * step + step, n)):
            if box[i, 0] > box[i, 1]:
                continue
            tx0, tx1 = box[i, 0] >> TILE_BITS, box[i, 1] >> TILE_BITS
            for ty in range(box[i, 2] >> TILE_BITS, (box[i, 3] >> TILE_BITS) + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    index[row[t]] = i
                    row[t] += 1
    return total, largest


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _setup(p, e, m, radius_scale, lowpass2, ewa_filter, curved):
    """The record of one splat from its staged inputs p (PACKED values) and extras e (EXTRAS
    values), without branches (the vertex stage of splatting.glsl): (record values MX..NZ, field
    values KU..EZ, its normal flip)."""
    one, zero, tiny = np.float32(1.0), np.float32(0.0), np.float32(1e-30)
    fx, fy, cx, cy, ortho, near = m[12], m[13], m[14], m[15], m[16], m[17]
    ex, ey, ez = _eye(m, p[PX], p[PY], p[PZ])
    nx, ny, nz = _turn(m, p[PNX], p[PNY], p[PNZ])
    inv_n = one / max(math.sqrt(nx * nx + ny * ny + nz * nz), tiny)
    facing = nz if ortho > 0 else -(nx * ex + ny * ey + nz * ez)
    flip = -one if facing < 0 else one  # every method shows the side that faces the camera
    nx, ny, nz = nx * inv_n * flip, ny * inv_n * flip, nz * inv_n * flip
    ux, uy, uz = _turn(m, p[PUX] * radius_scale, p[PUY] * radius_scale, p[PUZ] * radius_scale)
    vx, vy, vz = _turn(m, p[PVX] * radius_scale, p[PVY] * radius_scale, p[PVZ] * radius_scale)
    lu, lv = math.sqrt(ux * ux + uy * uy + uz * uz), math.sqrt(vx * vx + vy * vy + vz * vz)
    depth = -ez
    perspective = ortho <= 0
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
              depth, max(lu, lv), weight, p[PR], p[PG], p[PB], nx, ny, nz)
    field = FLAT_FIELD
    if curved:
        alpha, beta = flip * e[EALPHA], flip * e[EBETA]
        ilu, ilv = one / max(lu, tiny), one / max(lv, tiny)
        eux, euy, euz = ux * ilu, uy * ilu, uz * ilu
        evx, evy, evz = vx * ilv, vy * ilv, vz * ilv
        to_eye = one / max(math.sqrt(ex * ex + ey * ey + ez * ez), tiny)
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
         table[j + ROW[PVY]], table[j + ROW[PVZ]], table[j + ROW[PR]], table[j + ROW[PG]], table[j + ROW[PB]])
    e = (table[j + ROW[PACKED + EA0]], table[j + ROW[PACKED + EB0]], table[j + ROW[PACKED + EC0]],
         table[j + ROW[PACKED + EA1]], table[j + ROW[PACKED + EB1]], table[j + ROW[PACKED + EC1]],
         table[j + ROW[PACKED + EALPHA]], table[j + ROW[PACKED + EBETA]])
    return p, e


@nb.njit(fastmath=True, error_model="numpy")
def _setup_tile(table, ibox, count, ox, oy, m, radius_scale, lowpass2, ewa_filter, clip_src, field_src):
    """The records of a tile's `count` staged splats, block by block (SIMD), with each box made
    tile-local and clipped to the tile. `clip_src`, `field_src`: the extras, or None where the
    cloud has no clip lines or no normal field is drawn (then their rows are left alone)."""
    curved = field_src is not None
    scale = np.float32(1.0) / radius_scale
    cam = _scalars(m)
    for first in range(0, count, BLOCK):
        base = _slot(first, TABLE_ROWS)
        box_base = _slot(first, 4)
        for q in range(min(BLOCK, count - first)):
            j, jb = base + np.uint64(q), box_base + np.uint64(q)
            p, e = _staged(table, j)
            record, field = _setup(p, e, cam, radius_scale, lowpass2, ewa_filter, curved)
            (table[j + ROW[MX]], table[j + ROW[MY]], table[j + ROW[W0]], table[j + ROW[WX]], table[j + ROW[WY]],
             table[j + ROW[Z0]], table[j + ROW[ZX]], table[j + ROW[ZY]], table[j + ROW[U0]], table[j + ROW[UX]],
             table[j + ROW[UY]], table[j + ROW[V0]], table[j + ROW[VX]], table[j + ROW[VY]], table[j + ROW[CZ]],
             table[j + ROW[RAD]], table[j + ROW[WT]], table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]],
             table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]) = record
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


@nb.njit(inline="always")
def _geometry(table, j):
    """The rows MX..WT of the splat at table slot j: what every fragment of it needs."""
    return (table[j + ROW[MX]], table[j + ROW[MY]], table[j + ROW[W0]], table[j + ROW[WX]], table[j + ROW[WY]],
            table[j + ROW[Z0]], table[j + ROW[ZX]], table[j + ROW[ZY]], table[j + ROW[U0]], table[j + ROW[UX]],
            table[j + ROW[UY]], table[j + ROW[V0]], table[j + ROW[VX]], table[j + ROW[VY]], table[j + ROW[CZ]],
            table[j + ROW[RAD]], table[j + ROW[WT]])


@nb.njit(inline="always")
def _extras(table, clip_src, field_src, j):
    """The clip lines and normal field of the splat at table slot j, or inactive stand-ins of the
    same types (`clip_src is None` is known when a kernel is compiled: their arithmetic is then
    left out)."""
    if clip_src is not None:
        c = (table[j + ROW[C0A]], table[j + ROW[C0B]], table[j + ROW[C0C]], table[j + ROW[C1A]],
             table[j + ROW[C1B]], table[j + ROW[C1C]])
    else:
        c = INACTIVE_LINES
    if field_src is not None:
        f = (table[j + ROW[KU]], table[j + ROW[KV]], table[j + ROW[LU]], table[j + ROW[LV]], table[j + ROW[A10]],
             table[j + ROW[A1X]], table[j + ROW[A1Y]], table[j + ROW[B10]], table[j + ROW[B1X]],
             table[j + ROW[B1Y]], table[j + ROW[FUX]], table[j + ROW[FUY]], table[j + ROW[FUZ]],
             table[j + ROW[FVX]], table[j + ROW[FVY]], table[j + ROW[FVZ]], table[j + ROW[EX]], table[j + ROW[EY]],
             table[j + ROW[EZ]])
    else:
        f = FLAT_FIELD
    return c, f


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _fragment(s, c, f, clipping, curved, dx, dy, params):
    """Where the ray of the pixel at offset (dx, dy) meets the splat of geometry s, clip lines c
    and normal field f (splatting.glsl splat_distance and filter_distance), without branches:
    (kept, kernel distance², clamped eye depth, u, v, u² + v², clip excess, hit, 1/W). A ray
    that misses (parallel to the plane, or past the contour of a curved splat) has
    u² + v² = MISS and the centre's depth; `kept` is the test of both passes (inside the filter
    and the clip lines)."""
    mx, my, w0, wx, wy, z0, zx, zy, u0, ux, uy, v0, vx, vy, cz, radius, weight = s
    inv_lowpass2, no_lowpass, depth_clamp, depth_offset = params
    one = np.float32(1.0)
    w = w0 + wx * dx + wy * dy
    hit = abs(w) > np.float32(1e-12)
    iw = one / (w if hit else one)
    u = (u0 + ux * dx + uy * dy) * iw
    v = (v0 + vx * dx + vy * dy) * iw
    z = (z0 + zx * dx + zy * dy) * iw
    if curved:
        # Phong splatting's curved splat: the root of the ray-surface quadratic nearest the
        # plane's hit (splatting.glsl curved_splat_hit), moving t, u, v and the depth along d.
        ku, kv, lu, lv, a10, a1x, a1y, b10, b1x, b1y = f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8], f[9]
        a1, b1 = a10 + a1x * dx + a1y * dy, b10 + b1x * dx + b1y * dy
        a0, b0 = u * lu, v * lv
        half = np.float32(0.5)
        qa = half * (ku * a1 * a1 + kv * b1 * b1)
        qb = w + ku * a0 * a1 + kv * b0 * b1
        qc = half * (ku * a0 * a0 + kv * b0 * b0)
        disc = qb * qb - np.float32(4.0) * qa * qc
        hit = hit and disc >= 0
        root = math.sqrt(max(disc, np.float32(0.0)))
        h = -half * (qb + (-root if qb < 0 else root))
        dt = qc / (h if h != 0 else one) * np.float32(h != 0)  # no select of a division: LLVM makes it a branch
        u += a1 / max(lu, np.float32(1e-30)) * dt
        v += b1 / max(lv, np.float32(1e-30)) * dt
        z += dt
    extent = depth_clamp * radius
    z = min(max(z if hit else cz, cz - extent), cz + extent)
    u = u if hit else np.float32(0.0)
    v = v if hit else np.float32(0.0)
    rho2 = u * u + v * v if hit else MISS
    clipped = NO_CLIP
    if clipping:
        excess = max(c[0] * u + c[1] * v - c[2], c[3] * u + c[4] * v - c[5])
        clipped = excess if hit else NO_CLIP
    kernel2 = min(rho2, (dx * dx + dy * dy) * inv_lowpass2 + no_lowpass)
    kept = kernel2 <= 1 and clipped <= 0
    return kept, kernel2, z, u, v, rho2, clipped, hit, iw


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _visibility(s, c, f, clipping, curved, dx, dy, params):
    """A fragment's visibility-pass output (splatting.glsl PASS_VISIBILITY): its depth + z_t
    (FAR when discarded) and its coverage of the pixel (0 when discarded), 0.5 + the signed
    distance in pixels to the splat's edge, where rho = max(|(u, v)|, 1 + clip excess) is 1,
    from rho's screen-space gradient (analytic here, a quad's differences on the GPU), and at
    least the footprint of a pixel-wide disk at the projected centre (sub-pixel splats)."""
    kept, kernel2, z, u, v, rho2, clipped, hit, iw = _fragment(s, c, f, clipping, curved, dx, dy, params)
    mx, my, w0, wx, wy, z0, zx, zy, u0, ux, uy, v0, vx, vy, cz, radius, weight = s
    depth_offset = params[3]
    one, tiny = np.float32(1.0), np.float32(1e-6)
    # d(u, v)/d(dx, dy) of u = (u W) / W: the plane's, also for a curved splat
    dux, duy = (ux - u * wx) * iw, (uy - u * wy) * iw
    dvx, dvy = (vx - v * wx) * iw, (vy - v * wy) * iw
    rho = math.sqrt(rho2 if hit else one)
    # grad rho = (u grad u + v grad v) / rho (bounded at the centre, where the edge is far anyway)
    inv_rho = one / max(rho, np.float32(1e-12))
    gx, gy = (u * dux + v * dvx) * inv_rho, (u * duy + v * dvy) * inv_rho
    distance, gradient = one - rho, math.sqrt(gx * gx + gy * gy)
    if clipping:  # past a clip line, rho is 1 + its excess: the gradient of that line
        first = c[0] * u + c[1] * v - c[2] >= c[3] * u + c[4] * v - c[5]
        a, b = (c[0] if first else c[3]), (c[1] if first else c[4])
        lx, ly = a * dux + b * dvx, a * duy + b * dvy
        cut = one + clipped > rho
        distance = -clipped if cut else distance
        gradient = math.sqrt(lx * lx + ly * ly) if cut else gradient
    edge = distance / max(gradient, tiny)  # one division of selected operands: SIMD-safe
    edge = max(edge if hit else np.float32(-1e30), np.float32(0.5) - math.sqrt(dx * dx + dy * dy))
    coverage = min(max(np.float32(0.5) + edge, np.float32(0.0)), one)
    # a low-pass fragment off the disk hides nothing nearer than the disk's far end
    z = max(z, cz + radius) if hit and rho2 > 1 else z
    return (z + depth_offset * radius if kept else FAR), (coverage if kept else np.float32(0.0))


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _gaussian(kernel2):
    """The Gaussian weight exp(-GAUSSIAN_SHARPNESS kernel2) of splatting.py's lookup table,
    sampled at its texel centres (kernel2 clamped to the first and last)."""
    lo, hi = np.float32(0.5 / KERNEL_SIZE), np.float32(1.0 - 0.5 / KERNEL_SIZE)
    s = np.float32(2.0) * min(max(kernel2, lo), hi) - np.float32(1.0)
    acc = EXP_POLY[9]
    for k in range(8, -1, -1):
        acc = acc * s + EXP_POLY[k]
    return acc


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _attribute(s, c, f, clipping, curved, dx, dy, params, nx, ny, nz):
    """A fragment's attribute-pass output before its depth test: weight (0 when discarded), eye
    depth and normal: the splat's (nx, ny, nz), or with a normal field Phong splatting's
    N(u, v) = n + u alpha e_u + v beta e_v (eq. 8), unit and turned no further than edge-on
    (gl/common.glsl field_normal)."""
    kept, kernel2, z, u, v, rho2, clipped, hit, iw = _fragment(s, c, f, clipping, curved, dx, dy, params)
    w = s[16] * _gaussian(kernel2)
    if curved:
        fux, fuy, fuz, fvx, fvy, fvz, ex, ey, ez = f[10], f[11], f[12], f[13], f[14], f[15], f[16], f[17], f[18]
        nx, ny, nz = nx + u * fux + v * fvx, ny + u * fuy + v * fvy, nz + u * fuz + v * fvz
        away = min(nx * ex + ny * ey + nz * ez, np.float32(0.0))
        nx, ny, nz = nx - away * ex, ny - away * ey, nz - away * ez
        inv = np.float32(1.0) / max(math.sqrt(nx * nx + ny * ny + nz * nz), np.float32(1e-30))
        nx, ny, nz = nx * inv, ny * inv, nz * inv
    return (w if kept else np.float32(0.0)), z, nx, ny, nz


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def _blend(acc, p, w, z, r, g, b, nx, ny, nz):
    """The attribute pass's additive blend of one fragment of weight w into pixel p: the place
    where a further channel (a scalar, or a categorical winner) would join."""
    acc[0, p] += w * r
    acc[1, p] += w * g
    acc[2, p] += w * b
    acc[3, p] += w
    acc[4, p] += w * nx
    acc[5, p] += w * ny
    acc[6, p] += w * nz
    acc[7, p] += w * z


@nb.njit(fastmath=True, error_model="numpy")
def _visibility_tile(table, ibox, count, ox, oy, params, clip_src, field_src, tmp, zb, cov):
    """The visibility pass of a tile's `count` splats into zb (MIN of depth + z_t) and cov (MAX of
    coverage): per table block, the 2x2 blocks at the top-left of the boxes in one SIMD loop,
    blended one splat after another (a block's splats may overlap), then the rest of the larger
    boxes pixel by pixel."""
    clipping, curved = clip_src is not None, field_src is not None
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    for first in range(0, count, BLOCK):
        size = min(BLOCK, count - first)
        base, box_base = _slot(first, TABLE_ROWS), _slot(first, 4)
        for q in range(size):
            uq = np.uint64(q)
            j, jb = base + uq, box_base + uq
            s = _geometry(table, j)
            c, f = _extras(table, clip_src, field_src, j)
            x0, y0 = ibox[jb + TEMP[0]], ibox[jb + TEMP[2]]
            wide, tall = ibox[jb + TEMP[1]] > x0, ibox[jb + TEMP[3]] > y0
            dx, dy = np.float32(x0 + ox) + half - s[0], np.float32(y0 + oy) + half - s[1]
            z, cover = _visibility(s, c, f, clipping, curved, dx, dy, params)
            tmp[TEMP[0] + uq], tmp[TEMP[4] + uq] = z, cover
            z, cover = _visibility(s, c, f, clipping, curved, dx + one, dy, params)
            tmp[TEMP[1] + uq], tmp[TEMP[5] + uq] = (z if wide else FAR), (cover if wide else zero)
            z, cover = _visibility(s, c, f, clipping, curved, dx, dy + one, params)
            tmp[TEMP[2] + uq], tmp[TEMP[6] + uq] = (z if tall else FAR), (cover if tall else zero)
            z, cover = _visibility(s, c, f, clipping, curved, dx + one, dy + one, params)
            corner = wide and tall
            tmp[TEMP[3] + uq], tmp[TEMP[7] + uq] = (z if corner else FAR), (cover if corner else zero)
        for q in range(size):
            uq = np.uint64(q)
            jb = box_base + uq
            x0, x1, y0, y1 = ibox[jb + TEMP[0]], ibox[jb + TEMP[1]], ibox[jb + TEMP[2]], ibox[jb + TEMP[3]]
            p = y0 * STRIDE + x0
            for lane in range(4):
                pl = p + (lane >> 1) * STRIDE + (lane & 1)
                zb[pl] = min(zb[pl], tmp[TEMP[lane] + uq])
                cov[pl] = max(cov[pl], tmp[TEMP[4 + lane] + uq])
            if x1 - x0 < 2 and y1 - y0 < 2:
                continue
            j = base + uq
            s = _geometry(table, j)
            c, f = _extras(table, clip_src, field_src, j)
            for y in range(y0, y1 + 1):
                dy = np.float32(y + oy) + half - s[1]
                for x in range(x0 + 2 if y < y0 + 2 else x0, x1 + 1):
                    z, cover = _visibility(s, c, f, clipping, curved, np.float32(x + ox) + half - s[0], dy, params)
                    pl = y * STRIDE + x
                    zb[pl] = min(zb[pl], z)
                    cov[pl] = max(cov[pl], cover)


@nb.njit(fastmath=True, error_model="numpy")
def _attribute_tile(table, ibox, count, ox, oy, params, clip_src, field_src, tmp, zb, acc, levels, best):
    """The attribute pass of a tile's `count` splats: the weighted sums of the fragments no
    farther than zb into acc, block by block as `_visibility_tile`. With `levels` > 0 (a
    categorical colour mode, whose splats carry their palette index k as k / CODE_SCALE in
    red), `best` keeps per pixel the MAX of category_pack(w, k): the heaviest splat's category
    (splatting.glsl PASS_CATEGORY), never a blend."""
    clipping, curved = clip_src is not None, field_src is not None
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    for first in range(0, count, BLOCK):
        size = min(BLOCK, count - first)
        base, box_base = _slot(first, TABLE_ROWS), _slot(first, 4)
        for q in range(size):
            uq = np.uint64(q)
            j, jb = base + uq, box_base + uq
            s = _geometry(table, j)
            c, f = _extras(table, clip_src, field_src, j)
            nx, ny, nz = table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]
            x0, y0 = ibox[jb + TEMP[0]], ibox[jb + TEMP[2]]
            wide, tall = ibox[jb + TEMP[1]] > x0, ibox[jb + TEMP[3]] > y0
            dx, dy = np.float32(x0 + ox) + half - s[0], np.float32(y0 + oy) + half - s[1]
            w, z, fx, fy, fz = _attribute(s, c, f, clipping, curved, dx, dy, params, nx, ny, nz)
            tmp[TEMP[0] + uq], tmp[TEMP[4] + uq] = w, z
            if curved:
                tmp[TEMP[8] + uq], tmp[TEMP[12] + uq], tmp[TEMP[16] + uq] = fx, fy, fz
            w, z, fx, fy, fz = _attribute(s, c, f, clipping, curved, dx + one, dy, params, nx, ny, nz)
            tmp[TEMP[1] + uq], tmp[TEMP[5] + uq] = (w if wide else zero), z
            if curved:
                tmp[TEMP[9] + uq], tmp[TEMP[13] + uq], tmp[TEMP[17] + uq] = fx, fy, fz
            w, z, fx, fy, fz = _attribute(s, c, f, clipping, curved, dx, dy + one, params, nx, ny, nz)
            tmp[TEMP[2] + uq], tmp[TEMP[6] + uq] = (w if tall else zero), z
            if curved:
                tmp[TEMP[10] + uq], tmp[TEMP[14] + uq], tmp[TEMP[18] + uq] = fx, fy, fz
            w, z, fx, fy, fz = _attribute(s, c, f, clipping, curved, dx + one, dy + one, params, nx, ny, nz)
            tmp[TEMP[3] + uq], tmp[TEMP[7] + uq] = (w if wide and tall else zero), z
            if curved:
                tmp[TEMP[11] + uq], tmp[TEMP[15] + uq], tmp[TEMP[19] + uq] = fx, fy, fz
        for q in range(size):
            uq = np.uint64(q)
            j, jb = base + uq, box_base + uq
            x0, x1, y0, y1 = ibox[jb + TEMP[0]], ibox[jb + TEMP[1]], ibox[jb + TEMP[2]], ibox[jb + TEMP[3]]
            r, g, b = table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]]
            nx, ny, nz = table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]
            code = math.floor(r * np.float32(CODE_SCALE) + np.float32(0.5))
            p = y0 * STRIDE + x0
            for lane in range(4):
                pl = p + (lane >> 1) * STRIDE + (lane & 1)
                w, z = tmp[TEMP[lane] + uq], tmp[TEMP[4 + lane] + uq]
                if w > 0 and z <= zb[pl]:
                    if levels > 0:
                        best[pl] = max(best[pl], category_pack(w, code, levels))
                    if curved:
                        _blend(acc, pl, w, z, r, g, b, tmp[TEMP[8 + lane] + uq], tmp[TEMP[12 + lane] + uq],
                               tmp[TEMP[16 + lane] + uq])
                    else:
                        _blend(acc, pl, w, z, r, g, b, nx, ny, nz)
            if x1 - x0 < 2 and y1 - y0 < 2:
                continue
            s = _geometry(table, j)
            c, f = _extras(table, clip_src, field_src, j)
            for y in range(y0, y1 + 1):
                dy = np.float32(y + oy) + half - s[1]
                for x in range(x0 + 2 if y < y0 + 2 else x0, x1 + 1):
                    w, z, fx, fy, fz = _attribute(s, c, f, clipping, curved, np.float32(x + ox) + half - s[0], dy,
                                                  params, nx, ny, nz)
                    pl = y * STRIDE + x
                    if w > 0 and z <= zb[pl]:
                        if levels > 0:
                            best[pl] = max(best[pl], category_pack(w, code, levels))
                        _blend(acc, pl, w, z, r, g, b, fx, fy, fz)


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


@nb.njit(parallel=True, fastmath=True, error_model="numpy", cache=True)
def rasterize_tiles(packed, extras, box, index, tile_start, tile_count, order, tiles_x, width, height, m,
                    radius_scale, lowpass, depth_offset, depth_clamp, clip_src, field_src, per_splat_model,
                    deferred_model, color_mode, palette, levels, background, composite, tables, boxes, temp, zbuf,
                    cover, accum, best, present, color, alpha, depth, normals, indices):
    """Every tile of `order`, written into color (H, W, 3), alpha, depth (H, W) and normals
    (H, W, 3). `present` (H, W) uint8 gets, per pixel, 0 (no splat), 1, or 2 where
    `finish_surrounded` must still decide whether its neighbours in other tiles make it whole
    (the pixel then holds its raw colour and its own coverage). Each thread's scratch: tables
    (threads, table_size(largest tile)), boxes (threads, 4 x that), temp (threads,
    TEMP_ROWS x BLOCK), zbuf, cover (threads, STRIDE²), accum (threads, LAYER, STRIDE²).
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
    params = (np.float32(1.0) / max(lowpass2, np.float32(1e-30)), zero if ewa_filter else NO_LOWPASS, depth_clamp,
              depth_offset)
    categorical = color_mode == COLOR_CATEGORICAL
    for k in nb.prange(order.shape[0]):
        t = order[k]
        ox, oy = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        tw, th = min(TILE, width - ox), min(TILE, height - oy)
        count = tile_count[t]
        if count == 0:
            for y in range(oy, oy + th):
                for x in range(ox, ox + tw):
                    present[y, x] = 0
                    _write(color, alpha, depth, normals, y, x, zero, zero, zero, zero, zero, zero, zero, zero,
                           background, composite)
                    if categorical:
                        indices[y, x] = -1
            continue
        thread = nb.get_thread_id()
        table, ibox, tmp = tables[thread], boxes[thread], temp[thread]
        zb, cov, acc = zbuf[thread], cover[thread], accum[thread]
        # stage the tile's splats: one packed row each, its extras and its box
        start = tile_start[t]
        for slot in range(count):
            i = index[start + slot]
            j, jb = _slot(slot, TABLE_ROWS), _slot(slot, 4)
            for col in range(PACKED):
                table[j + np.uint64(col * BLOCK)] = packed[i, col]
            if extras is not None:
                for col in range(EXTRAS):
                    table[j + np.uint64((PACKED + col) * BLOCK)] = extras[i, col]
            for col in range(4):
                ibox[jb + np.uint64(col * BLOCK)] = box[i, col]
        _setup_tile(table, ibox, count, ox, oy, m, radius_scale, lowpass2, ewa_filter, clip_src, field_src)
        if per_splat_model >= 0:  # Botsch & Kobbelt 2003: each splat's colour shaded, then blended
            for slot in range(count):
                j = _slot(slot, TABLE_ROWS)
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
        _visibility_tile(table, ibox, count, ox, oy, params, clip_src, field_src, tmp, zb, cov)
        _attribute_tile(table, ibox, count, ox, oy, params, clip_src, field_src, tmp, zb, acc,
                        levels if categorical else 0, category)
        # normalization and deferred shading, straight into the output
        for ly in range(th):
            y = oy + ly
            for lx in range(tw):
                x = ox + lx
                p = ly * STRIDE + lx
                if acc[3, p] <= 0:
                    present[y, x] = 0
                    _write(color, alpha, depth, normals, y, x, zero, zero, zero, zero, zero, zero, zero, zero,
                           background, composite)
                    if categorical:
                        indices[y, x] = -1
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
