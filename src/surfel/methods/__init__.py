"""Every rendering method surfel has, by name and backend: the index to find a paper's code.

Each entry maps a backend to "module:function" (modules relative to the surfel package) and
names the method's parameter dataclass the same way. The function takes
(cloud: PointCloud, camera: Camera, options: RenderOptions, params, renderer) -- params an
instance of that dataclass, renderer the `rendering.Renderer` that owns the caches the method
keeps between frames -- and returns a RenderResult whose `stats` hold at least
{"splats": ...}. Modules are imported on first use so that `surfel --help` stays fast and the
CPU paths work without OpenGL.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from ..errors import SurfelError
from ..options import METHOD_DEPENDENT, RenderOptions


def _resolve(path: str):
    module, name = path.split(":")
    return getattr(importlib.import_module(f"{__package__.rpartition('.')[0]}.{module}"), name)


@dataclass(frozen=True)
class Method:
    name: str
    summary: str
    backends: dict[str, str]
    params: str  # "module:Class" of the method's parameter dataclass
    needs_mesh: bool = False
    needs_radii: bool = True  # draws splats: needs radii, and takes --lod-error
    shader_lod: bool = False  # its vertex stage runs the sequential point tree test (gl/lod.glsl)
    elliptical: bool = False  # fitted elliptical splats when the cloud has no axes
    ellipses_over_given_radii: bool = True  # ... even when it has radii (else circles of them)
    normal_field: bool = False  # draws with Phong splatting's linear normal fields (fitted if missing)
    # fits them for a level-of-detail cut too; without (deferred), a cut's splats are flat and
    # lit by one normal each: fitting every frame's cut would cost more than the frame
    fields_per_cut: bool = True
    dump_passes: tuple[str, ...] = ()  # the backends that can write their intermediate passes
    # --backend auto picks its CPU backend over a software GL rasterizer (llvmpipe): measured
    # faster there with `surfel bench` (README, issue 18)
    cpu_beats_software_gl: bool = False

    def fits_ellipses(self, cloud) -> bool:
        """Whether completing `cloud` for this method fits elliptical splats."""
        return self.elliptical and (cloud.radii is None or self.ellipses_over_given_radii)

    def function(self, backend: str):
        if backend not in self.backends:
            raise SurfelError(f"method {self.name!r} has no {backend!r} backend; it has {', '.join(self.backends)}")
        return _resolve(self.backends[backend])

    def params_class(self):
        return _resolve(self.params)

    def make_params(self, values=None):
        """The method's parameters from a mapping of names (defaults for the rest); a name it
        does not have, a wrong type or a value it cannot honour is a one-line SettingError."""
        return self.params_class().from_mapping(values or {}, f"method {self.name!r}")

    def uses(self, name: str) -> bool:
        """Whether the method does something with the RenderOptions field or parameter `name`."""
        if name in ("lod_error", "point_budget"):
            return self.needs_radii
        if name == "dump_passes":
            return bool(self.dump_passes)
        if name in RenderOptions.names():
            return True
        return name in self.params_class().names()

    def check_options(self, options: RenderOptions, backend: str | None = None) -> None:
        """Refuse an option the method does not use (set: not None) and parameters of another method."""
        for name in METHOD_DEPENDENT:
            if getattr(options, name) is not None and not self.uses(name):
                raise SurfelError(f"method {self.name!r} does not use {name}")
        if options.dump_passes is not None and backend is not None and backend not in self.dump_passes:
            raise SurfelError(f"method {self.name!r} writes no passes on its {backend} backend")
        cls = self.params_class()
        if options.params is not None and type(options.params) is not cls:
            raise SurfelError(f"method {self.name!r} takes {cls.__name__}, not {type(options.params).__name__}")


_GL_PASSES = ("gl",)

METHODS: dict[str, Method] = {
    m.name: m
    for m in [
        Method("mesh", "the input mesh's triangles, supersampled: the ground truth",
               {"gl": "methods.mesh:render_mesh"}, "methods.mesh:MeshParams", needs_mesh=True, needs_radii=False),
        Method("points",
               "naive: screen-aligned disks of the projected radius, z-buffer, flat shading (survey Fig. 6 left)",
               {"gl": "methods.points:render_points"}, "methods.params:RadiusParams", shader_lod=True),
        Method("gaussian", "Botsch & Kobbelt 2003: three-pass Gaussian splatting, per-splat shading (Fig. 6 middle)",
               {"gl": "methods.splatting:render_gaussian", "cpu": "methods.splatting_cpu:render_gaussian_cpu"},
               "methods.splatting:GaussianParams", shader_lod=True, cpu_beats_software_gl=True,
               dump_passes=_GL_PASSES),
        Method("deferred", "Botsch et al. 2005: deferred shading with the EWA filter approximation, curved splats "
               "lit by their normal fields",
               {"gl": "methods.splatting:render_deferred", "cpu": "methods.splatting_cpu:render_deferred_cpu"},
               "methods.splatting:DeferredParams", shader_lod=True, cpu_beats_software_gl=True,
               elliptical=True, ellipses_over_given_radii=False, normal_field=True, fields_per_cut=False,
               dump_passes=_GL_PASSES),
        Method("phong", "Botsch et al. 2004: Phong splatting, elliptical splats with linear normal fields",
               {"gl": "methods.splatting:render_phong", "cpu": "methods.splatting_cpu:render_phong_cpu"},
               "methods.splatting:PhongParams", shader_lod=True, cpu_beats_software_gl=True,
               elliptical=True, normal_field=True, dump_passes=_GL_PASSES),
        Method("object-space", "Ren, Pfister & Zwicker 2002: object-space EWA splatting with textured quads",
               {"gl": "methods.object_space:render_object_space"}, "methods.object_space:ObjectSpaceParams",
               dump_passes=_GL_PASSES),
        Method("ewa", "Zwicker et al. 2001: software EWA surface splatting, the full resampling filter",
               {"cpu": "methods.ewa:render_ewa_cpu", "gl": "methods.ewa_gl:render_ewa_gl"}, "methods.ewa:EwaParams",
               normal_field=True, dump_passes=_GL_PASSES, cpu_beats_software_gl=True),
        Method("mls", "Adamson & Alexa 2003: ray tracing the MLS point set surface",
               {"cpu": "mls.raytrace:render_mls_cpu"}, "mls.raytrace:MlsParams", needs_radii=False),
        Method("mls-gpu", "Tejada et al. 2006: multi-pass GPU ray casting of the MLS surface",
               {"gl": "mls.gpu:render_mls_gl"}, "mls.gpu:MlsGpuParams", needs_radii=False),
    ]
}

# The method of every interface that names none: of those that draw at interactive speed, the
# closest to the mesh in the README's quality tables (of vertices and of raw range scans, close
# and far views), smooth where splats are magnified, and the passes of `deferred`: interactive
# at one sample a pixel, at which the viewer and the page draw a moving camera; a still image
# takes 2x2 (methods/splatting.py, "Samples").
DEFAULT_METHOD = "phong"


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise SurfelError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return METHODS[name]
