"""Splat geometry on the GPU: per-point attributes packed into vertex buffers, drawn in chunks.

Every splat method reads the same layout (see splat_common.glsl):
    in_center (3) position relative to the cloud's local origin (float32 safe for LiDAR)
    in_normal (3) unit normal; zero for a splat that faces the camera (preprocess.structure)
    in_color  (3) RGB albedo
    in_axis_u (3), in_axis_v (3) tangent axes scaled to the ellipse semi-axes
    in_field  (4) the normal field's slopes: Phong splatting's (alpha, beta) that shade the
                  splat, then those that shape a curved one (surfel.preprocess.normal_field), 0
                  when absent
    in_lod    (3) sequential point tree node: e_g, parent's e_g, distance to the parent
                  (surfel.lod; a cloud without them is all leaves that always pass)
    in_clip0 (3), in_clip1 (3) clip lines (a, b, c) at sharp features: the splat keeps
                  a u + b v <= c in its local coordinates (surfel.preprocess; (0, 0, 1) cuts nothing)
    in_thickness (1) its layer's thickness, the cap of z_t (preprocess/thickness.py); 0 for none
Clouds larger than CHUNK points are drawn one chunk at a time so 10M+ points fit in memory;
a cloud's buffers are kept (by `rendering.Renderer`) so benchmarks measure drawing, not uploading.
Compute programs read the same packed rows from RGBA32F textures, made from a kept chunk the
first time one runs (`SplatBuffers.texels`, splat_attributes.glsl load_splat); `compute_chunks`
binds them.
"""

from __future__ import annotations

import weakref

import numpy as np

from ..cloud import PointCloud
from ..preprocess import INACTIVE_CLIP, drawn_normals, splat_slopes, splat_thickness
from .context import get_context
from .program import set_uniforms
from .uniforms import SPLATS_UNIT

CHUNK = 2_000_000
ATTRIBUTES = ("in_center", "in_normal", "in_color", "in_axis_u", "in_axis_v", "in_field", "in_lod",
              "in_clip0", "in_clip1", "in_thickness")
WIDTHS = (3, 3, 3, 3, 3, 4, 3, 3, 3, 1)
LOD_EXTRAS = ("lod_emin", "lod_emax", "lod_dparent")
FLOATS = sum(WIDTHS)
TEXELS = -(-FLOATS // 4)  # RGBA texels a splat in the compute programs' textures (splat_attributes.glsl)
TEXTURE_ROW = 512  # splats a row of those textures: 4096 texels wide, CHUNK splats 3907 rows high
COMPUTE_GROUP = 64    # the local size of splatting.glsl's compute programs
CACHE_LIMIT_BYTES = 2_000_000_000
NO_COLOR = 1.0  # the albedo code packed for every splat of a cloud without colours

def pack(cloud: PointCloud, start: int = 0, stop: int | None = None) -> np.ndarray:
    """(n, FLOATS) float32 interleaved attributes for points [start, stop)."""
    stop = len(cloud) if stop is None else stop
    n = stop - start
    out = np.empty((n, FLOATS), np.float32)
    out[:, 0:3] = cloud.positions[start:stop] - cloud.local_origin
    out[:, 3:6] = drawn_normals(cloud, start, stop) if cloud.normals is not None else (0, 0, 1)
    out[:, 6:9] = cloud.colors[start:stop] if cloud.colors is not None else NO_COLOR
    if cloud.axes is not None:
        out[:, 9:15] = cloud.axes[start:stop].reshape(n, 6)
    else:
        out[:, 9:15] = 0.0
    slopes = splat_slopes(cloud, start, stop)
    out[:, 15:19] = 0.0 if slopes is None else slopes
    if all(key in cloud.attributes for key in LOD_EXTRAS):
        out[:, 19:22] = np.stack([cloud.attributes[key][start:stop] for key in LOD_EXTRAS], axis=1)
    else:
        out[:, 19:22] = (0.0, np.finfo(np.float32).max, 0.0)
    if "clip_lines" in cloud.attributes:
        out[:, 22:28] = cloud.attributes["clip_lines"][start:stop].reshape(n, 6)
    else:
        out[:, 22:28] = INACTIVE_CLIP * 2
    out[:, 28] = splat_thickness(cloud, start, stop)
    return out


class SplatBuffers:
    """A cloud's packed attributes on the GPU, in chunks: uploaded once and kept (by their
    owner, `rendering.Renderer`) when they fit CACHE_LIMIT_BYTES, else uploaded chunk by
    chunk on every draw."""

    def __init__(self, cloud: PointCloud):
        self.cloud = weakref.ref(cloud)  # not a strong reference: the owner caches these per cloud
        self.count = len(cloud)
        self.kept = None
        self.textures = None
        if self.count * FLOATS * 4 <= CACHE_LIMIT_BYTES:
            ctx = get_context()
            self.kept = [(ctx.buffer(pack(cloud, start, min(start + CHUNK, self.count))),
                          min(start + CHUNK, self.count) - start) for start in range(0, self.count, CHUNK)]

    def texels(self) -> list:
        """The kept chunks' rows as (texture, count): TEXELS texels a splat, TEXTURE_ROW splats
        a row; made on the first call, since only compute programs read them. A cloud the
        compute passes draw then holds its rows twice on the GPU (the buffers serve the
        rasterized passes)."""
        if self.textures is None:
            ctx = get_context()
            self.textures = []
            for start in range(0, self.count, CHUNK):
                rows = pack(self.cloud(), start, min(start + CHUNK, self.count))
                padded = np.zeros((-(-len(rows) // TEXTURE_ROW) * TEXTURE_ROW, 4 * TEXELS), np.float32)
                padded[:len(rows), :FLOATS] = rows
                texture = ctx.texture((TEXTURE_ROW * TEXELS, len(padded) // TEXTURE_ROW), 4, padded, dtype="f4")
                texture.filter = (ctx.NEAREST, ctx.NEAREST)
                self.textures.append((texture, len(rows)))
        return self.textures

    def chunks(self):
        """Yield (vbo, count) pairs covering the cloud."""
        if self.kept is not None:
            yield from self.kept
            return
        ctx = get_context()
        cloud = self.cloud()
        for start in range(0, self.count, CHUNK):
            stop = min(start + CHUNK, self.count)
            vbo = ctx.buffer(pack(cloud, start, stop))
            yield vbo, stop - start
            vbo.release()

    def release(self) -> None:
        for vbo, _ in (self.kept or []) + (self.textures or []):
            vbo.release()


def vertex_array(ctx, program, vbo, *, instanced: bool, extra=()):
    """A VAO over a packed chunk; attributes the compiler dropped from `program` become padding.
    `extra`: further (buffer, name) pairs of one float per point."""
    fmt, names = [], []
    for name, width in zip(ATTRIBUTES, WIDTHS, strict=True):
        if name in program:
            fmt.append(f"{width}f")
            names.append(name)
        else:
            fmt.append(f"{4 * width}x")
    step = "/i" if instanced else ""
    return ctx.vertex_array(program, [(vbo, " ".join(fmt) + step, *names)]
                            + [(buffer, "1f" + step, name) for buffer, name in extra])


def draw(ctx, buffers: SplatBuffers, program, mode, *, instanced: bool, count: int | None = None,
         extra: dict[str, np.ndarray] | None = None):
    """Draw the first `count` points (all by default) of a cloud's buffers with `program`:
    instanced 4-vertex strips, or one vertex a point. `extra` maps attribute names to per-point
    floats computed per frame (uploaded chunk by chunk beside the kept attributes)."""
    remaining = buffers.count if count is None else count
    start = 0
    for vbo, chunk in buffers.chunks():
        count = min(chunk, remaining)
        remaining -= count
        if count > 0:
            buffers = [(ctx.buffer(np.ascontiguousarray(values[start:start + count], np.float32)), name)
                       for name, values in (extra or {}).items() if name in program]
            vao = vertex_array(ctx, program, vbo, instanced=instanced, extra=buffers)
            if instanced:
                vao.render(mode, vertices=4, instances=count)
            else:
                vao.render(mode, vertices=count)
            vao.release()
            for buffer, _ in buffers:
                buffer.release()
        start += chunk


def max_storage_bytes() -> int:
    """The largest storage buffer range a shader may use (GL_MAX_SHADER_STORAGE_BLOCK_SIZE:
    128 MiB on llvmpipe, GPUs' at least that)."""
    return int(get_context().info["GL_MAX_SHADER_STORAGE_BLOCK_SIZE"])


def compute_chunks(buffers: SplatBuffers, program, count: int | None = None):
    """Yield the number of splats of each kept chunk holding the first `count` splats (all by
    default), its texture (`SplatBuffers.texels`) bound at SPLATS_UNIT and `program`'s
    u_splat_count set; the caller runs `program` over `compute_groups(splats)` work groups."""
    remaining = buffers.count if count is None else count
    for texture, chunk in buffers.texels():
        splats = min(chunk, remaining)
        remaining -= splats
        if splats <= 0:
            return
        texture.use(SPLATS_UNIT)
        set_uniforms(program, u_splats=SPLATS_UNIT, u_splat_count=splats)
        yield splats


def compute_groups(splats: int) -> int:
    """Work groups of COMPUTE_GROUP invocations, one a splat."""
    return max(-(-splats // COMPUTE_GROUP), 1)


def lod_frame(cloud: PointCloud, camera, lod_error: float | None):
    """Per-frame sequential point tree parameters: (u_lod_k, prefix to draw, drawn mask).

    Without LOD: k = 0 (the shader test passes everything), the whole cloud, mask None.
    The mask is the CPU twin of the shader test, for the stats and the sprite-size bound.
    """
    if lod_error is None:
        return 0.0, None, None
    from ..lod import frame_parameters, select_sequential

    prefix, k = frame_parameters(cloud, camera, lod_error)
    return k, prefix, select_sequential(cloud, camera, lod_error)
