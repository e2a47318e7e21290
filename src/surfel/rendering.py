"""`render()`: one entry point for every method and backend (numpy in, RenderResult out)."""

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
from .shading import check_model


def default_camera(cloud: PointCloud, size=(1024, 1024), **framing) -> Camera:
    """The auto-framing camera of CONVENTIONS.md for this cloud."""
    return frame(cloud.center, cloud.bounding_radius, geospatial=cloud.geospatial, size=size, **framing)


_completed: weakref.WeakKeyDictionary[PointCloud, dict] = weakref.WeakKeyDictionary()


def complete(cloud: PointCloud, *, needs_radii: bool = True, elliptical: bool = False,
             normal_field: bool = False) -> tuple[PointCloud, dict]:
    """`preprocess.complete` (what a method with these capability flags needs), remembered per
    cloud, so that repeated renders of one cloud (turntables, benchmarks) estimate once."""
    from . import preprocess  # numba kernels: loaded when first needed

    key = (needs_radii, elliptical, normal_field)
    if key in _completed.get(cloud, {}):
        return _completed[cloud][key]
    completed = preprocess.complete(cloud, needs_radii=needs_radii, elliptical=elliptical, normal_field=normal_field)
    if completed[0] is not cloud:  # remember estimates only: the cloud itself would keep its key alive
        _completed.setdefault(cloud, {})[key] = completed
    return completed


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


def render(cloud, camera: Camera | None = None, method: str = "deferred", *,
           backend: str | None = None, size=(1024, 1024), options: RenderOptions | None = None,
           **option_values) -> RenderResult:
    """Render `cloud` (a PointCloud, or a lazy LodSource whose cut for the camera is selected
    first) with `method`; options as a RenderOptions or as keyword arguments."""
    options = options or RenderOptions(**option_values)
    check_model(options.shading)
    m = get_method(method)
    if not isinstance(cloud, PointCloud):
        return _render_source(cloud, camera, method, backend=backend, size=size, options=options)
    if m.needs_mesh and not cloud.is_mesh:
        raise SurfelError(f"method {method!r} needs a mesh input (faces); {cloud.source or 'this cloud'} has none")
    camera = camera or default_camera(cloud, size)
    input_points = len(cloud)
    backend = resolve_backend(method, backend)
    cloud, estimated = complete(cloud, needs_radii=m.needs_radii,
                                elliptical=m.elliptical, normal_field=m.normal_field)
    if options.lod_error is not None and m.needs_radii:
        from .lod import as_sequential, lod_subset

        cloud = as_sequential(cloud)
        if backend != "gl" or not m.shader_lod:  # no vertex stage runs the test: select on the CPU
            cloud = lod_subset(cloud, camera, options.lod_error)
    # clip planes around the splats themselves, not only their centres
    reach = cloud.max_splat_radius * options.radius_scale
    camera = camera.fit_clip_planes(cloud.center, cloud.bounding_radius + reach)
    function = m.function(backend)
    start = time.perf_counter()
    result = function(cloud, camera, options)
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


def _render_source(source, camera: Camera | None, method: str, *, backend: str | None, size,
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
    result = render(cut, camera, method, backend=backend, options=replace(options, lod_error=None))
    result.stats.update({"points": source.total_points, "lod": epsilon, "select_ms": round(select_ms, 3),
                         **selection})
    return result


__all__ = ["render", "default_camera", "complete", "resolve_backend"]
