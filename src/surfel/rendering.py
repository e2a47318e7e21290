"""`render()` and the `Renderer`: one entry point for every method and backend (numpy in,
RenderResult out), and the one owner of everything kept from one frame to the next.

A Renderer keeps, per cloud, what is derived from it once and reused every frame: the
completed cloud (estimated normals, radii, normal fields), its sequential point tree and the
last level-of-detail subset, the EWA rasterizer's Morton order, object-space EWA's per-surfel
weights, the MLS ray tracing scene, and the cloud's GPU buffers. Clouds are keyed by identity,
held weakly: a PointCloud and its arrays cannot change, so what was derived from one stays
true, and an entry goes when its cloud goes (its GL objects are released on the next frame).
It also keeps the compiled GL programs, the three-pass targets of the last frame size and
those a method draws with itself (the MLS caster's), also of the last size.
Its lifetime is the object's: `close()`, or leaving a `with` block, releases its GL objects.
`surfel.render()` uses a module-level Renderer; the viewer, turntable, bench and each batch
worker hold their own.
"""

from __future__ import annotations

import sys
import time
import weakref
from dataclasses import replace

from .camera import Camera, frame
from .cloud import PointCloud
from .errors import SurfelError
from .methods import get_method
from .options import RenderOptions
from .result import RenderResult


def default_camera(cloud: PointCloud, size=(1024, 1024), **framing) -> Camera:
    """The auto-framing camera of CONVENTIONS.md for this cloud."""
    return frame(cloud.center, cloud.bounding_radius, geospatial=cloud.geospatial, size=size, **framing)


def complete(cloud: PointCloud, *, need_radii: bool = True, elliptical: bool = False,
             normal_field: bool = False) -> tuple[PointCloud, dict]:
    """Estimate whatever attributes the method needs and the cloud lacks (reported)."""
    missing = cloud.normals is None or (need_radii and (cloud.radii is None or cloud.axes is None))
    missing = missing or (normal_field and "phong_alpha" not in cloud.attributes)
    if not missing:
        return cloud, {}
    from .preprocess import prepare

    return prepare(cloud, elliptical=elliptical, normal_field=normal_field)


def resolve_backend(method_name: str, backend: str | None) -> str:
    """The backend to use: as asked, else OpenGL, else the CPU with a one-line notice."""
    method = get_method(method_name)
    if backend is not None:
        method.function(backend)  # validates
        return backend
    if "gl" in method.backends:
        from .gl.context import get_context, gl_available

        if gl_available():
            return "gl"
        if "cpu" in method.backends:
            print(f"surfel: no OpenGL context, rendering {method_name} on the CPU", file=sys.stderr)
            return "cpu"
        get_context()  # raises NoOpenGLError with the install hint
    return next(iter(method.backends))


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

    def __init__(self):
        self._per_cloud: weakref.WeakKeyDictionary[PointCloud, dict] = weakref.WeakKeyDictionary()
        self._programs: dict = {}
        self._targets: tuple | None = None  # (size key, gl.passes.SplatTargets)
        self._kept_targets: dict = {}  # a method's own targets by kind: (key, targets) of the last key
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

    def program(self, path, defines: dict | None = None, *, geometry: bool = False):
        """The GL program of `path` with these #defines, compiled once."""
        key = (str(path), tuple(sorted((defines or {}).items())), geometry)
        if key not in self._programs:
            from .gl.program import build_program

            self._programs[key] = build_program(path, defines, geometry=geometry)
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

    def complete(self, cloud: PointCloud, *, need_radii: bool = True, elliptical: bool = False,
                 normal_field: bool = False) -> tuple[PointCloud, dict]:
        """`complete()`, once per cloud and setting (turntables and benchmarks estimate once)."""
        return self.cached(cloud, ("completed", need_radii, elliptical, normal_field),
                           lambda: complete(cloud, need_radii=need_radii, elliptical=elliptical,
                                            normal_field=normal_field))

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
        self._release_gone()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _release_gone(self) -> None:
        while self._released_clouds:
            self._released_clouds.pop().release()

    # ---- rendering --------------------------------------------------------------------
    def render(self, cloud, camera: Camera | None = None, method: str = "deferred", *,
               backend: str | None = None, size=(1024, 1024), options: RenderOptions | None = None,
               **values) -> RenderResult:
        """Render `cloud` (a PointCloud, or a lazy LodSource whose cut for the camera is selected
        first) with `method`. Options as a RenderOptions (its `params` the method's parameter
        dataclass, None for the defaults), and/or as keywords: RenderOptions fields and the
        method's parameters (`surfel.render(cloud, method="phong", radius_scale=1.2)`)."""
        m = get_method(method)
        options = split_options(method, values, options)
        m.check_options(options, backend)
        params = options.params if options.params is not None else m.make_params()
        if not isinstance(cloud, PointCloud):
            return self._render_source(cloud, camera, method, backend=backend, size=size, options=options)
        if m.needs_mesh and not cloud.is_mesh:
            raise SurfelError(f"method {method!r} needs a mesh input (faces); {cloud.source or 'this cloud'} has none")
        self._release_gone()
        camera = camera or default_camera(cloud, size)
        input_points = len(cloud)
        backend = resolve_backend(method, backend)
        cloud, estimated = self.complete(cloud, need_radii=m.needs_radii, elliptical=m.elliptical,
                                         normal_field=m.normal_field)
        if options.lod_error is not None:
            from .lod import as_sequential, lod_subset

            cloud = self.cached(cloud, "sequential point tree", lambda: as_sequential(cloud))
            if backend != "gl" or not m.shader_lod:  # no vertex stage runs the test: select on the CPU
                seq, epsilon = cloud, options.lod_error
                view = (camera.world_to_eye.tobytes(), camera.pixel_scale(), camera.ortho_height, float(epsilon))
                cloud = self.cached(seq, "lod subset", lambda: lod_subset(seq, camera, epsilon), version=view)
        # clip planes around the splats themselves, not only their centres (methods without
        # splats have no radius_scale)
        reach = cloud.max_splat_radius * getattr(params, "radius_scale", 1.0)
        camera = camera.fit_clip_planes(cloud.center, cloud.bounding_radius + reach)
        function = m.function(backend)
        start = time.perf_counter()
        result = function(cloud, camera, options, params, self)
        ms = (time.perf_counter() - start) * 1000
        if backend == "gl":
            from .gl.context import renderer_string

            renderer = renderer_string()
        else:
            renderer = "cpu"
        stats = {"method": method, "backend": backend, "renderer": renderer, "points": input_points,
                 "splats": len(cloud), "width": camera.width, "height": camera.height, "ms": round(ms, 3),
                 "shading": options.shading, "near": camera.near, "far": camera.far}
        stats.update(result.stats)
        if estimated:
            stats["estimated"] = estimated
        result.stats = stats
        return result

    def _render_source(self, source, camera: Camera | None, method: str, *, backend: str | None, size,
                       options: RenderOptions) -> RenderResult:
        """Select the source's cut for the view, then render it as an ordinary cloud."""
        from .lod.source import is_source

        if not is_source(source):
            raise TypeError(f"render needs a PointCloud or a LodSource, got {type(source).__name__}")
        if not get_method(method).needs_radii:
            raise SurfelError(f"method {method!r} cannot render a level-of-detail source (it needs splats)")
        camera = camera or frame(source.center, source.bounding_radius, geospatial=source.geospatial, size=size)
        epsilon = options.lod_error if options.lod_error is not None else SOURCE_DEFAULT_LOD_ERROR
        start = time.perf_counter()
        cut, selection = source.select(camera, epsilon, options.point_budget)
        select_ms = (time.perf_counter() - start) * 1000
        # the cut is already at the requested detail: no second selection on it
        result = self.render(cut, camera, method, backend=backend,
                             options=replace(options, lod_error=None, point_budget=None))
        result.stats.update({"points": source.total_points, "lod": epsilon, "select_ms": round(select_ms, 3),
                             **selection})
        return result


default_renderer = Renderer()


def render(cloud, camera: Camera | None = None, method: str = "deferred", **kwargs) -> RenderResult:
    """`Renderer.render` on the module's default Renderer (its caches live as long as the process)."""
    return default_renderer.render(cloud, camera, method, **kwargs)


__all__ = ["render", "Renderer", "default_renderer", "default_camera", "complete", "resolve_backend",
           "split_options"]
