"""Float render targets and readback (rows flipped so row 0 is the top of the image).

Every render target is checked before it is allocated (`check_target_size`): each side
against what the context allows (GL_MAX_TEXTURE_SIZE, GL_MAX_RENDERBUFFER_SIZE,
GL_MAX_VIEWPORT_DIMS). Beyond them drivers fail in ways no caller can report (an incomplete
framebuffer, or a native abort), so the size is refused in one line naming the options that
set it; an allocation the driver refuses all the same (out of memory) is reported likewise.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

from ..errors import SurfelError
from .context import get_context

SIZE_OPTIONS = "--size/--supersample"  # how messages name what sets a target's size


def max_target_side() -> int:
    """The longest side of a render target this context can draw into."""
    info = get_context().info
    return int(min(info["GL_MAX_TEXTURE_SIZE"], info["GL_MAX_RENDERBUFFER_SIZE"], *info["GL_MAX_VIEWPORT_DIMS"]))


def check_target_size(width: int, height: int) -> None:
    """Refuse a width x height render target (the image times its supersampling, plus any
    guard band) that this context cannot hold (module docstring)."""
    limit = max_target_side()
    if max(width, height) > limit:
        raise SurfelError(f"{SIZE_OPTIONS}: rendering needs {width}x{height} render targets (the image size times "
                          f"the supersampling, plus any guard band), more than this OpenGL context's limit of "
                          f"{limit} pixels a side; choose a smaller --size or --supersample")


@contextlib.contextmanager
def allocating(width: int, height: int):
    """Checks the size first, then turns a driver's refusal of the block's allocations (a
    moderngl.Error: out of memory, an incomplete framebuffer) into one line."""
    import moderngl

    check_target_size(width, height)
    try:
        yield
    except moderngl.Error as exc:
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise SurfelError(f"{SIZE_OPTIONS}: OpenGL could not allocate {width}x{height} render targets ({reason}); "
                          "choose a smaller --size or --supersample") from None


def read_rows(tex) -> np.ndarray:
    """A float32 texture as a writable (H, W, C) array with row 0 at the top: a flipped view of
    the rows OpenGL returns, not a copy (the G-buffer's readers take strided arrays)."""
    data = np.empty((tex.height, tex.width, tex.components), np.float32)
    tex.read_into(data)
    return data[::-1]


def read_texture(tex, components: int | None = None) -> np.ndarray:
    """A float32 texture as a contiguous (H, W, C) array with row 0 at the top (its first
    `components` channels)."""
    return np.ascontiguousarray(read_rows(tex)[..., :components or tex.components])


@dataclass
class GBuffer:
    """A method's output samples, laid out as `gbuffer_result` reads them: colour targets of
    RGBA32F (shaded RGB and coverage; eye normal and palette index) and R32F (eye depth, one
    channel rather than four for every pass to write and the read-back to copy), and a depth
    buffer for the methods that depth-test, all the same size."""

    width: int
    height: int

    def __post_init__(self):
        ctx = get_context()
        with allocating(self.width, self.height):
            self.textures = [ctx.texture((self.width, self.height), components, dtype="f4")
                             for components in (4, 4, 1)]
            for t in self.textures:
                t.filter = (0x2600, 0x2600)  # GL_NEAREST: the passes read texels, never interpolate
            self.depth = ctx.depth_texture((self.width, self.height))
            self.fbo = ctx.framebuffer(color_attachments=self.textures, depth_attachment=self.depth)
            self.depth_only = ctx.framebuffer(depth_attachment=self.depth)

    def clear(self, depth: float = 1.0):
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=depth)

    def release(self):
        for obj in (*self.textures, self.depth, self.fbo, self.depth_only):
            obj.release()


def gbuffer_result(gbuffer: GBuffer, camera, options, supersample: int, stats: dict, *, surface=None,
                   pinholes: bool = False):
    """The RenderResult of a G-buffer laid out as every method writes it: target 0 = shaded
    RGB and coverage, target 1 = eye normal and, in a categorical colour mode, the palette
    index of the category the shaders picked, target 2 = eye depth. `surface`: for methods
    without splats, a function of the sample depths (H, W) giving each sample's albedo and
    palette index (colors.surface_albedo), or None; the samples are shaded again with them.
    `pinholes`: fill them (RenderResult.from_samples), for the splatting methods."""
    from ..colors import shade_samples
    from ..result import RenderResult

    # views of the read-back targets, not copies: from_samples and the pinholes take strided arrays
    shaded, normals, depth = (read_rows(texture) for texture in gbuffer.textures)
    coverage, depth = np.clip(shaded[..., 3], 0, 1), depth[..., 0]
    indices, rgb = None, shaded[..., :3]
    albedo = None
    if surface is not None:  # these read the empty samples' depths as inf
        depth = np.where(coverage > 0, depth, np.inf)
        albedo, indices = surface(depth)
    if albedo is not None:
        rgb = shade_samples(rgb, normals[..., :3], depth, albedo, options.surface_shading, camera.near, camera.far)
    elif options.coloring is not None and options.coloring.categorical:
        indices = np.where(coverage > 0, np.round(normals[..., 3]), -1).astype(np.int32)
    return RenderResult.from_samples(rgb, coverage, depth, normals[..., :3],
                                     supersample=supersample, options=options, stats=stats, indices=indices,
                                     pinholes=pinholes)
