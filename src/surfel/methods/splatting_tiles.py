"""The per-tile passes of the CPU backends of `gaussian`, `deferred` and `phong`
(splatting_kernels.py drives them; splatting_cpu.py states the equations, splatting.glsl is
the GPU program they reproduce): the layout of a tile's splat table, and what one fragment
of a splat computes in the visibility pass and in the attribute pass (splatting.glsl
splat_distance, filter_distance, PASS_VISIBILITY and PASS_ATTRIBUTE), per table block.

The table holds BLOCK splats at a time, row after row (an array of structures of arrays): a
row of a block is contiguous and the rows lie at fixed distances, so that a loop over a
block's splats loads and stores each row as a vector, with no aliasing check for the compiler
to add. `visibility_tile` computes the 2x2 pixels at the top-left of each splat's box (all of
a splat smaller than the low-pass, the common case of a dense cloud) for a whole block in one
loop without branches, which the compiler turns into SIMD code: both passes' outputs from one
intersection of each ray with the splat, the attribute pass's kept for `attribute_tile`. Each
pass blends them into the tile one splat after another. The rest of a larger box comes in
further 2x2 blocks, copies of the splat's record drawn by the same loops (`visible_splats`), so
that no fragment is computed outside them. Per-fragment arithmetic is float32 under fastmath,
with error_model="numpy" (no division checks, which would keep the loops scalar); masked lanes
select finite values, so no infinity or NaN is computed ("no depth yet" is the finite FAR).
Helpers called inside the SIMD loops take scalars only: an array argument brings reference
counting into the loop, which keeps it scalar. So do a loop inside them (LLVM vectorizes
innermost loops), a call, and a tuple indexed by a loop variable (numba makes it a switch);
tests/test_splatting_cpu.py checks that the compiled loops use packed instructions. The
helpers are inlined: the small ones by numba (inline="always"), the per-fragment ones a loop
calls several times (`both_outputs` and splatting_kernels._setup) by LLVM (forceinline=True),
which leaves the same SIMD code; numba's own inlining of them made `rasterize_tiles` take 58 s
to compile instead of 37 (`deferred`'s signature, of four).

A categorical colour mode keeps per pixel the packed (weight level, palette index) of the
heaviest fragment (colors.category_pack, MAX as the GPU's PASS_CATEGORY blending).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.polynomial import chebyshev

from ..colors import CODE_SCALE, category_pack
from .ewa_kernels import FAR, TILE
from .splatting import GAUSSIAN_SHARPNESS, KERNEL_SIZE

# Rows of a cloud's packed inputs (splatting_cpu.pack_splats): one column per splat; PT its
# layer's thickness, the cap of z_t (0: none).
(PX, PY, PZ, PNX, PNY, PNZ, PUX, PUY, PUZ, PVX, PVY, PVZ, PR, PG, PB, PT) = range(16)
PACKED = 16
# Rows of its extras: two clip lines a u + b v <= c (surfel.preprocess), the normal field's
# slopes alpha, beta that shade it (Phong splatting) and those that shape a curved splat.
(EA0, EB0, EC0, EA1, EB1, EC1, EALPHA, EBETA, ECURVE_ALPHA, ECURVE_BETA) = range(10)
EXTRAS = 10
# Rows of a tile's table. The first PACKED + EXTRAS rows are the staged inputs. Then the
# setup's record: the projected centre (MX, MY); with (dx, dy) a pixel centre's offset from
# it, W = W0 + WX dx + WY dy, depth W = Z0 + ZX dx + ZY dy, u W = U0 + UX dx + UY dy and
# v W likewise; the centre's eye depth CZ; the largest semi-axis RAD; the EWA weight WT; z_t
# ZT; the low-pass footprint's share FT; the albedo (or per-splat shaded colour); the eye
# normal, turned to face the camera.
STAGED = PACKED + EXTRAS
(MX, MY, W0, WX, WY, Z0, ZX, ZY, U0, UX, UY, V0, VX, VY, CZ, RAD, WT, ZT, FT, R, G, B, NX, NY, NZ) = range(
    STAGED, STAGED + 25)
# The clip lines (c over radius_scale: the scaled splat's coordinates).
(C0A, C0B, C0C, C1A, C1B, C1C) = range(NZ + 1, NZ + 7)
# Phong splatting's normal field: the curvatures KU = alpha / |u_j|, KV; the semi-axes LU, LV;
# d.e_u = A10 + A1X dx + A1Y dy and d.e_v (B1*) along the unit axes; the field's eye-space
# slopes alpha e_u (FU*) and beta e_v (FV*); the unit direction to the eye (E*).
(KU, KV, LU, LV, A10, A1X, A1Y, B10, B1X, B1Y, FUX, FUY, FUZ, FVX, FVY, FVZ, EX, EY, EZ) = range(C1C + 1,
                                                                                                 C1C + 20)
CURVE_VALUES = B1Y - KU + 1  # KU..B1Y: what curves the splat; the rest shade it (`phong`)
TABLE_ROWS = EZ + 1
BLOCK_BITS = 6
BLOCK = 1 << BLOCK_BITS
ROW = tuple(np.uint64(row * BLOCK) for row in range(TABLE_ROWS))  # a row's offset inside a block
TILE_BITS = TILE.bit_length() - 1  # TILE is a power of two: a pixel's tile is pixel >> TILE_BITS
STRIDE = TILE + 2  # row stride of the tile scratch: a splat's 2x2 block may reach one past the tile
# A pixel's accumulators, side by side (a fragment's blend then writes one cache line): the GL
# attribute pass's two targets, w r, w g, w b, w, w n, w depth
LAYER = 8
TEMP_ROWS = 8  # a block's visibility results: 4 lanes each of depth and coverage
TEMP = tuple(np.uint64(row * BLOCK) for row in range(TEMP_ROWS))
# A block's attribute-pass results, computed with its visibility results (one ray-splat
# intersection serves both passes) and kept until the attribute pass: 4 lanes each of w,
# depth and 3 normal components.
KEPT_ROWS = 20
KEPT = tuple(np.uint64(row * BLOCK) for row in range(KEPT_ROWS))
# The pixels of a box beyond its top-left 2x2 come as further 2x2 blocks, each a copy of its
# splat's record in a second table of SPLIT_BLOCKS slots, drawn by the same SIMD loops
# (`visible_splats`).
SPLIT_BLOCKS = 4 * BLOCK
MISS = np.float32(1e30)  # the squared kernel distance of a ray that misses the splat
NO_CLIP = np.float32(-1e30)
CREASE_BLEND = np.float32(0.5)  # splatting.glsl's: an attribute fragment's reach past a clip line
CREASE_BLEND_DEPTH = np.float32(2.0)  # splatting.glsl's: z_t's in front of the visible depth it may lie there
NO_LOWPASS = np.float32(2.0)  # added to the low-pass distance when the EWA filter is off: never <= 1
INACTIVE_LINES = tuple(np.float32(c) for c in (0, 0, 1, 0, 0, 1))  # clip lines that cut nothing
FLAT_FIELD = tuple(np.float32(0) for _ in range(19))  # no normal field
# exp(-t) on [0, GAUSSIAN_SHARPNESS] as a polynomial in s = 2 t / GAUSSIAN_SHARPNESS - 1 (Chebyshev
# interpolation, relative error below 1e-6): the weight in SIMD code, where math.exp stays scalar
EXP_POLY = tuple(np.float32(c) for c in chebyshev.cheb2poly(chebyshev.chebinterpolate(
    lambda s: np.exp(-0.5 * GAUSSIAN_SHARPNESS * (s + 1)), 9)))


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def face_camera(ex, ey, ez, nx, ny, nz, ux, uy, uz, vx, vy, vz, ortho):
    """gl/common.glsl face_camera without branches: a splat packed with a zero normal (no
    orientation, surfel.preprocess.structure) gets the direction to the eye as its normal and
    its axes, their lengths kept, turned perpendicular to it (u along (0, 1, 0) x n); the
    eye-space (normal, u, v), unchanged for every other splat."""
    one, zero = np.float32(1.0), np.float32(0.0)
    unoriented = nx * nx + ny * ny + nz * nz <= np.float32(0.25)
    inv_d = one / max(math.sqrt(ex * ex + ey * ey + ez * ez), np.float32(1e-30))
    tx, ty, tz = (zero if ortho > 0 else -ex * inv_d), (zero if ortho > 0 else -ey * inv_d), \
        (one if ortho > 0 else -ez * inv_d)
    rx, rz = tz, -tx  # (0, 1, 0) x n: zero only for a centre on the eye's vertical
    length2 = rx * rx + rz * rz
    inv_r = one / math.sqrt(max(length2, np.float32(1e-30)))
    turned = length2 > np.float32(1e-12)
    rx, rz = (rx * inv_r if turned else one), (rz * inv_r if turned else zero)
    lu, lv = math.sqrt(ux * ux + uy * uy + uz * uz), math.sqrt(vx * vx + vy * vy + vz * vz)
    su = (rx * lu, zero, rz * lu)
    sv = (ty * rz * lv, (tz * rx - tx * rz) * lv, -ty * rx * lv)  # n x right
    if unoriented:
        return tx, ty, tz, su[0], su[1], su[2], sv[0], sv[1], sv[2]
    return nx, ny, nz, ux, uy, uz, vx, vy, vz


def table_size(count: int, rows: int = TABLE_ROWS) -> int:
    """Entries of a table of `rows` rows for `count` splats (whole blocks)."""
    return -(-count // BLOCK) * BLOCK * rows


@nb.njit(inline="always")
def table_slot(k, rows):
    """Where the splat at slot k lies in a table of `rows` rows (unsigned: no negative-index
    wrap, which would keep loads from being vectors)."""
    return np.uint64((k >> BLOCK_BITS) * (rows * BLOCK) + (k & (BLOCK - 1)))


@nb.njit(inline="always")
def splat_geometry(table, j):
    """The rows MX..ZT of the splat at table slot j: what every fragment of it needs."""
    return (table[j + ROW[MX]], table[j + ROW[MY]], table[j + ROW[W0]], table[j + ROW[WX]], table[j + ROW[WY]],
            table[j + ROW[Z0]], table[j + ROW[ZX]], table[j + ROW[ZY]], table[j + ROW[U0]], table[j + ROW[UX]],
            table[j + ROW[UY]], table[j + ROW[V0]], table[j + ROW[VX]], table[j + ROW[VY]], table[j + ROW[CZ]],
            table[j + ROW[RAD]], table[j + ROW[WT]], table[j + ROW[ZT]], table[j + ROW[FT]])


@nb.njit(inline="always")
def splat_extras(table, clip_src, field_src, j):
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
def curved_quadratic(f, w, u, v, dx, dy):
    """The coefficients (qa, qb, qc) of the ray-surface quadratic of a curved splat with normal
    field f at the pixel offset (dx, dy), whose ray meets the plane at (u, v) with W = w
    (splatting.glsl curved_quadratic), and the ray's tangent components (a1, b1)."""
    ku, kv, lu, lv, a10, a1x, a1y, b10, b1x, b1y = f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8], f[9]
    a1, b1 = a10 + a1x * dx + a1y * dy, b10 + b1x * dx + b1y * dy
    a0, b0 = u * lu, v * lv
    half = np.float32(0.5)
    return (half * (ku * a1 * a1 + kv * b1 * b1), w + ku * a0 * a1 + kv * b0 * b1,
            half * (ku * a0 * a0 + kv * b0 * b0), a1, b1)


@nb.njit(fastmath=True, error_model="numpy", cache=True)
def curved_discriminant(s, f, dx, dy):
    """The discriminant of a curved splat's ray-surface quadratic at the pixel offset (dx, dy):
    negative where the ray passes beyond the splat's contour (splatting.glsl). Compiled apart,
    not inlined into its fifteen call sites, which cost 27 s more of compilation for the three
    methods and rendered no faster."""
    w0, wx, wy, u0, ux, uy, v0, vx, vy = s[2], s[3], s[4], s[8], s[9], s[10], s[11], s[12], s[13]
    one = np.float32(1.0)
    w = w0 + wx * dx + wy * dy
    iw = one / (w if abs(w) > np.float32(1e-12) else one)
    qa, qb, qc, a1, b1 = curved_quadratic(f, w, (u0 + ux * dx + uy * dy) * iw, (v0 + vx * dx + vy * dy) * iw, dx, dy)
    return qb * qb - np.float32(4.0) * qa * qc


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def fragment(s, c, f, clipping, curved, dx, dy, params):
    """Where the ray of the pixel at offset (dx, dy) meets the splat of geometry s, clip lines c
    and normal field f (splatting.glsl splat_distance and filter_distance), without branches:
    (kept, kernel distance², clamped eye depth, u, v, u² + v², clip excess, hit, 1/W). A ray
    that misses (parallel to the plane, or past the contour of a curved splat) has
    u² + v² = MISS and the centre's depth; `kept` is the visibility pass's test (inside the
    filter and the clip lines; the attribute pass reaches CREASE_BLEND past the lines)."""
    mx, my, w0, wx, wy, z0, zx, zy, u0, ux, uy, v0, vx, vy, cz, radius, weight, zt, footprint = s
    inv_lowpass2, no_lowpass, depth_clamp = params
    one = np.float32(1.0)
    w = w0 + wx * dx + wy * dy
    hit = abs(w) > np.float32(1e-12)
    iw = one / (w if hit else one)
    u = (u0 + ux * dx + uy * dy) * iw
    v = (v0 + vx * dx + vy * dy) * iw
    z = (z0 + zx * dx + zy * dy) * iw
    if curved:
        # the curved splat of the normal field: the root of the ray-surface quadratic nearest the
        # plane's hit (splatting.glsl curved_splat_hit), moving t, u, v and the depth along d.
        lu, lv = f[2], f[3]
        qa, qb, qc, a1, b1 = curved_quadratic(f, w, u, v, dx, dy)
        half = np.float32(0.5)
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
def visibility_output(s, c, f, hit_record, clipping, curved, dx, dy, params):
    """The visibility-pass output (splatting.glsl PASS_VISIBILITY) of the fragment whose
    `fragment` results are `hit_record`: its depth + z_t
    (FAR when discarded or off the disk) and its coverage of the pixel (0 when discarded), 0.5 + the signed
    distance in pixels to the splat's edge, where rho = max(|(u, v)|, 1 + clip excess) is 1,
    from rho's screen-space gradient (analytic here and in the GPU's compute pass, a quad's
    differences in its fragment shader), for a curved splat no farther than its contour (where
    the discriminant of its quadratic, over its forward differences, falls to 0), and at least
    the footprint of a pixel-wide disk at the projected centre (sub-pixel splats), a half-pixel
    one off the disk, counted by the splat's share FT (splatting.glsl footprint_edge)."""
    kept, kernel2, z, u, v, rho2, clipped, hit, iw = hit_record
    mx, my, w0, wx, wy, z0, zx, zy, u0, ux, uy, v0, vx, vy, cz, radius, weight, zt, footprint = s
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
    if curved:  # forward differences one pixel right and one up (the GPU's window +x and +y)
        disc = curved_discriminant(s, f, dx, dy)
        ddx = curved_discriminant(s, f, dx + one, dy) - disc
        ddy = curved_discriminant(s, f, dx, dy - one) - disc
        edge = min(edge, disc / max(math.sqrt(ddx * ddx + ddy * ddy), np.float32(1e-30)))
    # a low-pass fragment off the disk: the half-pixel footprint, by the splat's share
    share, reach = (one, one) if rho2 <= one else (footprint, np.float32(0.5))
    edge = max(edge if hit else np.float32(-1e30), share * (reach - math.sqrt(dx * dx + dy * dy)) - np.float32(0.5))
    coverage = min(max(np.float32(0.5) + edge, np.float32(0.0)), one)
    # a low-pass fragment off the disk filters but hides nothing
    return (z + zt if kept and rho2 <= 1 else FAR), (coverage if kept else np.float32(0.0))


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def gaussian_weight(kernel2):
    """The Gaussian weight exp(-GAUSSIAN_SHARPNESS kernel2) of splatting.py's lookup table,
    sampled at its texel centres (kernel2 clamped to the first and last)."""
    lo, hi = np.float32(0.5 / KERNEL_SIZE), np.float32(1.0 - 0.5 / KERNEL_SIZE)
    s = np.float32(2.0) * min(max(kernel2, lo), hi) - np.float32(1.0)
    acc = EXP_POLY[9]
    for k in range(8, -1, -1):
        acc = acc * s + EXP_POLY[k]
    return acc


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def attribute_output(s, f, hit_record, field_normals, nx, ny, nz):
    """The attribute-pass output before its depth test of the fragment whose `fragment`
    results are `hit_record`: weight (0 when discarded; negated past a clip line, where it
    fades over CREASE_BLEND and blends only near the visible depth: `blends`), eye depth and
    normal: the splat's (nx, ny, nz), or with `field_normals` Phong splatting's N(u, v) = n +
    u alpha e_u + v beta e_v (eq. 8), unit and turned no further than edge-on (gl/common.glsl
    field_normal)."""
    _, kernel2, z, u, v, rho2, clipped, hit, iw = hit_record
    one = np.float32(1.0)
    fade = min(one - clipped / CREASE_BLEND, one)
    w = s[16] * gaussian_weight(kernel2) * fade * (one if clipped <= 0 else -one)
    kept = kernel2 <= 1 and clipped <= CREASE_BLEND  # the visibility pass's test, CREASE_BLEND wider
    if field_normals:
        fux, fuy, fuz, fvx, fvy, fvz, ex, ey, ez = f[10], f[11], f[12], f[13], f[14], f[15], f[16], f[17], f[18]
        nx, ny, nz = nx + u * fux + v * fvx, ny + u * fuy + v * fvy, nz + u * fuz + v * fvz
        away = min(nx * ex + ny * ey + nz * ez, np.float32(0.0))
        nx, ny, nz = nx - away * ex, ny - away * ey, nz - away * ez
        inv = np.float32(1.0) / max(math.sqrt(nx * nx + ny * ny + nz * nz), np.float32(1e-30))
        nx, ny, nz = nx * inv, ny * inv, nz * inv
    return (w if kept else np.float32(0.0)), z, nx, ny, nz


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def blends(w, z, visible, zt):
    """Whether an attribute-pass fragment of `attribute_output` weight w and eye depth z blends
    into a pixel of visibility depth `visible`: no farther than it, and past its splat's clip
    line (w < 0) no more than CREASE_BLEND_DEPTH z_t in front of it (splatting.glsl)."""
    return w != 0 and z <= visible and (w > 0 or z >= visible - CREASE_BLEND_DEPTH * zt)


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def blend(acc, p, w, z, r, g, b, nx, ny, nz):
    """The attribute pass's additive blend of one fragment of weight w into pixel p's
    accumulators (acc (STRIDE², LAYER)): the place where a further channel (a scalar, or a
    categorical winner) would join."""
    acc[p, 0] += w * r
    acc[p, 1] += w * g
    acc[p, 2] += w * b
    acc[p, 3] += w
    acc[p, 4] += w * nx
    acc[p, 5] += w * ny
    acc[p, 6] += w * nz
    acc[p, 7] += w * z


@nb.njit(forceinline=True, fastmath=True, error_model="numpy")
def both_outputs(s, c, f, clipping, curved, field_normals, dx, dy, params, nx, ny, nz, inside):
    """A fragment's visibility and attribute outputs from one intersection of its ray with the
    splat: (depth + z_t, coverage, w, depth, normal), those of a discarded fragment where
    `inside` (the splat's box) is False."""
    hit_record = fragment(s, c, f, clipping, curved, dx, dy, params)
    z, cover = visibility_output(s, c, f, hit_record, clipping, curved, dx, dy, params)
    w, depth, fx, fy, fz = attribute_output(s, f, hit_record, field_normals, nx, ny, nz)
    zero = np.float32(0.0)
    return (z if inside else FAR), (cover if inside else zero), (w if inside else zero), depth, fx, fy, fz


@nb.njit(inline="always")
def lane_pixel(ibox, jb, lane):
    """The tile scratch's pixel of lane 0..3 (left to right, then down) of the 2x2 block at the
    top-left of box jb; unsigned: no wraparound test."""
    return np.uint64((ibox[jb + TEMP[2]] + (lane >> 1)) * STRIDE + ibox[jb + TEMP[0]] + (lane & 1))


@nb.njit(fastmath=True, error_model="numpy")
def visibility_tile(table, ibox, count, ox, oy, params, clip_src, field_src, normal_src, tmp, kept, zb, cov):
    """The visibility pass of the 2x2 blocks at the top-left of a table's `count` boxes into zb
    (MIN of depth + z_t) and cov (MAX of coverage): per table block, in one SIMD loop, then
    blended one splat after another (a block's splats may overlap). The same loop keeps their
    attribute outputs in `kept` (table_size(count, KEPT_ROWS)) for `attribute_tile`: the two
    passes meet the same rays. `visible_splats` draws the rest of the larger boxes."""
    clipping, curved = clip_src is not None, field_src is not None
    field_normals = curved and normal_src is not None
    half, one = np.float32(0.5), np.float32(1.0)
    for first in range(0, count, BLOCK):
        size = min(BLOCK, count - first)
        base, box_base = table_slot(first, TABLE_ROWS), table_slot(first, 4)
        kept_base = table_slot(first, KEPT_ROWS)
        for q in range(size):
            uq = np.uint64(q)
            j, jb, k = base + uq, box_base + uq, kept_base + uq
            s = splat_geometry(table, j)
            c, f = splat_extras(table, clip_src, field_src, j)
            nx, ny, nz = table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]
            x0, y0 = ibox[jb + TEMP[0]], ibox[jb + TEMP[2]]
            wide, tall = ibox[jb + TEMP[1]] > x0, ibox[jb + TEMP[3]] > y0
            dx, dy = np.float32(x0 + ox) + half - s[0], np.float32(y0 + oy) + half - s[1]
            # the four lanes written out: a loop over them would stay a loop, which the vectorizer
            # (innermost loops only) would take instead of the loop over the block's splats
            z0, cover0, w0, d0, fx0, fy0, fz0 = both_outputs(s, c, f, clipping, curved, field_normals, dx, dy, params,
                                                             nx, ny, nz, True)
            z1, cover1, w1, d1, fx1, fy1, fz1 = both_outputs(s, c, f, clipping, curved, field_normals, dx + one, dy,
                                                             params, nx, ny, nz, wide)
            z2, cover2, w2, d2, fx2, fy2, fz2 = both_outputs(s, c, f, clipping, curved, field_normals, dx, dy + one,
                                                             params, nx, ny, nz, tall)
            z3, cover3, w3, d3, fx3, fy3, fz3 = both_outputs(s, c, f, clipping, curved, field_normals, dx + one,
                                                             dy + one, params, nx, ny, nz, wide and tall)
            tmp[TEMP[0] + uq], tmp[TEMP[1] + uq], tmp[TEMP[2] + uq], tmp[TEMP[3] + uq] = z0, z1, z2, z3
            tmp[TEMP[4] + uq], tmp[TEMP[5] + uq], tmp[TEMP[6] + uq], tmp[TEMP[7] + uq] = cover0, cover1, cover2, cover3
            kept[k + KEPT[0]], kept[k + KEPT[1]], kept[k + KEPT[2]], kept[k + KEPT[3]] = w0, w1, w2, w3
            kept[k + KEPT[4]], kept[k + KEPT[5]], kept[k + KEPT[6]], kept[k + KEPT[7]] = d0, d1, d2, d3
            if field_normals:
                kept[k + KEPT[8]], kept[k + KEPT[9]], kept[k + KEPT[10]], kept[k + KEPT[11]] = fx0, fx1, fx2, fx3
                kept[k + KEPT[12]], kept[k + KEPT[13]], kept[k + KEPT[14]], kept[k + KEPT[15]] = fy0, fy1, fy2, fy3
                kept[k + KEPT[16]], kept[k + KEPT[17]], kept[k + KEPT[18]], kept[k + KEPT[19]] = fz0, fz1, fz2, fz3
        for q in range(size):
            uq = np.uint64(q)
            jb = box_base + uq
            for lane in range(4):
                pl = lane_pixel(ibox, jb, lane)
                row = np.uint64(lane * BLOCK)  # TEMP[lane]: a tuple indexed at run time is a switch
                zb[pl] = min(zb[pl], tmp[row + uq])
                cov[pl] = max(cov[pl], tmp[row + TEMP[4] + uq])


@nb.njit(fastmath=True, error_model="numpy")
def attribute_tile(table, ibox, count, field_src, normal_src, kept, zb, acc, levels, best):
    """The attribute pass of the 2x2 blocks of `visibility_tile`: the weighted sums of the
    fragments no farther than zb into acc, from its `kept` outputs; shaded with their splats'
    normal fields with `field_src` and `normal_src` (Phong splatting; else the splat's own
    normal, `deferred`). With
    `levels` > 0 (a categorical colour mode, whose splats carry their palette index k as
    k / CODE_SCALE in red), `best` keeps per pixel the MAX of category_pack(w, k): the heaviest
    splat's category (splatting.glsl PASS_CATEGORY), never a blend."""
    field_normals = field_src is not None and normal_src is not None
    for first in range(0, count, BLOCK):
        size = min(BLOCK, count - first)
        base, box_base = table_slot(first, TABLE_ROWS), table_slot(first, 4)
        kept_base = table_slot(first, KEPT_ROWS)
        for q in range(size):
            uq = np.uint64(q)
            j, jb = base + uq, box_base + uq
            r, g, b = table[j + ROW[R]], table[j + ROW[G]], table[j + ROW[B]]
            nx, ny, nz = table[j + ROW[NX]], table[j + ROW[NY]], table[j + ROW[NZ]]
            zt = table[j + ROW[ZT]]
            # only categorical modes use it: numba's floor is a call, about 6% of a deferred frame (bench)
            code = math.floor(r * np.float32(CODE_SCALE) + np.float32(0.5)) if levels > 0 else 0
            k = kept_base + uq
            for lane in range(4):
                pl = lane_pixel(ibox, jb, lane)
                row = k + np.uint64(lane * BLOCK)  # KEPT[lane]: a tuple indexed at run time is a switch
                w, z = kept[row], kept[row + KEPT[4]]
                if blends(w, z, zb[pl], zt):
                    w = abs(w)
                    if levels > 0:
                        best[pl] = max(best[pl], category_pack(w, code, levels))
                    if field_normals:
                        blend(acc, pl, w, z, r, g, b, kept[row + KEPT[8]], kept[row + KEPT[12]], kept[row + KEPT[16]])
                    else:
                        blend(acc, pl, w, z, r, g, b, nx, ny, nz)


@nb.njit(fastmath=True, error_model="numpy")
def split_boxes(table, ibox, count, clip_src, field_src, slot, block, split, split_box):
    """The 2x2 blocks of the boxes of a table's splats beyond the first (the top-left one,
    which `visibility_tile` draws), from splat `slot`'s block `block` on: each a copy of its
    splat's record (the rows that the passes read) in the table `split`, with the block as its
    box in `split_box`, SPLIT_BLOCKS at most. (blocks made, slot and block to go on from)."""
    made = 0
    while slot < count and made < SPLIT_BLOCKS:
        j, jb = table_slot(slot, TABLE_ROWS), table_slot(slot, 4)
        x0, x1, y0, y1 = ibox[jb + TEMP[0]], ibox[jb + TEMP[1]], ibox[jb + TEMP[2]], ibox[jb + TEMP[3]]
        across = (x1 - x0) // 2 + 1  # 2x2 blocks along a row of the box
        blocks = across * ((y1 - y0) // 2 + 1)
        while block < blocks and made < SPLIT_BLOCKS:
            k, kb = table_slot(made, TABLE_ROWS), table_slot(made, 4)
            for row in range(MX, NZ + 1):
                split[k + np.uint64(row * BLOCK)] = table[j + np.uint64(row * BLOCK)]
            if clip_src is not None:
                for row in range(C0A, C1C + 1):
                    split[k + np.uint64(row * BLOCK)] = table[j + np.uint64(row * BLOCK)]
            if field_src is not None:
                for row in range(KU, EZ + 1):
                    split[k + np.uint64(row * BLOCK)] = table[j + np.uint64(row * BLOCK)]
            bx, by = x0 + 2 * (block % across), y0 + 2 * (block // across)
            split_box[kb + TEMP[0]], split_box[kb + TEMP[1]] = bx, min(bx + 1, x1)
            split_box[kb + TEMP[2]], split_box[kb + TEMP[3]] = by, min(by + 1, y1)
            made += 1
            block += 1
        if block >= blocks:
            slot, block = slot + 1, 1
    return made, slot, block


@nb.njit(fastmath=True, error_model="numpy")
def visible_splats(table, ibox, count, ox, oy, params, clip_src, field_src, normal_src, tmp, kept, split,
                   split_box, split_kept, zb, cov):
    """The visibility pass of a table's `count` set-up splats, every 2x2 block of their boxes:
    the top-left blocks straight from the table, the rest of the larger boxes from copies of
    their splats' records (`split_boxes`), so that every fragment is computed in the SIMD loops
    (pixel by pixel, a `deferred` frame of the bunny's 35k vertices at 1024x1024 took 77-84 ms
    instead of 45, `surfel bench`). Returns (rounds of SPLIT_BLOCKS copies, copies in the last
    round), for `attributes_of_splats`."""
    visibility_tile(table, ibox, count, ox, oy, params, clip_src, field_src, normal_src, tmp, kept, zb, cov)
    rounds, drawn, slot, block = 0, 0, 0, 1
    while slot < count:
        made, slot, block = split_boxes(table, ibox, count, clip_src, field_src, slot, block, split, split_box)
        if made > 0:
            visibility_tile(split, split_box, made, ox, oy, params, clip_src, field_src, normal_src, tmp,
                            split_kept, zb, cov)
            rounds, drawn = rounds + 1, made
    return rounds, drawn


@nb.njit(fastmath=True, error_model="numpy")
def attributes_of_splats(table, ibox, count, rounds, drawn, ox, oy, params, clip_src, field_src, normal_src, tmp,
                         kept, split, split_box, split_kept, zb, cov, acc, levels, best):
    """The attribute pass of a table's `count` splats, after `visible_splats` drew them: from
    their kept outputs, and their copies' (`rounds` and `drawn`: what visible_splats returned).
    Where the copies took more than one round, or `split` no longer holds them (rounds 2), they
    are made again and their visibility outputs recomputed, which leaves zb and cov as they are
    (the MIN and MAX of the same values)."""
    attribute_tile(table, ibox, count, field_src, normal_src, kept, zb, acc, levels, best)
    if rounds == 1:
        attribute_tile(split, split_box, drawn, field_src, normal_src, split_kept, zb, acc, levels, best)
    elif rounds > 1:
        slot, block = 0, 1
        while slot < count:
            made, slot, block = split_boxes(table, ibox, count, clip_src, field_src, slot, block, split, split_box)
            if made > 0:
                visibility_tile(split, split_box, made, ox, oy, params, clip_src, field_src, normal_src, tmp,
                                split_kept, zb, cov)
                attribute_tile(split, split_box, made, field_src, normal_src, split_kept, zb, acc, levels, best)
