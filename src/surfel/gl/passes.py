"""The render targets and blend states of three-pass splatting, shared by every method that
splats with a visibility pass (Ren et al. 2002; Botsch & Kobbelt 2003; Botsch et al. 2005):

1. visibility: MIN blending into an RG32F target: (eye depth + z_t, 1 - coverage), i.e. the
   nearest surface pushed back by z_t, and how much of the pixel some splat covers; or
   (`visibility_compute`) the same minima taken by a compute program's atomics on two R32UI
   images, then resolved into that target;
1c. occlusion (`occlusion_pass`, optional): a full-screen triangle writes the visibility
   depth into a depth buffer, which the attribute and category passes then test their
   splats against, each drawn at the nearest depth any of its fragments can have: a
   conservative early cull of hidden splats' fragments before their fragment shader runs,
   which leaves every sum unchanged (the shaders still compare each fragment's exact depth);
2. attribute: additive blending into two RGBA32F accumulators: (w rgb, w) and (w n, w z),
   of fragments no farther than the visibility depth; or (`attribute_compute`) the same sums
   taken by a compute program's integer atomics in fixed point in a storage buffer
   (passes.glsl ACCUMULATOR_SUMS);
3. normalization: a full-screen triangle turns the sums (the accumulators', or with
   ACCUMULATOR_SUMS the storage buffer's, read where they lie: resolving them into the
   accumulators first cost llvmpipe a tenth of a bench frame) into the G-buffer layout of
   targets.gbuffer_result (shaded RGB + coverage, eye normal, eye depth).

Categorical colour modes add, after the attribute pass,
2c. category: MAX blending into an RG32F target of the packed (weight, palette index) of the
   attribute pass's fragments (colors.glsl), per layer (front, back); the normalization pass
   reads it at unit 15.

With a back layer (`back_layer=True`, the EWA method's A-buffer-like compositing of the
visible surface over the one behind it at partly covered pixels):
1b. back: MIN blending into an R32F target: the depth of the nearest fragment behind the
   visible surface;
2.  attribute: four accumulators, (w rgb, w) and (w n, w z) of each layer, read back by
   `accumulators()`.

Texture units seen by the shaders: 1 visibility, 2 (w rgb, w), 3 (w n, w z), 4 back; unit 0
is the method's kernel texture; storage buffer 1 holds the compute pass's sums. `guard` pixels
of margin on each side of the splat targets let rasterized point sprites centred outside the
image reach into it (the compute passes clip each sprite to the targets themselves and draw
on targets without one); the output has the image's size.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SurfelError
from ..files import write_atomically
from .context import get_context
from .targets import GBuffer, allocating, gbuffer_result, read_texture
from .uniforms import CATEGORY_UNIT

UNIFORM_UNITS = {"u_visibility": 1, "u_accum_color": 2, "u_accum_normal": 3, "u_category": CATEGORY_UNIT}
BACK_LAYER_UNITS = {"u_visibility": 1, "u_back": 4}  # the back layer's programs (ewa_gl.glsl)
FAR = 3.0e38
SUM_CHANNELS = 8  # passes.glsl
SUM_SCALE = 4194304.0  # passes.glsl


@dataclass
class SplatTargets:
    """The float targets of one frame size and their framebuffers; the back layer's only with
    `back_layer` (else None and empty). Kept from frame to frame by `rendering.Renderer`."""

    guard: int
    visibility: object
    visibility_fbo: object
    accum: list
    accum_fbo: object        # the front accumulators, then the back layer's
    out: GBuffer
    category: object = None
    category_fbo: object = None
    back: object = None
    back_fbo: object = None
    back_accum: list = field(default_factory=list)
    depth: object = None      # the attribute pass's depth buffer (occlusion culling)
    occlusion_fbo: object = None
    minima: list = field(default_factory=list)  # the compute visibility pass's images and their clear values
    sums: object = None       # the compute attribute pass's fixed-point sums
    sums_dirty: bool = False  # summed into since they were last zeroed

    def compute_images(self) -> list:
        """[(nearest, its clear buffer), (uncovered, its clear buffer)]: R32UI images of the
        bits of (depth + z_t, 1 - coverage), made on first use."""
        if not self.minima:
            ctx = get_context()
            size = self.visibility.size
            with allocating(*size):
                for clear in (FAR, 1.0):
                    image = ctx.texture(size, 1, dtype="u4")
                    bits = np.full(size[0] * size[1], clear, np.float32).view(np.uint32)
                    self.minima.append((image, ctx.buffer(bits.tobytes())))
        return self.minima

    def accumulator_sums(self):
        """The compute attribute pass's sums (passes.glsl ACCUMULATOR_SUMS: 8 uints a pixel),
        zero (a memset, far cheaper than zeroing them in a shader), made on first use."""
        if self.sums is None:
            width, height = self.visibility.size
            with allocating(width, height):
                self.sums = get_context().buffer(reserve=SUM_CHANNELS * 4 * width * height)
                self.sums.clear()
        elif self.sums_dirty:
            self.sums.clear()
        self.sums_dirty = False
        return self.sums

    @classmethod
    def allocate(cls, width: int, height: int, guard: int = 0, back_layer: bool = False) -> SplatTargets:
        ctx = get_context()
        target = (width + 2 * guard, height + 2 * guard)
        with allocating(*target):
            visibility = ctx.texture(target, 2, dtype="f4")
            accum = [ctx.texture(target, 4, dtype="f4") for _ in range(2)]
            back = ctx.texture(target, 1, dtype="f4") if back_layer else None
            back_accum = [ctx.texture(target, 4, dtype="f4") for _ in range(2)] if back_layer else []
            category = ctx.texture(target, 2, dtype="f4")
            depth = ctx.depth_texture(target)
            for tex in (visibility, *accum, *back_accum, *([back] if back else []), category):
                tex.filter = (ctx.NEAREST, ctx.NEAREST)
            accum_fbo = ctx.framebuffer(color_attachments=accum + back_accum, depth_attachment=depth)
            category_fbo = ctx.framebuffer(color_attachments=[category], depth_attachment=depth)
            for fbo in (accum_fbo, category_fbo):
                fbo.depth_mask = False  # the passes test the occlusion pass's depths, never write or clear them
            return cls(guard, visibility, ctx.framebuffer(color_attachments=[visibility]), accum, accum_fbo,
                       GBuffer(width, height), category, category_fbo,
                       back, ctx.framebuffer(color_attachments=[back]) if back else None, back_accum,
                       depth, ctx.framebuffer(depth_attachment=depth))

    def release(self) -> None:
        for obj in (self.visibility, self.visibility_fbo, *self.accum, self.accum_fbo, self.out,
                    self.category, self.category_fbo, self.back, self.back_fbo, *self.back_accum,
                    self.depth, self.occlusion_fbo, *(obj for pair in self.minima for obj in pair), self.sums):
            if obj is not None:
                obj.release()


class SplatPasses:
    """Use as a context manager around one frame drawn into `targets`."""

    def __init__(self, targets: SplatTargets):
        ctx = self.ctx = get_context()
        t = self.targets = targets
        self.guard = t.guard
        self.visibility, self.visibility_fbo, self.accum, self.accum_fbo, self.out = \
            t.visibility, t.visibility_fbo, t.accum, t.accum_fbo, t.out
        self.back, self.back_fbo, self.back_accum = t.back, t.back_fbo, t.back_accum
        self.category = t.category
        self.summed = False  # this frame's attribute pass summed into the compute sums
        self.uniform_color = None
        ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.enable(ctx.BLEND | ctx.PROGRAM_POINT_SIZE)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.ctx.blend_equation = self.ctx.FUNC_ADD
        self.ctx.disable(self.ctx.DEPTH_TEST)
        self.ctx.depth_func = "<"  # OpenGL's default, which the other methods draw with

    def _min_blended(self, fbo, clear: tuple, draw) -> None:
        fbo.use()
        fbo.clear(*clear)
        self.ctx.enable(self.ctx.BLEND)
        self.ctx.blend_equation = self.ctx.MIN
        draw()

    def visibility_pass(self, draw) -> None:
        self._min_blended(self.visibility_fbo, (FAR, 1.0, 0.0, 0.0), draw)

    def visibility_compute(self, dispatch, resolve_program) -> None:
        """The visibility pass by a compute program: `dispatch()` runs it over the splats with
        the two images of `SplatTargets.compute_images` bound at image units 0 and 1;
        `resolve_program` (passes.glsl PASS_RESOLVE) then writes them into the visibility
        target, as visibility_pass leaves it."""
        ctx = self.ctx
        images = self.targets.compute_images()
        for unit, (image, clear) in enumerate(images):
            image.write(clear)
            image.bind_to_image(unit, read=True, write=True)
        ctx.memory_barrier()
        dispatch()
        ctx.memory_barrier()
        self.visibility.bind_to_image(2, read=False, write=True)
        width, height = self.visibility.size
        resolve_program.run(-(-width // 16), -(-height // 16))
        ctx.memory_barrier()

    def attribute_compute(self, dispatch, uniform_color: float | None) -> None:
        """The attribute pass by a compute program (after the visibility pass): `dispatch()`
        runs it over the splats with the visibility target at texture unit 1 and the zeroed
        sums at storage binding 1, where the normalization pass (with ACCUMULATOR_SUMS) then
        reads them. `uniform_color`: every splat's albedo code where the sums skip the colour
        (passes.glsl UNIFORM_COLOR), else None."""
        targets = self.targets
        targets.accumulator_sums().bind_to_storage_buffer(1)
        self.visibility.use(1)
        targets.sums_dirty = True
        self.summed, self.uniform_color = True, uniform_color
        dispatch()
        self.ctx.memory_barrier()

    def back_pass(self, draw) -> None:
        """The back layer's depth (after visibility_pass)."""
        self.visibility.use(1)
        self._min_blended(self.back_fbo, (FAR, 0.0, 0.0, 0.0), draw)

    def occlusion_pass(self, program) -> None:
        """The visibility depths into the depth buffer (after visibility_pass), so that the
        attribute and category passes depth-test their splats against them."""
        ctx = self.ctx
        ctx.disable(ctx.BLEND)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.depth_func = "1"  # always: every pixel's depth written
        self.targets.occlusion_fbo.use()
        self.visibility.use(1)
        self._full_screen(program)
        ctx.depth_func = "<="  # the splat passes: drawn where their nearest depth is not behind it

    def _full_screen(self, program) -> None:
        triangle = self.ctx.vertex_array(program, [])
        triangle.render(self.ctx.TRIANGLES, vertices=3)
        triangle.release()

    def attribute_pass(self, draw) -> None:
        ctx = self.ctx
        self.accum_fbo.use()
        self.accum_fbo.clear(0.0, 0.0, 0.0, 0.0)
        ctx.enable(ctx.BLEND)
        ctx.blend_equation = ctx.FUNC_ADD
        ctx.blend_func = ctx.ONE, ctx.ONE
        self.visibility.use(1)
        if self.back is not None:
            self.back.use(4)
        draw()

    def category_pass(self, draw) -> None:
        """The packed category of the heaviest splat per pixel and layer (after attribute_pass)."""
        self.visibility.use(1)
        if self.back is not None:
            self.back.use(4)
        self._max_blended(self.targets.category_fbo, draw)
        self.category.use(CATEGORY_UNIT)

    def _max_blended(self, fbo, draw) -> None:
        fbo.use()
        fbo.clear(-1.0, -1.0, 0.0, 0.0)
        self.ctx.enable(self.ctx.BLEND)
        self.ctx.blend_equation = self.ctx.MAX
        draw()

    def categories(self) -> np.ndarray:
        """The category pass's packed values (H, W, 2): front layer, back layer."""
        return read_texture(self.category)

    def coverage(self) -> np.ndarray:
        """How much of each pixel (H, W) the visibility pass's splats cover."""
        return 1.0 - read_texture(self.visibility)[..., 1]

    def accumulators(self) -> np.ndarray:
        """The attribute pass's sums as one (H, W, 4 x layers) array, front layer first."""
        return np.concatenate([read_texture(t) for t in (*self.accum, *self.back_accum)], axis=-1)

    def accumulated_color(self) -> np.ndarray:
        """The attribute pass's (w rgb, w) as an (H, W, 4) array, row 0 at the top: the
        accumulator's, or decoded from the compute pass's sums (passes.glsl ACCUMULATOR_SUMS)."""
        if not self.summed:
            return read_texture(self.accum[0])
        width, height = self.visibility.size
        sums = np.frombuffer(self.targets.sums.read(), np.int32).reshape(height, width, SUM_CHANNELS)[::-1]
        color = sums[..., :4] / np.float32(SUM_SCALE)
        if self.uniform_color is not None:
            color[..., :3] = color[..., 3:] * np.float32(self.uniform_color)
        return color

    def normalize_pass(self, program) -> None:
        ctx = self.ctx
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
        self.out.fbo.use()  # no clear: the full-screen triangle writes every pixel of every target
        self.visibility.use(1)
        self.accum[0].use(2)
        self.accum[1].use(3)
        self.category.use(CATEGORY_UNIT)
        if self.summed:
            self.targets.sums.bind_to_storage_buffer(1)
        self._full_screen(program)
        ctx.finish()

    def result(self, camera, options, supersample: int, stats: dict):
        result = gbuffer_result(self.out, camera, options, supersample, stats, pinholes=True)
        if options.dump_passes is not None:
            self.dump(options.dump_passes, result)
        return result

    def dump(self, folder, result) -> None:
        """The survey's Fig. 5: visibility depth, accumulated weight and colour, final image."""
        from PIL import Image

        folder = Path(folder)
        try:
            folder.mkdir(exist_ok=True)  # not its parents: like every output, it goes in an existing folder
        except OSError as exc:
            raise SurfelError(f"{folder}: cannot write the passes here: {exc.strerror}") from None
        g = self.guard
        inner = (slice(g, self.visibility.height - g), slice(g, self.visibility.width - g))
        depth = read_texture(self.visibility)[inner][..., 0]
        valid = depth < FAR / 10
        gray = np.zeros_like(depth)
        if valid.any():
            lo, hi = depth[valid].min(), depth[valid].max()
            gray[valid] = 1 - 0.8 * (depth[valid] - lo) / max(hi - lo, 1e-12)
        color = self.accumulated_color()[inner]
        weight = color[..., 3] / max(float(color[..., 3].max()), 1e-12)

        def save(name, image):
            picture = Image.fromarray(np.round(np.clip(image, 0, 1) * 255).astype(np.uint8))
            write_atomically(folder / name, lambda file: picture.save(file, format="PNG"))

        save("1-visibility-depth.png", gray)
        save("2-accumulated-weight.png", weight)
        save("3-accumulated-color.png", np.clip(color[..., :3], 0, 1))
        save("4-normalized.png", result.color)
