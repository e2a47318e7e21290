"""Every rendering method surfel has, by name and backend: the index to find a paper's code.

Each entry maps a backend to "module:function" (plus what the method needs); the function takes
(cloud: PointCloud, camera: Camera, options: RenderOptions) and returns a RenderResult
whose `stats` hold at least {"splats": ...}. Modules are imported on first use so that
`surfel --help` stays fast and the CPU paths work without OpenGL.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from ..errors import SurfelError


@dataclass(frozen=True)
class Method:
    name: str
    summary: str
    backends: dict[str, str]
    needs_mesh: bool = False
    needs_radii: bool = True
    shader_lod: bool = False  # its vertex stage runs the sequential point tree test (gl/lod.glsl)
    elliptical: bool = False  # fitted elliptical splats when the cloud has no axes
    normal_field: bool = False  # shades with Phong splatting's linear normal fields (fitted if missing)

    def function(self, backend: str):
        if backend not in self.backends:
            raise SurfelError(f"method {self.name!r} has no {backend!r} backend; it has {', '.join(self.backends)}")
        module, func = self.backends[backend].split(":")
        return getattr(importlib.import_module(f"{__name__}.{module}"), func)


METHODS: dict[str, Method] = {
    m.name: m
    for m in [
        Method("mesh", "the input mesh's triangles, supersampled: the ground truth",
               {"gl": "mesh:render_mesh"}, needs_mesh=True, needs_radii=False),
        Method("points",
               "naive: screen-aligned disks of the projected radius, z-buffer, flat shading (survey Fig. 6 left)",
               {"gl": "points:render_points"}, shader_lod=True),
        Method("gaussian", "Botsch & Kobbelt 2003: three-pass Gaussian splatting, per-splat shading (Fig. 6 middle)",
               {"gl": "splatting:render_gaussian"}, shader_lod=True),
        Method("deferred", "Botsch et al. 2005: deferred shading with the EWA filter approximation",
               {"gl": "splatting:render_deferred"}, shader_lod=True),
        Method("phong", "Botsch et al. 2004: Phong splatting, elliptical splats with linear normal fields",
               {"gl": "splatting:render_phong"}, shader_lod=True, elliptical=True, normal_field=True),
        Method("object-space", "Ren, Pfister & Zwicker 2002: object-space EWA splatting with textured quads",
               {"gl": "object_space:render_object_space"}),
        Method("ewa", "Zwicker et al. 2001: software EWA surface splatting, the full resampling filter",
               {"cpu": "ewa:render_ewa_cpu", "gl": "ewa_gl:render_ewa_gl"}, normal_field=True),
        Method("mls", "Adamson & Alexa 2003: ray tracing the MLS point set surface",
               {"cpu": "mls:render_mls_cpu"}, needs_radii=False),
        Method("mls-gpu", "Tejada et al. 2006: multi-pass GPU ray casting of the MLS surface",
               {"gl": "mls_gpu:render_mls_gl"}, needs_radii=False),
    ]
}


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise SurfelError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return METHODS[name]
