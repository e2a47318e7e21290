"""Binning of the CPU backends of `gaussian`, `deferred` and `phong` (splatting_kernels.py
rasterizes what this sorts; splatting_cpu.py states the equations), and the camera arithmetic
both stages share.

1. `bound_splats` (parallel over chunks of splats): each splat's pixel box, as the GPU's quad
   (the projected corners of its disk's bounding square, and the low-pass disk), and culling
   (conservative: the fragment tests decide which pixels it covers), for BOUND_BLOCK splats at
   a time in one SIMD loop (`bound_block`); then how many splats of the chunk meet each
   TILE x TILE screen tile.
2. `tile_offsets` (serial over tiles) and `place_splats` (parallel over chunks): an index
   list per tile of the splats meeting it, in draw order.

The camera reaches the kernels as splatting_cpu._camera's float32 array, unpacked into scalars
(`camera_scalars`) before the SIMD loops: an array read there would keep them scalar.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .splatting_tiles import EC0, EC1, PNX, PNY, PNZ, PUX, PUY, PUZ, PVX, PVY, PVZ, PX, PY, PZ, TILE_BITS, face_camera

BOUND_BLOCK = 1024  # splats whose boxes bound_splats computes before counting them (in cache)
FRONT = np.float32(-1e30)  # bound_splats' nearest depth of a splat facing the camera: none lies in front of it
NEAREST_SHRINK, EXTENT_MARGIN = np.float32(1.0 - 1e-6), np.float32(1.01)


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def eye_space(m, x, y, z):
    """Rotate (m[0..8] row-major), then translate (m[9..11])."""
    return (m[0] * x + m[1] * y + m[2] * z + m[9], m[3] * x + m[4] * y + m[5] * z + m[10],
            m[6] * x + m[7] * y + m[8] * z + m[11])


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def rotate(m, x, y, z):
    """Rotate only (m[0..8] row-major)."""
    return m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z, m[6] * x + m[7] * y + m[8] * z


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def to_pixels(x, y, z, m):
    """Image position of an eye-space point (splatting.glsl to_pixels); m[12..16] = fx, fy, cx,
    cy, pixels per unit of an orthographic camera (0: perspective). A point at or behind the
    eye gets a finite stand-in (no splat uses it)."""
    fx, fy, cx, cy, ortho = m[12], m[13], m[14], m[15], m[16]
    inv = np.float32(-1.0) / min(z, np.float32(-1e-30))
    px, py = cx + fx * x * inv, cy - fy * y * inv
    return (cx + ortho * x if ortho > 0 else px), (cy - ortho * y if ortho > 0 else py)


@nb.njit(inline="always")
def camera_scalars(m):
    """The frame's camera array as a tuple: scalars for the SIMD loops (see the module docstring)."""
    return (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10], m[11], m[12], m[13], m[14], m[15],
            m[16], m[17], m[18])


@nb.njit(parallel=True, fastmath=True, error_model="numpy", cache=True)
def bound_splats(packed, extras, m, radius_scale, lowpass, backface, depth_clamp, width, height, box, hiding, nearest,
                 tiles_x, counts, scratch):
    """Each splat's pixel box in `box` (4, N) int32, as the GPU's quad (splatting.glsl): the
    pixel centres inside the projected corners of the disk's bounding square and, with the EWA
    filter, the low-pass disk of `lowpass` pixels around the projected centre (x0, x1, y0, y1
    inclusive; x0 > x1 marks a culled splat). A splat with a corner behind the near plane gets
    the whole image. `nearest` (N,) float32: for a splat seen from its back, an eye depth that
    none of its fragments lies in front of (its centre's, less `depth_clamp` times its larger
    semi-axis: the clamp of splatting_tiles.fragment), which lets a tile pass it by where the
    splats facing the camera cover its box in front of that (splatting_kernels.rasterize_tiles);
    FRONT for the others. With `hiding` False every splat counts as facing the camera in the
    tiles' lists, which then keep the draw order. m: the frame's camera (splatting_cpu._camera).
    In the same pass, binning's count: counts (2 chunks, tiles) gets how many splats of each
    chunk of the cloud (one thread each) meet each TILE x TILE tile, those facing the camera in
    row `chunk`, the others in row chunks + chunk (so that a tile's list holds the first before
    the others). scratch (chunks, 4 BOUND_BLOCK) int32: each chunk's boxes of BOUND_BLOCK splats,
    computed in one SIMD loop before they are counted."""
    n = packed.shape[1]
    cam = camera_scalars(m)
    chunks = counts.shape[0] // 2
    step = (n + chunks - 1) // chunks
    for chunk in nb.prange(chunks):
        front_row, back_row = counts[chunk], counts[chunks + chunk]
        front_row[:] = 0
        back_row[:] = 0
        bounds = scratch[chunk]
        end = min(chunk * step + step, n)
        for first in range(chunk * step, end, BOUND_BLOCK):
            last = min(first + BOUND_BLOCK, end)
            bound_block(packed, extras, cam, radius_scale, lowpass, backface, depth_clamp, width, height, bounds,
                        nearest, first, last)
            for i in range(first, last):
                slot = i - first
                x0, x1 = bounds[slot], bounds[slot + BOUND_BLOCK]
                y0, y1 = bounds[slot + 2 * BOUND_BLOCK], bounds[slot + 3 * BOUND_BLOCK]
                box[0, i], box[1, i], box[2, i], box[3, i] = x0, x1, y0, y1
                if x0 > x1:
                    continue
                row = back_row if hiding and nearest[i] != FRONT else front_row  # as place_splats sorts them
                for ty in range(y0 >> TILE_BITS, (y1 >> TILE_BITS) + 1):
                    for tx in range(x0 >> TILE_BITS, (x1 >> TILE_BITS) + 1):
                        row[ty * tiles_x + tx] += 1


@nb.njit(fastmath=True, error_model="numpy")
def bound_block(packed, extras, cam, radius_scale, lowpass, backface, depth_clamp, width, height, bounds, nearest,
                first, last):
    """bound_splats' boxes and nearest depths of splats first..last-1, without branches (a SIMD loop)."""
    ortho, near = cam[16], cam[17]
    one = np.float32(1.0)
    for index in range(first, last):
        # the packed column read element by element: a column view would bring reference counting,
        # an atomic shared by every thread, into the loop; unsigned, as no wraparound test is needed
        i = np.uint64(index)
        ex, ey, ez = eye_space(cam, packed[PX, i], packed[PY, i], packed[PZ, i])
        nx, ny, nz = rotate(cam, packed[PNX, i], packed[PNY, i], packed[PNZ, i])
        ux, uy, uz = rotate(cam, packed[PUX, i] * radius_scale, packed[PUY, i] * radius_scale,
                           packed[PUZ, i] * radius_scale)
        vx, vy, vz = rotate(cam, packed[PVX, i] * radius_scale, packed[PVY, i] * radius_scale,
                           packed[PVZ, i] * radius_scale)
        nx, ny, nz, ux, uy, uz, vx, vy, vz = face_camera(ex, ey, ez, nx, ny, nz, ux, uy, uz, vx, vy, vz, ortho)
        depth = -ez
        perspective = ortho <= 0
        lu, lv = math.sqrt(ux * ux + uy * uy + uz * uz), math.sqrt(vx * vx + vy * vy + vz * vz)
        reach = lu + lv
        away = (nz if ortho > 0 else -(nx * ex + ny * ey + nz * ez)) < 0
        culled = (backface & away) | (perspective & (depth + reach < near))  # or wholly behind the near plane
        # the margins cover the rounding of the same arithmetic in splatting_kernels._setup
        nearest[i] = depth * NEAREST_SHRINK - EXTENT_MARGIN * depth_clamp * max(lu, lv) if away else FRONT
        if extras is not None:  # cut away whole (a point on a crease)
            culled |= (extras[EC0, i] < -1) | (extras[EC1, i] < -1)
        whole = perspective & (depth - abs(uz) - abs(vz) < near)  # a corner behind it: the whole image
        lo_x = lo_y = np.float32(1e30)
        hi_x = hi_y = np.float32(-1e30)
        for corner in range(4):
            su = -one if corner & 1 == 0 else one
            sv = -one if corner < 2 else one
            sx, sy = to_pixels(ex + su * ux + sv * vx, ey + su * uy + sv * vy, ez + su * uz + sv * vz, cam)
            lo_x, lo_y, hi_x, hi_y = min(lo_x, sx), min(lo_y, sy), max(hi_x, sx), max(hi_y, sy)
        if lowpass > 0:
            mx, my = to_pixels(ex, ey, ez, cam)
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
        slot = index - first
        bounds[slot] = 1 if empty else x0
        bounds[slot + BOUND_BLOCK] = 0 if empty else x1
        bounds[slot + 2 * BOUND_BLOCK] = 1 if empty else y0
        bounds[slot + 3 * BOUND_BLOCK] = 0 if empty else y1


@nb.njit(cache=True)
def tile_offsets(counts, tile_start, tile_count, tile_front):
    """Binning's prefix sum, tile-major and row-minor so that each tile's splats stay in draw
    order, those facing the camera first: counts (2 chunks, tiles), from bound_splats, becomes
    each row's first place in the index list of each tile, tile t's list being
    index[tile_start[t]:tile_start[t] + tile_count[t]], its first tile_front[t] facing the
    camera. Returns (tile-splat pairs, largest tile count)."""
    rows, tiles = counts.shape
    total, largest = 0, 0
    for t in range(tiles):
        tile_start[t] = total
        for row in range(rows):
            if row == rows // 2:
                tile_front[t] = total - tile_start[t]
            count = counts[row, t]
            counts[row, t] = total
            total += count
        tile_count[t] = total - tile_start[t]
        largest = max(largest, tile_count[t])
    return total, largest


@nb.njit(parallel=True, cache=True)
def place_splats(box, hiding, nearest, tiles_x, places, index):
    """Binning's scatter: each chunk's splats (one thread each) into the index lists of the
    tiles they meet, from `places` (2 chunks, tiles), which tile_offsets made; `hiding` and
    `nearest` as bound_splats had them."""
    n = box.shape[1]
    chunks = places.shape[0] // 2
    step = (n + chunks - 1) // chunks
    for chunk in nb.prange(chunks):
        for i in range(chunk * step, min(chunk * step + step, n)):
            if box[0, i] > box[1, i]:
                continue
            row = places[chunks + chunk] if hiding and nearest[i] != FRONT else places[chunk]
            tx0, tx1 = box[0, i] >> TILE_BITS, box[1, i] >> TILE_BITS
            for ty in range(box[2, i] >> TILE_BITS, (box[3, i] >> TILE_BITS) + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    index[row[t]] = i
                    row[t] += 1
