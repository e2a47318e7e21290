"""Numba kernels of the CPU EWA splatting backend (the equations are stated in ewa.py).

Three stages, none of them a Python loop over splats:

1. `setup_splats` (parallel over splats): eye-space centre, the Jacobian J of the
   projective mapping at the centre, the resampling kernel's conic M^-1, its 1/|J^-1|
   scale, the screen-space depth gradient and the pixel bounding box; one row of
   `SPLAT_FIELDS` float32 values per splat plus an int32 box.
2. `bin_splats` (serial, O(splats + tile overlaps)): count, prefix sum and scatter the
   splats into screen tiles of TILE x TILE pixels, keeping draw order inside a tile.
3. `rasterize_tiles` (parallel over tiles): each tile owns its pixels, so threads never
   write the same memory. Two passes per tile in tile-local buffers: visibility (the
   nearest fragment depth plus its splat's threshold, and the most any splat covers the
   pixel), then accumulation of
   w, w*albedo, w*normal, w*depth into the front layer for the fragments not behind that
   depth and into the back layer (the nearest surface behind it) for the others.
4. `normalise_layers` (parallel over rows): per-layer albedo, normal, depth and coverage.

Everything per fragment is float32 (fastmath); float64 is used only to move centres into
eye space, so LiDAR coordinates keep their precision.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..colors import category_pack

TILE = 32
SMALL_BOX = 16  # pixels: a splat box this small is scanned whole, testing the conic per pixel,
                # instead of solving for each row's span (the cost of tiny minified splats)
# Columns of the per-splat parameter table.
MX, MY, CA, CB, CC, WS, ZC, GX, GY, DZ, ZT, R, G, B, NX, NY, NZ, VA, VB, VC = range(20)
SPLAT_FIELDS = 20
# Columns of the optional table for clip lines and normal fields (filled only for clouds that
# have them): P0*, P1*: the clip lines as pixel half-planes a dx + b dy <= c around the
# centre; I00..I11: J^-1, pixel offsets to local coordinates; FU*, FV*: the eye-space slopes
# of the Phong normal field, alpha u^ and beta v^; E*: the unit direction to the eye.
(P0A, P0B, P0C, P1A, P1B, P1C, I00, I01, I10, I11, FUX, FUY, FUZ, FVX, FVY, FVZ, EX, EY, EZ) = range(19)
EXTRA_FIELDS = 19
# Accumulator channels, the order of the GL backend's two RGBA32F targets.
LAYER = 8  # w*r, w*g, w*b, w, w*nx, w*ny, w*nz, w*depth
ACC_CHANNELS = 2 * LAYER  # front layer, then back layer
# Finite "no depth yet" sentinel: fastmath may assume no infinities.
FAR = np.float32(3e38)
# A pixel inside some kernel's ellipse of this many standard deviations is covered (ewa.py).
COVERAGE_SIGMAS = np.float32(1.0)
MIN_LAYER_COS = np.float32(0.05)  # gl/common.glsl's: the least |n . view| a layer's thickness is divided by


@nb.njit(inline="always", fastmath=True, error_model="numpy")
def layer_offset(offset, thickness, crossing):
    """gl/common.glsl layer_offset: the threshold `offset` capped by the thickness of the
    splat's layer (0: no cap) as eye depth along a ray that crosses the layer at
    |n . view| = `crossing` (preprocess/thickness.py)."""
    return min(offset, thickness / max(crossing, MIN_LAYER_COS)) if thickness > 0 else offset


@nb.njit(parallel=True, fastmath=True, cache=True)
def setup_splats(positions, origin, view, normals, colors, axes, clip_lines, fields, thickness, intr, ortho, near,
                 radius_scale, sigma2, lowpass2, vis2, cutoff2, depth_offset, depth_clamp, backface,
                 width, height):
    """Per-splat parameter table (N, SPLAT_FIELDS) float32, the table of clip lines and
    normal fields (N, EXTRA_FIELDS) float32 (one unused row when the cloud has neither) and
    pixel boxes (N, 4) int32 (x0, x1, y0, y1 inclusive; x0 > x1 marks a culled splat).

    positions (N,3) f64, origin (3,) f64, view (4,4) f64 world-to-eye, normals (N,3) f32 (zero rows:
    splats facing the camera, surfel.preprocess.structure),
    colors (N,3) f32 or (1,3) for a constant colour, axes (N,2,3) f32, clip_lines (N,2,3)
    f32 or (1,2,3) for none (a u + b v <= c in the splat's unscaled local coordinates),
    fields (N,2) f32 Phong normal-field slopes (alpha, beta) or (1,2) zeros,
    thickness (N,) f32 the layers' thickness, the cap of z_t (0: none; gl/common.glsl layer_offset),
    intr = fx, fy, cx, cy; ortho > 0 is the orthographic pixels-per-unit scale.
    """
    n = positions.shape[0]
    out = np.empty((n, SPLAT_FIELDS), np.float32)
    with_extra = clip_lines.shape[0] > 1 or fields.shape[0] > 1
    extra = np.zeros((n if with_extra else 1, EXTRA_FIELDS), np.float32)
    box = np.empty((n, 4), np.int32)
    fx, fy, cx, cy = np.float32(intr[0]), np.float32(intr[1]), np.float32(intr[2]), np.float32(intr[3])
    # eye = R (p - origin) + t: fold the origin into t in float64 once.
    t0 = view[0, 3] + view[0, 0] * origin[0] + view[0, 1] * origin[1] + view[0, 2] * origin[2]
    t1 = view[1, 3] + view[1, 0] * origin[0] + view[1, 1] * origin[1] + view[1, 2] * origin[2]
    t2 = view[2, 3] + view[2, 0] * origin[0] + view[2, 1] * origin[1] + view[2, 2] * origin[2]
    rot = view[:3, :3].astype(np.float32)
    color_step = 1 if colors.shape[0] > 1 else 0  # (1, 3) colours: one for all
    clip_step = 1 if clip_lines.shape[0] > 1 else 0
    field_step = 1 if fields.shape[0] > 1 else 0
    cutoff = np.float32(math.sqrt(cutoff2))
    for i in nb.prange(n):
        box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 1, 0, 1, 0
        px, py, pz = positions[i, 0] - origin[0], positions[i, 1] - origin[1], positions[i, 2] - origin[2]
        ex = np.float32(view[0, 0] * px + view[0, 1] * py + view[0, 2] * pz + t0)
        ey = np.float32(view[1, 0] * px + view[1, 1] * py + view[1, 2] * pz + t1)
        ez = np.float32(view[2, 0] * px + view[2, 1] * py + view[2, 2] * pz + t2)
        d = -ez
        if ortho <= 0 and d <= near:
            continue  # behind the camera: the affine approximation is meaningless there
        lines = clip_lines[i * clip_step]
        if lines[0, 2] < -1 or lines[1, 2] < -1:
            continue  # clipped away whole (a point on a crease)
        nx = rot[0, 0] * normals[i, 0] + rot[0, 1] * normals[i, 1] + rot[0, 2] * normals[i, 2]
        ny = rot[1, 0] * normals[i, 0] + rot[1, 1] * normals[i, 1] + rot[1, 2] * normals[i, 2]
        nz = rot[2, 0] * normals[i, 0] + rot[2, 1] * normals[i, 1] + rot[2, 2] * normals[i, 2]
        ux = radius_scale * (rot[0, 0] * axes[i, 0, 0] + rot[0, 1] * axes[i, 0, 1] + rot[0, 2] * axes[i, 0, 2])
        uy = radius_scale * (rot[1, 0] * axes[i, 0, 0] + rot[1, 1] * axes[i, 0, 1] + rot[1, 2] * axes[i, 0, 2])
        uz = radius_scale * (rot[2, 0] * axes[i, 0, 0] + rot[2, 1] * axes[i, 0, 1] + rot[2, 2] * axes[i, 0, 2])
        vx = radius_scale * (rot[0, 0] * axes[i, 1, 0] + rot[0, 1] * axes[i, 1, 1] + rot[0, 2] * axes[i, 1, 2])
        vy = radius_scale * (rot[1, 0] * axes[i, 1, 0] + rot[1, 1] * axes[i, 1, 1] + rot[1, 2] * axes[i, 1, 2])
        vz = radius_scale * (rot[2, 0] * axes[i, 1, 0] + rot[2, 1] * axes[i, 1, 1] + rot[2, 2] * axes[i, 1, 2])
        if nx * nx + ny * ny + nz * nz <= 0.25:
            # No orientation (a zero normal, surfel.preprocess.structure): the disk faces the
            # camera, as common.glsl's face_camera: perpendicular to the ray through its centre.
            nx, ny, nz = _to_eye(ex, ey, ez, ortho)
            rx, rz = nz, -nx  # (0, 1, 0) x n
            length = math.sqrt(rx * rx + rz * rz)
            if length * length > 1e-12:
                rx, rz = rx / length, rz / length
            else:
                rx, rz = np.float32(1.0), np.float32(0.0)
            lu = math.sqrt(ux * ux + uy * uy + uz * uz)
            lv = math.sqrt(vx * vx + vy * vy + vz * vz)
            ux, uy, uz = rx * lu, np.float32(0.0), rz * lu
            vx, vy, vz = ny * rz * lv, (nz * rx - nx * rz) * lv, -ny * rx * lv  # n x right
        facing = nz if ortho > 0 else -(nx * ex + ny * ey + nz * ez)
        flip = np.float32(1.0)
        if facing < 0:
            if backface:
                continue
            nx, ny, nz = -nx, -ny, -nz
            flip = np.float32(-1.0)  # the normal field turns with the normal
        # J = dproject/deye (2x3) times [u v] (3x2): local tangent coordinates -> pixels.
        if ortho > 0:
            mx, my = cx + ortho * ex, cy - ortho * ey
            j00, j01 = ortho * ux, ortho * vx
            j10, j11 = -ortho * uy, -ortho * vy
        else:
            inv = np.float32(1.0) / d
            mx, my = cx + fx * ex * inv, cy - fy * ey * inv
            a0, a2 = fx * inv, fx * ex * inv * inv
            b1, b2 = -fy * inv, -fy * ey * inv * inv
            j00, j01 = a0 * ux + a2 * uz, a0 * vx + a2 * vz
            j10, j11 = b1 * uy + b2 * uz, b1 * vy + b2 * vz
        # Resampling kernel covariance M = J V J^T + L, V = sigma^2 I, L = lowpass^2 I.
        m00 = sigma2 * (j00 * j00 + j01 * j01) + lowpass2
        m01 = sigma2 * (j00 * j10 + j01 * j11)
        m11 = sigma2 * (j10 * j10 + j11 * j11) + lowpass2
        det_m = m00 * m11 - m01 * m01
        det_j = j00 * j11 - j01 * j10
        hx, hy = cutoff * math.sqrt(m00), cutoff * math.sqrt(m11)
        x0 = max(int(math.ceil(mx - hx - 0.5)), 0)
        x1 = min(int(math.floor(mx + hx - 0.5)), width - 1)
        y0 = max(int(math.ceil(my - hy - 0.5)), 0)
        y1 = min(int(math.floor(my + hy - 0.5)), height - 1)
        if x0 > x1 or y0 > y1:
            continue
        # Eye depth on the splat plane, linear in the pixel offset: h J^-1 with h = d depth/d(s,t).
        h0, h1 = -uz, -vz
        if abs(det_j) > 1e-12:
            gx = (h0 * j11 - h1 * j10) / det_j
            gy = (h1 * j00 - h0 * j01) / det_j
        else:
            gx, gy = np.float32(0.0), np.float32(0.0)
        row = out[i]
        row[MX], row[MY] = mx, my
        row[CA], row[CB], row[CC] = m11 / det_m, -m01 / det_m, m00 / det_m
        row[WS] = abs(det_j) / math.sqrt(det_m)
        row[ZC], row[GX], row[GY] = d, gx, gy
        radius = max(math.sqrt(ux * ux + uy * uy + uz * uz), math.sqrt(vx * vx + vy * vy + vz * vz))
        # The visibility footprint: the reconstruction kernel itself, J V J^T + v^2 I with a small
        # v, so the low-pass fringe of a splat seen edge-on cannot hide the surface behind it.
        n00, n11 = m00 - lowpass2 + vis2, m11 - lowpass2 + vis2
        det_n = n00 * n11 - m01 * m01
        row[VA], row[VB], row[VC] = n11 / det_n, -m01 / det_n, n00 / det_n
        # The plane's depth range over that footprint is +-R sqrt(g^T N g); capped so that a
        # splat seen edge-on (J near singular, g huge) cannot claim absurd depths.
        row[DZ] = min(cutoff * math.sqrt(gx * gx * n00 + 2 * gx * gy * m01 + gy * gy * n11), depth_clamp * radius)
        # Threshold: the splat's own depth range over its footprint is one surface, plus z_t;
        # where another layer lies close, no farther than the layer's thickness along the ray.
        to_eye = np.float32(1.0) if ortho > 0 else math.sqrt(ex * ex + ey * ey + ez * ez)
        crossing = abs(facing) / max(math.sqrt(nx * nx + ny * ny + nz * nz) * to_eye, np.float32(1e-30))
        row[ZT] = layer_offset(depth_offset * radius + row[DZ], thickness[i], crossing)
        c = i * color_step
        row[R], row[G], row[B] = colors[c, 0], colors[c, 1], colors[c, 2]
        row[NX], row[NY], row[NZ] = nx, ny, nz
        box[i, 0], box[i, 1], box[i, 2], box[i, 3] = x0, x1, y0, y1
        if not with_extra:
            continue
        e = extra[i]
        # A clip line a s + b t <= c of the local coordinates (s, t) = J^-1 dx / radius_scale
        # becomes the pixel half-plane (a, b) adj(J) dx / (det J radius_scale) <= c.
        for line in range(2):
            a, b, cl = lines[line, 0], lines[line, 1], lines[line, 2]
            col = P0A + 3 * line
            if abs(det_j) > 1e-12 and cl < 1:
                inv_det = np.float32(1.0) / (det_j * radius_scale)
                e[col] = (a * j11 - b * j10) * inv_det
                e[col + 1] = (b * j00 - a * j01) * inv_det
                e[col + 2] = cl
            else:  # edge-on (the line is a point) or inactive: cuts nothing
                e[col], e[col + 1], e[col + 2] = 0, 0, 1
        if abs(det_j) > 1e-12:
            inv = np.float32(1.0) / det_j
            e[I00], e[I01], e[I10], e[I11] = j11 * inv, -j01 * inv, -j10 * inv, j00 * inv
        else:
            e[I00], e[I01], e[I10], e[I11] = 0, 0, 0, 0
        # the field's tilts at the drawn rim, radius_scale times as far as the fitted one
        turn = flip * radius_scale
        alpha = turn * fields[i * field_step, 0] / max(math.sqrt(ux * ux + uy * uy + uz * uz), np.float32(1e-30))
        beta = turn * fields[i * field_step, 1] / max(math.sqrt(vx * vx + vy * vy + vz * vz), np.float32(1e-30))
        e[FUX], e[FUY], e[FUZ] = alpha * ux, alpha * uy, alpha * uz
        e[FVX], e[FVY], e[FVZ] = beta * vx, beta * vy, beta * vz
        # the direction to the eye, for the field's normals (_field_normal)
        e[EX], e[EY], e[EZ] = _to_eye(ex, ey, ez, ortho)
    return out, extra, box


@nb.njit(inline="always", fastmath=True)
def _to_eye(ex, ey, ez, ortho):
    """The unit direction from eye point (ex, ey, ez) to the eye (the view axis if orthographic)."""
    if ortho > 0:
        return np.float32(0.0), np.float32(0.0), np.float32(1.0)
    inv_d = np.float32(1.0) / math.sqrt(ex * ex + ey * ey + ez * ez)
    return -ex * inv_d, -ey * inv_d, -ez * inv_d


@nb.njit(cache=True)
def bin_splats(box, tiles_x, tiles_y):
    """Tile offsets (tiles+1,) int64 and splat indices sorted by tile (draw order kept)."""
    n = box.shape[0]
    counts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    for i in range(n):
        if box[i, 0] > box[i, 1]:
            continue
        for ty in range(box[i, 2] // TILE, box[i, 3] // TILE + 1):
            for tx in range(box[i, 0] // TILE, box[i, 1] // TILE + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    index = np.empty(offsets[-1], np.int32)
    for i in range(n):
        if box[i, 0] > box[i, 1]:
            continue
        for ty in range(box[i, 2] // TILE, box[i, 3] // TILE + 1):
            for tx in range(box[i, 0] // TILE, box[i, 1] // TILE + 1):
                t = ty * tiles_x + tx
                index[fill[t]] = i
                fill[t] += 1
    return offsets, index


@nb.njit(inline="always", fastmath=True)
def _span(s, conic, yc, x_lo, x_hi, cutoff2):
    """Pixel columns [x0, x1] of row centre yc inside the ellipse of the conic at columns
    conic..conic+2, a dx^2 + 2 b dx dy + c dy^2 <= cutoff2 (empty when x0 > x1)."""
    dy = yc - s[MY]
    a, b = s[conic], s[conic + 1]
    disc = b * b * dy * dy - a * (s[conic + 2] * dy * dy - cutoff2)
    if disc < 0:
        return 1, 0, dy
    root = math.sqrt(disc)
    left = s[MX] + (-b * dy - root) / a
    right = s[MX] + (-b * dy + root) / a
    return max(int(math.ceil(left - 0.5)), x_lo), min(int(math.floor(right - 0.5)), x_hi), dy


@nb.njit(inline="always", fastmath=True)
def _quadric(s, conic, dx, dy):
    """The conic at columns conic..conic+2 at the pixel offset: a dx^2 + 2 b dx dy + c dy^2."""
    return s[conic] * dx * dx + np.float32(2.0) * s[conic + 1] * dx * dy + s[conic + 2] * dy * dy


@nb.njit(inline="always")
def _tile_box(box, i, ox, oy, tw, th):
    """Splat i's pixel box clipped to the tile, and whether it is small enough to scan whole."""
    x_lo, x_hi = max(box[i, 0], ox), min(box[i, 1], ox + tw - 1)
    y_lo, y_hi = max(box[i, 2], oy), min(box[i, 3], oy + th - 1)
    return x_lo, x_hi, y_lo, y_hi, (x_hi - x_lo + 1) * (y_hi - y_lo + 1) <= SMALL_BOX


@nb.njit(inline="always", fastmath=True)
def _row(s, conic, small, yc, x_lo, x_hi, cutoff2):
    """Columns [x0, x1] to visit on the row with centre yc, and its dy: the whole box row of a
    small splat (whose pixels are then tested one by one), else the conic's exact span."""
    if small:
        return x_lo, x_hi, yc - s[MY]
    return _span(s, conic, yc, x_lo, x_hi, cutoff2)


@nb.njit(inline="always", fastmath=True)
def _clipped(e, dx, dy):
    """Whether the pixel offset (dx, dy) lies beyond one of the splat's clip lines (e: its
    row of the extra table)."""
    return e[P0A] * dx + e[P0B] * dy > e[P0C] or e[P1A] * dx + e[P1B] * dy > e[P1C]


@nb.njit(inline="always", fastmath=True)
def _field_normal(s, e, dx, dy):
    """The unit normal N(u, v) = n + u alpha u^ + v beta v^ at the pixel offset (dx, dy), with
    (u, v) = J^-1 (dx, dy) kept within the splat's rim (the low-pass fringe of an edge-on
    splat lies far out in (u, v), where the linear field means nothing), turned no further
    than edge-on (as gl/common.glsl field_normal: past the silhouette it would face away, and
    two-sided shading would light it as if it faced the viewer again)."""
    u = e[I00] * dx + e[I01] * dy
    v = e[I10] * dx + e[I11] * dy
    length2 = u * u + v * v
    if length2 > 1:
        scale = np.float32(1.0) / math.sqrt(length2)
        u *= scale
        v *= scale
    nx = s[NX] + u * e[FUX] + v * e[FVX]
    ny = s[NY] + u * e[FUY] + v * e[FVY]
    nz = s[NZ] + u * e[FUZ] + v * e[FVZ]
    away = min(nx * e[EX] + ny * e[EY] + nz * e[EZ], np.float32(0.0))
    nx, ny, nz = nx - away * e[EX], ny - away * e[EY], nz - away * e[EZ]
    inv = np.float32(1.0) / max(math.sqrt(nx * nx + ny * ny + nz * nz), np.float32(1e-20))
    return nx * inv, ny * inv, nz * inv


@nb.njit(inline="always", fastmath=True)
def _coverage(s, dx, dy, q):
    """How much of the pixel at offset d = (dx, dy) the splat covers, anti-aliased over a
    pixel: 0.5 plus the pixel distance to the rim sqrt(q) = COVERAGE_SIGMAS of its visibility
    footprint's ellipse (q = d^T N^-1 d), (COVERAGE_SIGMAS - sqrt(q)) / |grad sqrt(q)| with
    |grad sqrt(q)| = |N^-1 d| / sqrt(q), clamped to [0, 1]; ewa_gl.glsl's `coverage` too."""
    gx = s[VA] * dx + s[VB] * dy
    gy = s[VB] * dx + s[VC] * dy
    slope = math.sqrt(gx * gx + gy * gy)
    root = math.sqrt(q)
    if slope <= np.float32(1e-20) * root:
        return np.float32(1.0)  # at the centre
    return min(max(np.float32(0.5) + (COVERAGE_SIGMAS - root) * root / slope, np.float32(0.0)), np.float32(1.0))


@nb.njit(parallel=True, fastmath=True, cache=True)
def rasterize_tiles(splats, extra, box, offsets, index, order, tiles_x, width, height, cutoff2, clip_lines,
                    normal_field, categories, category_levels):
    """Accumulators (H, W, ACC_CHANNELS) float32, coverage (H, W) float32, the fragment count
    and, with `category_levels` > 0, the packed heaviest category (surfel.colors) of each
    pixel's front and back layer (H, W, 2) float32 (-1 where none; `categories` holds each
    splat's palette index), else a (1, 1, 2) placeholder.

    Visibility (A-buffer in the spirit of Zwicker et al. 2001, Sec. 5): pass 1 stores per
    pixel Z = min over fragments of (depth + threshold of its splat); pass 2 blends every
    fragment with depth <= Z into the front layer (channels 0-7), independent of drawing
    order, and the others into the back layer (channels 8-15) with a running threshold
    z-buffer, so partly covered front pixels can be composited over the surface behind.
    Pass 1 also keeps the most any splat covers each pixel (`_coverage`: ewa.py, coverage).
    With `clip_lines`, fragments beyond a splat's clip lines are dropped; with `normal_field`,
    a fragment's normal is the splat's linear normal field at its local coordinates (Botsch,
    Spernat & Kobbelt 2004, eq. 8), else the splat's normal (both from the `extra` table).
    """
    acc = np.zeros((height, width, ACC_CHANNELS), np.float32)
    coverage = np.zeros((height, width), np.float32)
    with_categories = category_levels > 0
    best = np.full((height, width, 2) if with_categories else (1, 1, 2), -1.0, np.float32)
    fragments = np.zeros(order.shape[0], np.int64)
    half = np.float32(0.5)
    for k in nb.prange(order.shape[0]):
        t = order[k]
        if t < 0:  # padding (ewa.balanced_tile_order)
            continue
        start, stop = offsets[t], offsets[t + 1]
        if start == stop:
            continue
        ox, oy = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        tw, th = min(TILE, width - ox), min(TILE, height - oy)
        zbuf = np.full((TILE, TILE), FAR, np.float32)
        covered = np.zeros((TILE, TILE), np.float32)
        zback = np.full((TILE, TILE), FAR, np.float32)
        local = np.zeros((TILE, TILE, ACC_CHANNELS), np.float32)
        local_best = np.full((TILE, TILE, 2), -1.0, np.float32)
        for j in range(start, stop):
            i = index[j]
            s = splats[i]
            x_lo, x_hi, y_lo, y_hi, small = _tile_box(box, i, ox, oy, tw, th)
            for y in range(y_lo, y_hi + 1):
                x0, x1, dy = _row(s, VA, small, np.float32(y) + half, x_lo, x_hi, cutoff2)
                zrow = zbuf[y - oy]
                crow = covered[y - oy]
                for x in range(x0, x1 + 1):
                    dx = np.float32(x) + half - s[MX]
                    q = _quadric(s, VA, dx, dy)
                    if small and q > cutoff2:
                        continue
                    if clip_lines and _clipped(extra[i], dx, dy):
                        continue
                    dz = min(max(s[GX] * dx + s[GY] * dy, -s[DZ]), s[DZ])
                    z = s[ZC] + dz + s[ZT]
                    if z < zrow[x - ox]:
                        zrow[x - ox] = z
                    crow[x - ox] = max(crow[x - ox], _coverage(s, dx, dy, q))
        count = 0
        for j in range(start, stop):
            i = index[j]
            s = splats[i]
            x_lo, x_hi, y_lo, y_hi, small = _tile_box(box, i, ox, oy, tw, th)
            for y in range(y_lo, y_hi + 1):
                x0, x1, dy = _row(s, CA, small, np.float32(y) + half, x_lo, x_hi, cutoff2)
                zrow = zbuf[y - oy]
                brow = zback[y - oy]
                lrow = local[y - oy]
                for x in range(x0, x1 + 1):
                    dx = np.float32(x) + half - s[MX]
                    q = _quadric(s, CA, dx, dy)
                    if small and q > cutoff2:
                        continue
                    if clip_lines and _clipped(extra[i], dx, dy):
                        continue
                    dz = min(max(s[GX] * dx + s[GY] * dy, -s[DZ]), s[DZ])
                    z = s[ZC] + dz
                    cell = lrow[x - ox]
                    base = 0
                    if z > zrow[x - ox]:
                        # Behind the front surface: the back layer, a running z-buffer with the
                        # same threshold rule (nearer by more than z_t replaces, within blends).
                        zb = brow[x - ox]
                        if z > zb + s[ZT]:
                            continue
                        base = LAYER
                        if z < zb - s[ZT]:
                            cell[LAYER:] = 0
                            local_best[y - oy, x - ox, 1] = -1.0
                        if z < zb:
                            brow[x - ox] = z
                    w = s[WS] * math.exp(np.float32(-0.5) * q)
                    nx, ny, nz = s[NX], s[NY], s[NZ]
                    if normal_field:
                        nx, ny, nz = _field_normal(s, extra[i], dx, dy)
                    cell[base] += w * s[R]
                    cell[base + 1] += w * s[G]
                    cell[base + 2] += w * s[B]
                    cell[base + 3] += w
                    cell[base + 4] += w * nx
                    cell[base + 5] += w * ny
                    cell[base + 6] += w * nz
                    cell[base + 7] += w * z
                    if with_categories:
                        packed = category_pack(w, categories[i], category_levels)
                        if packed > local_best[y - oy, x - ox, base // LAYER]:
                            local_best[y - oy, x - ox, base // LAYER] = packed
                    count += 1
        acc[oy:oy + th, ox:ox + tw] = local[:th, :tw]
        coverage[oy:oy + th, ox:ox + tw] = covered[:th, :tw]
        if with_categories:
            best[oy:oy + th, ox:ox + tw] = local_best[:th, :tw]
        fragments[k] = count
    return acc, coverage, fragments.sum(), best


@nb.njit(parallel=True, fastmath=True, cache=True)
def normalise_layers(acc, scale):
    """Per layer of the (H, W, 8 * layers) accumulators: albedo (L, H, W, 3), unit normal
    (L, H, W, 3), depth (L, H, W) (inf where empty) and coverage alpha = clamp(w * scale)."""
    h, w = acc.shape[0], acc.shape[1]
    layers = acc.shape[2] // LAYER
    albedo = np.zeros((layers, h, w, 3), np.float32)
    normals = np.zeros((layers, h, w, 3), np.float32)
    depth = np.full((layers, h, w), np.inf, np.float32)
    alpha = np.zeros((layers, h, w), np.float32)
    for y in nb.prange(h):
        for x in range(w):
            for layer in range(layers):
                c = acc[y, x, layer * LAYER:(layer + 1) * LAYER]
                weight = c[3]
                if weight <= 0:
                    continue
                inv = np.float32(1.0) / weight
                for channel in range(3):
                    albedo[layer, y, x, channel] = c[channel] * inv
                length = math.sqrt(c[4] * c[4] + c[5] * c[5] + c[6] * c[6])
                if length > 1e-20:
                    for axis in range(3):
                        normals[layer, y, x, axis] = c[4 + axis] / length
                depth[layer, y, x] = c[7] * inv
                alpha[layer, y, x] = min(weight * scale, np.float32(1.0))
    return albedo, normals, depth, alpha


@nb.njit(parallel=True, cache=True)
def composite_layers(shaded, alpha, depth, normals, winner_only):  # pragma: no cover - compiled
    """Front-to-back "over" of the shaded layers (L, H, W, 3) with coverages (L, H, W): the
    straight colour (H, W, 3), total alpha (H, W), and the depth (H, W), normal (H, W, 3)
    and index (H, W) of the layer that contributes most to each pixel. `winner_only`: the
    colour is that layer's alone (categories are never blended)."""
    layers, h, w = alpha.shape
    color = np.zeros((h, w, 3), np.float32)
    total = np.zeros((h, w), np.float32)
    depth_out = np.empty((h, w), np.float32)
    normals_out = np.empty((h, w, 3), np.float32)
    tops = np.zeros((h, w), np.int64)
    for y in nb.prange(h):
        for x in range(w):
            so_far = np.float32(0.0)
            best = np.float32(-1.0)
            top = 0
            r = g = b = np.float32(0.0)
            for layer in range(layers):
                contribution = (np.float32(1.0) - so_far) * alpha[layer, y, x]
                r += contribution * shaded[layer, y, x, 0]
                g += contribution * shaded[layer, y, x, 1]
                b += contribution * shaded[layer, y, x, 2]
                so_far += contribution
                if contribution > best:
                    best = contribution
                    top = layer
            total[y, x] = so_far
            tops[y, x] = top
            depth_out[y, x] = depth[top, y, x]
            for c in range(3):
                normals_out[y, x, c] = normals[top, y, x, c]
            if winner_only:
                for c in range(3):
                    color[y, x, c] = shaded[top, y, x, c]
            elif so_far > 0:
                color[y, x, 0], color[y, x, 1], color[y, x, 2] = r / so_far, g / so_far, b / so_far
    return color, total, depth_out, normals_out, tops
