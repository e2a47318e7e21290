"""`render()` and the `Renderer`: one entry point for every method and backend (numpy in,
RenderResult out), and the one owner of everything kept from one frame to the next.

Before anything is estimated, the Renderer applies --classes and --returns and resolves
what the data decides (surfel.colors, surfel.shading): the colour mode (rgb where the cloud
has colours, else elevation for geospatial data) with its range, and the shading (eye-dome
lighting for a geospatial cloud without normals, else phong). The cloud a method draws
carries the colour mode's encoded colours (`colors.Coloring.encode`); the options it gets
carry the resolved `coloring`. All of it is reported in the stats.

A Renderer keeps, per cloud, what is derived from it once and reused every frame: the
filtered cloud, its colour mode, the completed cloud (estimated normals, radii, normal
fields), its sequential point tree and the last level-of-detail subset, the encoded colours,
the EWA rasterizer's Morton order, object-space EWA's per-surfel weights, the MLS ray tracing
scene, the neighbour tree that picks the categories of methods without splats, and the
cloud's GPU buffers. Clouds are keyed by identity,
held weakly: a PointCloud and its arrays cannot change, so what was derived from one stays
true, and an entry goes when its cloud goes (its GL objects are released on the next frame).
It also keeps the compiled GL programs, the three-pass targets of the last frame size and
those a method draws with itself (the MLS caster's), also of the last size, and the colour
table of the last colour mode.
Its lifetime is the object's: `close()`, or leaving a `with` block, releases its GL objects.
`surfel.render()` uses a module-level Renderer; the viewer, turntable, bench and each batch
worker hold their own.
"""

from __future__ import annotations

import sys
import time
import weakref
from dataclasses import replace

import numpy as np

from . import colors
from .camera import Camera, frame
from .cloud import PointCloud, render_unit
from .compile_ahead import CompileAhead, render_spec
from .errors import SurfelError
from .methods import DEFAULT_METHOD, get_method
from .options import RenderOptions
from .result import RenderResult
from .shading import default_for


def default_camera(cloud: PointCloud, size=(1024, 1024), **framing) -> Camera:
    """The auto-framing camera of docs/conventions.md for this cloud."""
    return frame(cloud.center, cloud.bounding_radius, geospatial=cloud.geospatial, size=size, bounds=cloud.bounds,
                 **framing)


# GL_RENDERER names of software rasterizers (Mesa's llvmpipe and softpipe, SwiftShader, the
# old swrast): where OpenGL runs on the CPU anyway, a rasterizer written for the CPU is faster.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swiftshader", "software rasterizer", "swrast")


def is_software_renderer(renderer: str) -> bool:
    """Whether a GL_RENDERER string names a software rasterizer."""
    return any(name in renderer.lower() for name in SOFTWARE_RENDERERS)


def choose_backend(method_name: str, backend: str | None, *, dump_passes: bool = False) -> tuple[str, str]:
    """The backend to use and why. As asked; else (auto) the CPU where the method's CPU path
    beats the GL renderer because that is a software rasterizer (`Method.cpu_beats_software_gl`,
    measured with `surfel bench`) and no GL-only option (--dump-passes) is set; else OpenGL;
    else the CPU with a one-line notice."""
    method = get_method(method_name)
    if backend is not None:
        method.function(backend)  # validates
        return backend, "asked"
    if "gl" in method.backends:
        from .gl.context import get_context, gl_available, renderer_string

        if gl_available():
            renderer = renderer_string()
            if "cpu" in method.backends and method.cpu_beats_software_gl and is_software_renderer(renderer) \
                    and not (dump_passes and "cpu" not in method.dump_passes):
                return "cpu", f"auto: the GL renderer is a software rasterizer ({renderer}); the CPU path is faster"
            return "gl", f"auto: {renderer}"
        if "cpu" in method.backends:
            print(f"surfel: no OpenGL context, rendering {method_name} on the CPU", file=sys.stderr)
            return "cpu", "auto: no OpenGL context"
        get_context()  # raises NoOpenGLError with the install hint
    return next(iter(method.backends)), "auto: the method's only backend"


# eps of a lazy source rendered without --lod-error: it cannot be drawn at full detail
SOURCE_DEFAULT_LOD_ERROR = 1.0


def split_options(method: str, values: dict, options: RenderOptions | None = None) -> RenderOptions:
    """RenderOptions from keyword values: RenderOptions fields and the method's parameters, on
    top of `options` (and its params) when given; a name that is neither is refused."""
    m = get_method(method)
    common = {k: v for k, v in values.items() if k in RenderOptions.names()}
    named = {k: v for k, v in values.items() if k not in common}
    options = options or RenderOptions()
    if common:
        options = replace(options, **common)
    if not named:
        return options
    cls = m.params_class()
    for name in named:
        if name not in cls.names():
            known = ", ".join([n for n in RenderOptions.names() if n != "params"] + list(cls.names()))
            raise SurfelError(f"render: method {method!r} has no option {name!r}; it has: {known}")
    m.check_options(options)
    start = options.params if options.params is not None else m.make_params()
    return replace(options, params=replace(start, **named))


class Renderer:
    """Renders clouds and keeps what one frame leaves for the next (see the module docstring)."""

    def __init__(self, *, compile_ahead: bool = True):
        """compile_ahead: on the first CPU render after installing, compile the method's kernels
        in a helper process while the cloud is completed (compile_ahead.py); off where every
        core already renders (the batch's workers)."""
        self.compile_ahead = compile_ahead
        self._per_cloud: weakref.WeakKeyDictionary[PointCloud, dict] = weakref.WeakKeyDictionary()
        self._programs: dict = {}
        self._targets: tuple | None = None  # (size key, gl.passes.SplatTargets)
        self._kept_targets: dict = {}  # a method's own targets by kind: (key, targets) of the last key
        self._color_table: tuple | None = None  # (Coloring, its GL texture)
        self._released_clouds: list = []  # GL objects of clouds that are gone, released on the next frame

    # ---- the caches methods use -----------------------------------------------------
    def cached(self, cloud: PointCloud, key, make, *, version=None):
        """`make()` computed once per cloud and key. With `version`, only the latest version
        is kept: a different one recomputes (the last LOD subset, keyed by the view)."""
        entries = self._per_cloud.setdefault(cloud, {})
        entry = entries.get(key)
        if entry is None or entry[0] != version:
            value = make()
            if value is cloud or (isinstance(value, tuple) and value[0] is cloud):
                return value  # nothing derived (already complete): storing it would keep the cloud alive
            entry = entries[key] = (version, value)
        return entry[1]

    def cached_gl(self, cloud: PointCloud, key, make):
        """As `cached`, for an object with GL resources (`release()`): released with the
        Renderer, or on the next frame once its cloud is gone."""
        entries = self._per_cloud.setdefault(cloud, {})
        if key not in entries:
            value = make()
            entries[key] = (None, value)
            weakref.finalize(cloud, self._released_clouds.append, value)
        return entries[key][1]

    def program(self, path, defines: dict | None = None, *, geometry: bool = False, compute: bool = False):
        """The GL program of `path` with these #defines (`compute`: its compute shader),
        compiled once."""
        key = (str(path), tuple(sorted((defines or {}).items())), geometry, compute)
        if key not in self._programs:
            from .gl.program import build_program

            self._programs[key] = build_program(path, defines, geometry=geometry, compute=compute)
        return self._programs[key]

    def splat_buffers(self, cloud: PointCloud):
        """The cloud's splat attributes on the GPU (gl.splats.SplatBuffers)."""
        from .gl.splats import SplatBuffers

        return self.cached_gl(cloud, "splat buffers", lambda: SplatBuffers(cloud))

    def splat_targets(self, width: int, height: int, guard: int = 0, back_layer: bool = False):
        """The three-pass float targets of this size; those of the last size are kept, since
        animations and benchmarks render many frames of one size."""
        from .gl.passes import SplatTargets

        key = (width, height, guard, back_layer)
        if self._targets is None or self._targets[0] != key:
            if self._targets is not None:
                self._targets[1].release()
            self._targets = None  # nothing kept if the allocation fails
            self._targets = (key, SplatTargets.allocate(width, height, guard, back_layer))
        return self._targets[1]

    def targets(self, kind: str, key, make):
        """A method's own GL targets (`release()`), made by `make()` for `key` (their size);
        those of the last key of each kind are kept, as `splat_targets` keeps its own."""
        kept = self._kept_targets.get(kind)
        if kept is None or kept[0] != key:
            if kept is not None:
                self._kept_targets.pop(kind)[1].release()  # nothing kept if the allocation fails
            self._kept_targets[kind] = (key, make())
        return self._kept_targets[kind][1]

    def use_color_table(self, options: RenderOptions) -> None:
        """Bind the colour mode's LUT or palette (gl/colors.glsl's u_color_table), 256
        entries a row; made once per colour mode."""
        from .gl.context import get_context
        from .gl.uniforms import COLOR_TABLE_UNIT

        coloring = options.coloring
        if self._color_table is None or self._color_table[0] is not coloring:
            if self._color_table is not None:
                self._color_table[1].release()
            self._color_table = None
            table = coloring.table if coloring is not None else np.ones((1, 3), np.float32)
            rows = -(-len(table) // 256)
            padded = np.zeros((rows * 256 if rows > 1 else len(table), 4), np.float32)
            padded[:len(table), :3] = table
            texture = get_context().texture((min(len(table), 256) if rows == 1 else 256, rows), 4,
                                            padded.tobytes(), dtype="f4")
            texture.filter = (texture.ctx.NEAREST,) * 2  # entries are read by index, never interpolated
            self._color_table = (coloring, texture)
        self._color_table[1].use(COLOR_TABLE_UNIT)

    def surface_colors(self, cloud: PointCloud, camera: Camera, options: RenderOptions):
        """For methods without splats: a function of a sample depth buffer (seen by `camera`)
        giving (albedo, palette indices) per sample (colors.surface_albedo), or None where
        the colour mode is the method's own blend."""
        coloring = options.coloring
        if coloring is None or not (coloring.categorical or coloring.name == colors.ELEVATION):
            return None
        tree = None
        if coloring.categorical:
            from scipy.spatial import cKDTree

            tree = self.cached(cloud, "neighbour tree", lambda: cKDTree(cloud.local_positions()))
        return lambda depth: colors.surface_albedo(cloud, camera, depth, coloring, tree)

    def appearance(self, cloud: PointCloud, options: RenderOptions) -> tuple[PointCloud, RenderOptions]:
        """The cloud --classes and --returns keep, and the options with the data's defaults
        (shading, colour mode) and the resolved colour mode; both kept per cloud."""
        if options.classes is not None or options.returns is not None:
            source = cloud
            cloud = self.cached(source, ("filtered", options.classes, options.returns),
                                lambda: source.take(colors.selection(source, options.classes, options.returns)))
        shading = options.shading or default_for(cloud)
        coloring = self.cached(cloud, ("coloring", options.color, options.colormap, options.color_range),
                               lambda: colors.resolve(cloud, options.color, options.colormap, options.color_range))
        return cloud, replace(options, shading=shading, coloring=coloring)

    def colored(self, cloud: PointCloud, coloring) -> PointCloud:
        """`cloud` with the colour mode's encoded colours (the cloud itself for rgb)."""
        if coloring is None or coloring.kind == colors.RGB:
            return cloud
        return self.cached(cloud, "colored", lambda: cloud.with_(colors=coloring.encode(cloud)), version=coloring)

    def complete(self, cloud: PointCloud, *, needs_radii: bool = True, elliptical: bool = False,
                 normal_field: bool = False, smooth: bool = False) -> tuple[PointCloud, dict]:
        """`preprocess.complete` (what a method with these capability flags needs; smooth: the
        positions denoised first), once per cloud and setting (turntables and benchmarks
        estimate once)."""
        from . import preprocess  # numba kernels: loaded when first needed

        return self.cached(cloud, ("completed", needs_radii, elliptical, normal_field, smooth),
                           lambda: preprocess.complete(cloud, needs_radii=needs_radii, elliptical=elliptical,
                                                       normal_field=normal_field, smooth=smooth))

    def close(self) -> None:
        """Release every GL object this Renderer holds; it can render again afterwards."""
        for entries in list(self._per_cloud.values()):
            for _, value in entries.values():
                if hasattr(value, "release"):
                    value.release()
        self._per_cloud = weakref.WeakKeyDictionary()
        for program in self._programs.values():
            program.release()
        self._programs.clear()
        if self._targets is not None:
            self._targets[1].release()
            self._targets = None
        for _, targets in self._kept_targets.values():
            targets.release()
        self._kept_targets.clear()
        if self._color_table is not None:
            self._color_table[1].release()
            self._color_table = None
        self._release_gone()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _release_gone(self) -> None:
        while self._released_clouds:
            self._released_clouds.pop().release()

    # ---- rendering --------------------------------------------------------------------
    def render(self, cloud, camera: Camera | None = None, method: str = DEFAULT_METHOD, *,
               backend: str | None = None, size=(1024, 1024), options: RenderOptions | None = None,
               **values) -> RenderResult:
        """Render `cloud` (a PointCloud, or a lazy LodSource whose cut for the camera is selected
        first) with `method` on `backend` ("gl", "cpu", or None or "auto": `choose_backend`).
        Options as a RenderOptions (its `params` the method's parameter dataclass, None for the
        defaults), and/or as keywords: RenderOptions fields and the
        method's parameters (`surfel.render(cloud, method="phong", radius_scale=1.2)`)."""
        if camera is not None and not isinstance(camera, Camera):
            raise TypeError(f"camera must be a surfel Camera (surfel.camera.frame, Camera.look_at or "
                            f"Camera.from_opencv), got {type(camera).__name__}")
        m = get_method(method)
        backend = None if backend == "auto" else backend
        options = split_options(method, values, options)
        m.check_options(options, backend)
        params = options.params if options.params is not None else m.make_params()
        if not isinstance(cloud, PointCloud):
            return self._render_source(cloud, camera, method, backend=backend, size=size, options=options)
        if m.needs_mesh and not cloud.is_mesh:
            raise SurfelError(f"method {method!r} needs a mesh input (faces); {cloud.source or 'this cloud'} has none")
        self._release_gone()
        camera = camera or default_camera(cloud, size)
        lo, hi = cloud.bounds
        # coincident points have no extent to bring to unit scale (their framing radius is a
        # fraction of their distance from the origin, which scaling does not change)
        unit = render_unit(cloud.bounding_radius) if (hi > lo).any() else 1.0
        if unit != 1.0:
            return self._render_at_unit_scale(cloud, camera, method, unit, backend=backend, options=options,
                                              params=params)
        return self._render_cloud(cloud, camera, method, backend=backend, options=options, params=params)

    def _render_cloud(self, cloud: PointCloud, camera: Camera, method: str, *, backend: str | None,
                      options: RenderOptions, params) -> RenderResult:
        """`render` of a PointCloud at a scale the methods work at."""
        m = get_method(method)
        input_points = len(cloud)
        backend, backend_choice = choose_backend(method, backend, dump_passes=options.dump_passes is not None)
        cloud, options = self.appearance(cloud, options)
        selected = len(cloud)
        with self._compile_ahead(cloud, camera, m, backend, options, params) as ahead:
            with ahead.watching():
                cloud, estimated = self.complete(cloud, needs_radii=m.needs_radii,
                                                 elliptical=m.fits_ellipses(cloud), normal_field=m.normal_field,
                                                 smooth=options.smooth)
            if options.lod_error is not None:
                from .lod import as_sequential, lod_subset

                cloud = self.cached(cloud, "sequential point tree", lambda: as_sequential(cloud))
                if backend != "gl" or not m.shader_lod:  # no vertex stage runs the test: select on the CPU
                    seq, epsilon = cloud, options.lod_error
                    view = (camera.world_to_eye.tobytes(), camera.pixel_scale(), camera.ortho_height, float(epsilon))
                    cloud = self.cached(seq, "lod subset", lambda: lod_subset(seq, camera, epsilon), version=view)
            cloud = self.colored(cloud, options.coloring)
            # clip planes around the splats themselves, not only their centres (methods without
            # splats have no radius_scale)
            reach = cloud.max_splat_radius * getattr(params, "radius_scale", 1.0)
            camera = camera.fit_clip_planes(cloud.center, cloud.bounding_radius + reach)
            function = m.function(backend)
            ahead.wait()
            start = time.perf_counter()
            result = function(cloud, camera, options, params, self)
            ms = (time.perf_counter() - start) * 1000
        if backend == "gl":
            from .gl.context import renderer_string

            renderer = renderer_string()
        else:
            renderer = "cpu"
        stats = {"method": method, "backend": backend, "backend_choice": backend_choice, "renderer": renderer,
                 "points": input_points,
                 "splats": len(cloud), "width": camera.width, "height": camera.height, "ms": round(ms, 3),
                 "shading": options.shading, "near": camera.near, "far": camera.far,
                 **options.coloring.describe()}
        if selected != input_points:
            stats.update(selected=selected, classes=options.classes, returns=options.returns)
        stats.update(result.stats)
        if estimated:
            stats["estimated"] = estimated
        result.stats = stats
        return result

    def _compile_ahead(self, cloud: PointCloud, camera: Camera, m, backend: str, options: RenderOptions,
                       params) -> CompileAhead:
        """What compiles the method's CPU kernels in a helper process if this render's completion
        starts compiling (compile_ahead.py); nothing for the GL backend, or when switched off."""
        if backend != "cpu" or not self.compile_ahead:
            return CompileAhead(None)
        from .preprocess import completes_with_clip_lines

        clip = completes_with_clip_lines(cloud, needs_radii=m.needs_radii, normal_field=m.normal_field,
                                         smooth=options.smooth)
        return CompileAhead(render_spec(m.name, params, clip=clip, width=camera.width, height=camera.height,
                                        shading=options.shading, supersample=options.supersample))

    def _render_at_unit_scale(self, cloud: PointCloud, camera: Camera, method: str, unit: float, *,
                              backend: str | None, options: RenderOptions, params) -> RenderResult:
        """Render a cloud far from unit scale (1e-30 or 1e30 units across) divided by `unit`, a
        power of two, so that every method's float32 arithmetic and tolerances work as they do
        at unit scale; the image is the same, eye depths are scaled back, and an elevation
        colour range is the original's (elevation is a length: it scales with the cloud)."""
        scaled = self.cached(cloud, ("unit scale", unit), lambda: cloud.scaled(1 / unit))
        coloring = self.appearance(cloud, options)[1].coloring
        if coloring.name == colors.ELEVATION:
            options = replace(options, color_range=(coloring.range[0] / unit, coloring.range[1] / unit))
        result = self._render_cloud(scaled, camera.scaled(1 / unit), method, backend=backend, options=options,
                                    params=params)
        result.depth = result.depth * np.float32(unit)
        result.stats.update(near=result.stats["near"] * unit, far=result.stats["far"] * unit, unit_scale=unit)
        if coloring.name == colors.ELEVATION:
            result.stats["color_range"] = list(coloring.range)
        return result

    def _render_source(self, source, camera: Camera | None, method: str, *, backend: str | None, size,
                       options: RenderOptions) -> RenderResult:
        """Select the source's cut for the view, then render it as an ordinary cloud."""
        from .lod.source import is_source

        if not is_source(source):
            raise TypeError(f"render needs a PointCloud or a LodSource, got {type(source).__name__}")
        if not get_method(method).needs_radii:
            raise SurfelError(f"method {method!r} cannot render a level-of-detail source (it needs splats)")
        if options.smooth:
            raise SurfelError("smoothing applies to clouds loaded whole, not to a .lod hierarchy or COPC file")
        camera = camera or frame(source.center, source.bounding_radius, geospatial=source.geospatial, size=size,
                                 bounds=source.bounds)
        epsilon = options.lod_error if options.lod_error is not None else SOURCE_DEFAULT_LOD_ERROR
        start = time.perf_counter()
        cut, selection = source.select(camera, epsilon, options.point_budget)
        select_ms = (time.perf_counter() - start) * 1000
        m = get_method(method)
        if m.normal_field and not m.fields_per_cut and "phong_alpha" not in cut.attributes:
            flat = np.zeros(len(cut), np.float32)
            cut = cut.with_(attributes={**cut.attributes, "phong_alpha": flat, "phong_beta": flat})
        # the cut is already at the requested detail: no second selection on it; its shading is
        # the source's default (a COPC file without normals is shaded as such, though its cut's
        # normals were estimated)
        result = self.render(cut, camera, method, backend=backend,
                             options=replace(options, lod_error=None, point_budget=None,
                                             shading=options.shading or default_for(source)))
        result.stats.update({"points": source.total_points, "lod": epsilon, "select_ms": round(select_ms, 3),
                             **selection})
        return result


default_renderer = Renderer()


def render(cloud, camera: Camera | None = None, method: str = DEFAULT_METHOD, **kwargs) -> RenderResult:
    """`Renderer.render` on the module's default Renderer (its caches live as long as the process)."""
    return default_renderer.render(cloud, camera, method, **kwargs)


__all__ = ["render", "Renderer", "default_renderer", "default_camera", "choose_backend", "is_software_renderer",
           "split_options"]
