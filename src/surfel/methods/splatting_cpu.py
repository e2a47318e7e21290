"""The CPU backends of `gaussian`, `deferred` and `phong`: the three passes of GPU surface
splatting (Botsch & Kobbelt 2003; Botsch, Spernat & Kobbelt 2004; Botsch, Hornung, Zwicker &
Kobbelt 2005; survey 2.1.3-2.1.6), rasterized in software to give the pictures of their GL
programs (splatting.py, splatting.glsl) on machines whose OpenGL is itself a software
rasterizer, which the dedicated one beats.

Per splat (the vertex stage), in eye space: centre c, normal n turned to face the camera,
semi-axes u_j, v_j (times radius_scale; a curved splat's divided by its reach, splatting.py).
The ray of the pixel at offset (dx, dy) from the projected centre is
d = d_c + (dx / f_x, -dy / f_y, 0) from the eye (d_c = c / -c_z), or
starts at o = o_c + (dx, -dy) / s along (0, 0, -1) for an orthographic camera of s pixels per
unit. Where it meets the splat plane,

    W = d.n,   eye depth = ((c - o).n) / W,   u = ((q - c).u_j) / |u_j|²,  v likewise,

each a ratio of affine functions of (dx, dy) whose coefficients the setup computes once (for
perspective u W = d.((c.n) u_j/|u_j|² - (c.u_j/|u_j|²) n), zero on the centre's ray), so a
fragment costs one division. `deferred` and `phong` move t to the root of the ray's quadratic
with the curved splat h = -(k_u s_u² + k_v s_v²)/2 nearest the plane's hit; `phong`'s normal
is the linear field N(u, v) = n + u alpha e_u + v beta e_v (eq. 8), turned no further than
edge-on, and so is `deferred`'s (phong_normals; off, the splat's own).

The passes, as in splatting.glsl (r_lp the low-pass radius in pixels, z_t = depth_offset r):

1. visibility: fragments with rho² = min(u² + v², |x - m|² / r_lp²) <= 1 (the union of the
   disk and the screen-space low-pass, EWA filter on) or u² + v² <= 1 (off), inside their
   clip lines, give per pixel Z = min(depth + z_t) (a low-pass fragment off the disk hides
   nothing: it filters, it covers no surface) and the coverage max(clamp(0.5 + e)), e the
   larger of the signed distance (1 - rho) / |grad rho| to the splat's edge (rho's analytic
   screen gradient) and s (r - |x - m|) - 0.5, the footprint of a sub-pixel splat: on the
   disk s = r = 1; off it r = 1/2 (a dense cloud's outline covers the pixels beyond it as a
   mesh's does) and its share s = clamp(1.5 - a, 0, 1), a the projected semi-major axis in
   pixels (the largest eigenvalue of S below is a²), so that resolved edge-on splats do not
   widen an outline by the low-pass (splatting.glsl footprint_edge);
2. attributes: fragments with depth <= Z add w (rgb, 1, n, depth), w = v_w exp(-3 rho²) (the
   lookup table sampled at its texel centres), v_w = sqrt(det S / det(S + r_lp² I)) the EWA
   resampling kernel's relative amplitude (S = J Jᵀ of the projected splat);
3. normalization: rgb = sum w rgb / sum w, n and depth likewise; `deferred` and `phong` shade
   here, `gaussian` shaded each splat's colour before blending. A pixel whose four neighbours'
   centres splats cover (coverage at least 1/2; the low-pass's weight alone reaches beyond an
   outline) is whole (alpha 1), else its alpha is the coverage.

As on the GPU, a splat with a zero normal (no orientation, preprocess.drawn_normals) faces the
camera, and in `deferred` and `phong` a splat seen from its back weighs 1/256 where front
splats cover the pixel too (splatting.glsl BACK_SPLAT_WEIGHT).

Colour modes as on the GPU (surfel.colors): continuous attributes are splatted like colour and
mapped through the colour map per pixel (per splat for `gaussian`); in a categorical mode a
pixel shows the palette entry of its heaviest splat (the MAX of colors.category_pack over the
attribute pass's fragments), shaded per pixel, never a blend. Eye-dome lighting and
supersampling's box filter are RenderResult.from_samples', shared with every method.

Speed (issue 18): the cloud is drawn in Morton order (made once per cloud by the Renderer), so
a tile's splats lie together in memory; splats are binned into TILE x TILE screen tiles by
all threads, and tiles are rasterized in parallel, dealt to the threads by their splats
(ewa.balanced_tile_order), each in its thread's cache-sized scratch, normalized and shaded in
place; a tile draws the splats facing the camera first and passes by those seen from their
backs that they hide (splatting_kernels.rasterize_tiles; the stats' `hidden_in_tiles` counts
them); the splat table, bins and scratch are kept by the Renderer from frame to frame
(`CpuSplatBuffers`); per-fragment arithmetic is float32 under fastmath.
"""

from __future__ import annotations

import numba
import numpy as np

from ..cloud import PointCloud
from ..options import check_cpu_samples, fitting_supersample
from ..pinholes import fill_pinholes
from ..preprocess import drawn_normals, splat_slopes, splat_thickness
from ..result import RenderResult
from ..shading import MODEL_IDS
from . import splatting_bins as bins
from . import splatting_kernels as k
from . import splatting_tiles as t
from .ewa import (
    balanced_tile_order,
    ortho_scale,
    spatially_ordered,
    splat_axes,
    splat_clip_lines,
    splat_colors,
    target_camera,
)
from .ewa_kernels import TILE
from .splatting import DEFAULT_SUPERSAMPLES, DeferredParams, GaussianParams, PhongParams

DEPTH_CLAMP = 32.0  # splatting.glsl's: splat radii a plane's depth may stray from its centre's
# Back splats are passed by (splatting_kernels.rasterize_tiles) where the larger semi-axis of
# the cloud's median splat spans at least this many samples at the cloud's centre. Smaller
# splats leave samples their front neighbours' disks miss, which lets few back splats be passed
# by (the bench's 1M replicated bunny splats, 0.7 samples: one in seven), and the test and the
# reordering cost more than that saves (the bench's frame 3-5% slower); the tiles then draw
# their lists in order. The sphere of tests/test_splatting_cpu.py, at 1.3 samples: 58%.
HIDE_FROM_RADIUS = 1.0
BIN_CHUNKS_PER_THREAD = 4


def pack_splats(cloud: PointCloud, extras: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """A cloud's splats as the kernels read them, made once per cloud: (PACKED, N) float32
    (centre relative to the local origin, as the GPU path uploads it; unit normal, zero for a
    splat that faces the camera (preprocess.drawn_normals); the tangent axes; albedo, white
    without colours; the layer's thickness, 0 for none) and, with `extras`, (EXTRAS, N) of clip
    lines (inactive where the cloud has none) and Phong normal-field slopes (0 where none).
    One column per splat: the per-splat loop of bins.bound_splats then reads each value of
    consecutive splats from consecutive addresses (about 6% of a deferred frame, against rows).
    Row-major (N, PACKED) in Fortran order would store the same, but numba types an array of
    one splat as C-ordered, which compiled every kernel a second time for it (about 40 s)."""
    n = len(cloud)
    packed = np.zeros((t.PACKED, n), np.float32)
    packed[t.PX:t.PZ + 1] = (cloud.positions - np.asarray(cloud.local_origin, np.float64)).T
    packed[t.PNX:t.PNZ + 1] = drawn_normals(cloud).T
    packed[t.PUX:t.PVZ + 1] = splat_axes(cloud).reshape(n, 6).T
    packed[t.PR:t.PB + 1] = splat_colors(cloud).T
    packed[t.PT] = splat_thickness(cloud)
    if not extras:
        return packed, None
    extra = np.empty((t.EXTRAS, n), np.float32)
    extra[t.EA0:t.EC1 + 1] = splat_clip_lines(cloud).reshape(-1, 6).T
    slopes = splat_slopes(cloud)  # the shading field's, then the surface's: EALPHA..ECURVE_BETA
    extra[t.EALPHA:t.ECURVE_BETA + 1] = 0.0 if slopes is None else slopes.T
    return packed, extra


class CpuSplatBuffers:
    """What the frames of one cloud share: its packed splats, and the per-frame buffers they
    reuse (boxes, bins, each thread's tile table and scratch, the per-pixel flags of the last
    frame size), kept by the Renderer from frame to frame."""

    def __init__(self, cloud: PointCloud, extras: bool):
        self.packed, self.extras = pack_splats(cloud, extras)
        # the median splat's larger semi-axis (a strided sample), which `hides` projects per frame
        axes = self.packed[t.PUX:t.PVZ + 1, ::max(len(cloud) // 4096, 1)].reshape(2, 3, -1)
        self.median_radius = float(np.median(np.linalg.norm(axes, axis=1).max(axis=0))) if len(cloud) else 0.0
        # a colour or the layers' thickness that every splat shares (a cloud without colours or
        # layers) is written into the tables once, not staged for each tile (a 1M-splat bunny's
        # staging: 20 rows -> 16); only those rows are compared, a new LOD cut's buffers included
        self.constant_rows = {row: float(self.packed[row, 0]) for row in (t.PR, t.PG, t.PB, t.PT)
                              if len(cloud) and np.all(self.packed[row] == self.packed[row, 0])}
        self.staged_rows = np.array([row for row in range(t.PACKED) if row not in self.constant_rows], np.int64)
        count = len(cloud)
        self.box = np.empty((4, count), np.int32)  # a column per splat, as `packed`
        self.nearest = np.empty(count, np.float32)
        self.index = np.empty(count + count // 4 + 1, np.int32)
        self.capacity = -1  # no tables yet: the first frame makes them, even with every tile empty
        self.size = None
        self.threads = 0

    def frame(self, width: int, height: int) -> None:
        """Fit the per-size and per-thread parts to this frame (allocating only on a change)."""
        threads = numba.get_num_threads()
        if self.size == (width, height) and self.threads == threads:
            return
        self.size, self.threads = (width, height), threads
        self.tiles_x, self.tiles_y = -(-width // TILE), -(-height // TILE)
        tiles = self.tiles_x * self.tiles_y
        # per chunk, a row for its splats facing the camera and one for the others (bins.bound_splats)
        self.counts = np.empty((2 * threads * BIN_CHUNKS_PER_THREAD, tiles), np.int64)
        self.bounds = np.empty((threads * BIN_CHUNKS_PER_THREAD, 4 * bins.BOUND_BLOCK), np.int32)
        self.tile_start = np.empty(tiles, np.int64)
        self.tile_count = np.empty(tiles, np.int64)
        self.tile_front = np.empty(tiles, np.int64)
        self.tile_drawn = np.empty(tiles, np.int64)
        self.present = np.empty((height, width), np.uint8)
        self.zbuf = np.empty((threads, t.STRIDE * t.STRIDE), np.float32)
        self.cover = np.empty((threads, t.STRIDE * t.STRIDE), np.float32)
        self.accum = np.empty((threads, t.STRIDE * t.STRIDE, t.LAYER), np.float32)
        self.best = np.empty((threads, t.STRIDE * t.STRIDE), np.float32)
        self.temp = np.empty((threads, t.TEMP_ROWS * t.BLOCK), np.float32)
        self.split = np.zeros((threads, t.table_size(t.SPLIT_BLOCKS)), np.float32)
        self.split_box = np.zeros((threads, 4 * t.SPLIT_BLOCKS), np.int32)
        self.split_kept = np.zeros((threads, t.table_size(t.SPLIT_BLOCKS, t.KEPT_ROWS)), np.float32)
        self.capacity = -1

    def hides(self, camera, center, radius_scale: float) -> bool:
        """Whether this frame passes by hidden back splats: the median splat's larger semi-axis,
        at the cloud's centre, spans HIDE_FROM_RADIUS samples of `camera` (the frame's target)."""
        scale = ortho_scale(camera)
        if not scale:
            view = camera.view_matrix(np.zeros(3))
            depth = -(view[2, :3] @ np.asarray(center, np.float64) + view[2, 3])
            scale = camera.fx / max(depth, camera.near)
        return self.median_radius * radius_scale * scale >= HIDE_FROM_RADIUS

    def bin(self, hiding: bool) -> None:
        """Sort this frame's splats into tiles (after bins.bound_splats counted them, with
        `nearest` where `hiding`); make each thread's table hold the largest tile."""
        pairs, largest = bins.tile_offsets(self.counts, self.tile_start, self.tile_count, self.tile_front)
        if pairs > len(self.index):  # more tile overlaps than ever before
            self.index = np.empty(pairs + pairs // 4, np.int32)
        bins.place_splats(self.box, hiding, self.nearest, self.tiles_x, self.counts, self.index)
        self.order = balanced_tile_order(self.tile_count, self.threads)
        if largest > self.capacity:
            self.capacity = largest + largest // 4
            # two a thread: for the splats facing the camera, and the others (splatting_kernels.rasterize_tiles)
            self.tables = np.zeros((2 * self.threads, t.table_size(self.capacity)), np.float32)
            blocks = self.tables.reshape(2 * self.threads, -1, t.TABLE_ROWS, t.BLOCK)
            for row, value in self.constant_rows.items():
                blocks[:, :, row] = value
            self.boxes = np.zeros((2 * self.threads, 4 * t.table_size(self.capacity) // t.TABLE_ROWS), np.int32)
            self.kept = np.zeros((2 * self.threads, t.table_size(self.capacity, t.KEPT_ROWS)), np.float32)


def render_gaussian_cpu(cloud, camera, options, params: GaussianParams, renderer):
    return _render_cpu(cloud, camera, options, params, renderer, per_splat_shading=True,
                       supersample=DEFAULT_SUPERSAMPLES["gaussian"])


def render_deferred_cpu(cloud, camera, options, params: DeferredParams, renderer):
    return _render_cpu(cloud, camera, options, params, renderer, per_splat_shading=False, curved=True,
                       normal_field=params.phong_normals, supersample=DEFAULT_SUPERSAMPLES["deferred"])


def render_phong_cpu(cloud, camera, options, params: PhongParams, renderer):
    return _render_cpu(cloud, camera, options, params, renderer, per_splat_shading=False, curved=True,
                       normal_field=True, supersample=DEFAULT_SUPERSAMPLES["phong"])


def _camera(camera, origin) -> np.ndarray:
    """The frame's camera as the kernels read it (float32, as the GPU's uniforms): the rotation
    (row-major) and translation from the cloud's local origin to eye space, fx, fy, cx, cy, the
    orthographic pixels per unit (0: perspective), near, far."""
    view = camera.view_matrix(origin)
    return np.concatenate([view[:3, :3].ravel(), view[:3, 3], [camera.fx, camera.fy, camera.cx, camera.cy,
                                                               ortho_scale(camera), camera.near, camera.far]]
                          ).astype(np.float32)


def _color_mode(options) -> tuple[int, np.ndarray, int]:
    """The kernels' colour mode (splatting_kernels.COLOR_*), its table (the colour map's LUT or
    the palette; one white entry for rgb) and the packed categories' code levels (0: none)."""
    coloring = options.coloring
    if coloring is None or not (coloring.continuous or coloring.categorical):
        return k.COLOR_RGB, np.ones((1, 3), np.float32), 0
    if coloring.continuous:
        return k.COLOR_CONTINUOUS, coloring.table, 0
    return k.COLOR_CATEGORICAL, coloring.table, coloring.code_levels


def _render_cpu(cloud, camera, options, params, renderer, *, per_splat_shading: bool, curved: bool = False,
                normal_field: bool = False, supersample: int):
    cloud = renderer.cached(cloud, "morton order", lambda: spatially_ordered(cloud))
    ss = options.supersample or fitting_supersample(supersample, camera.width, camera.height)
    target = target_camera(camera, ss)
    width, height = target.width, target.height
    check_cpu_samples(width, height)
    extras = "clip_lines" in cloud.attributes or curved
    buffers = renderer.cached(cloud, ("cpu splat buffers", extras), lambda: CpuSplatBuffers(cloud, extras))
    buffers.frame(width, height)
    color_mode, palette, levels = _color_mode(options)
    categorical = color_mode == k.COLOR_CATEGORICAL
    model = MODEL_IDS[options.surface_shading]
    # a categorical pixel shows its winning splat's palette entry, shaded per pixel (splatting.glsl
    # PASS_NORMALIZE), whatever the method
    per_splat = per_splat_shading and not categorical
    lowpass = np.float32(params.lowpass_radius * ss if params.ewa_filter else 0.0)
    m = _camera(target, cloud.local_origin)
    clip = buffers.extras if "clip_lines" in cloud.attributes else None  # the kernels' CLIP_LINES
    hiding = buffers.hides(target, cloud.center, params.radius_scale)
    bins.bound_splats(buffers.packed, clip, m, np.float32(params.radius_scale), lowpass,
                      params.backface_culling, np.float32(DEPTH_CLAMP), width, height, buffers.box, hiding,
                      buffers.nearest, buffers.tiles_x, buffers.counts, buffers.bounds)
    buffers.bin(hiding)
    # one sample a pixel and no screen-space pass after it: the kernels write the final image
    composite = ss == 1 and not options.edl
    color = np.empty((height, width, 3), np.float32)
    alpha = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    normals = np.empty((height, width, 3), np.float32)
    indices = np.empty((height, width) if categorical else (1, 1), np.int32)
    background = np.asarray(options.background, np.float32)
    k.rasterize_tiles(buffers.packed, buffers.staged_rows, buffers.extras, buffers.box, buffers.nearest, buffers.index,
                      buffers.tile_start, buffers.tile_count, buffers.tile_front, buffers.tile_drawn, buffers.order,
                      buffers.tiles_x, width, height, m,
                      np.float32(params.radius_scale), lowpass, np.float32(params.depth_offset),
                      np.float32(DEPTH_CLAMP), clip, buffers.extras if curved else None,
                      buffers.extras if normal_field else None,
                      model if per_splat else -1,
                      -1 if per_splat else model, color_mode, palette, levels, background, composite,
                      buffers.tables, buffers.boxes, buffers.temp, buffers.kept, buffers.split, buffers.split_box,
                      buffers.split_kept, buffers.zbuf, buffers.cover, buffers.accum, buffers.best, buffers.present,
                      color, alpha, depth, normals, indices)
    k.finish_surrounded(buffers.present, color, alpha, depth, normals, background, composite)
    # tile-splat pairs that splats facing the camera hid (splatting_kernels.rasterize_tiles)
    hidden = int(buffers.tile_count.sum() - buffers.tile_drawn.sum())
    stats = {"splats": len(cloud), "supersample": ss, "ewa_filter": params.ewa_filter, "hidden_in_tiles": hidden}
    if composite:  # already over the background: the pinholes of its pixels filled (as from_samples does)
        color, alpha, depth, normals, _, filled = fill_pinholes(color, alpha, depth, normals,
                                                                indices if categorical else None)
        return RenderResult(color, alpha, depth, normals, dict(stats, pinholes=filled))
    return RenderResult.from_samples(color, alpha, depth, normals, supersample=ss, options=options, stats=stats,
                                     indices=indices if categorical else None, pinholes=True)
