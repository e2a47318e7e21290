"""Shading models (docs/conventions.md "Shading"), numpy side; gl/shading.glsl is the GPU twin.

lambert : albedo * (0.2 + 0.8 |n . v|), v the camera's viewing axis (a head-light). The
          comparable one: tests and `compare` use it.
phong   : the default for pretty pictures: a key light from the upper left plus a
          Blinn-Phong specular highlight, two-sided.
none    : unlit albedo.  normals: eye-space normal as colour.  depth: near white, far black
          between the camera's near and far planes.
edl     : eye-dome lighting (surfel.edl): the unlit albedo times a screen-space term of the
          depth buffer, for clouds without normals; per pixel it is `none` (PER_PIXEL), the
          term is applied to the samples of every method (result.RenderResult.from_samples).

The default (`default_for`) depends on the data: edl for a geospatial cloud without normals
of its own (a raw LiDAR tile, whose estimated normals are those of a neighbourhood that is often
not a surface; or such a tile after `surfel prepare` or `lod build` wrote those estimates, which
the screen_facing attribute marks: only the estimation writes it), else phong.

`shade` works on arrays; `shade_pixel` is the same for one pixel inside a numba kernel.
"""

from __future__ import annotations

import numba
import numpy as np

from .errors import SurfelError

MODELS = ("lambert", "phong", "none", "normals", "depth", "edl")
MODEL_IDS = {"lambert": 0, "phong": 1, "none": 2, "normals": 3, "depth": 4}
DEFAULT = "phong"
EDL = "edl"
PER_PIXEL = {EDL: "none"}  # what a model shades per pixel, where that is another model
DEFAULT_HELP = "edl for geospatial clouds without normals of their own, else phong"

KEY_LIGHT = np.array([-0.4, 0.6, 0.8]) / np.linalg.norm([-0.4, 0.6, 0.8])
_HALFWAY = (KEY_LIGHT + [0, 0, 1]) / np.linalg.norm(KEY_LIGHT + [0, 0, 1])


def default_for(cloud) -> str:
    """The shading of a cloud rendered without --shading (module docstring)."""
    estimated = getattr(cloud, "normals", None) is None or "screen_facing" in getattr(cloud, "attributes", {})
    return EDL if cloud.geospatial and estimated else DEFAULT


def check_model(model: str) -> int:
    if model not in MODEL_IDS:
        raise SurfelError(f"unknown shading model {model!r}; choose one of {', '.join(MODELS)}")
    return MODEL_IDS[model]


def shade(model: str, albedo: np.ndarray, normals: np.ndarray, depth: np.ndarray,
          near: float, far: float) -> np.ndarray:
    """Shaded RGB (..., 3) float32 from albedo (..., 3), unit eye normals (..., 3), eye depth (...)."""
    model = PER_PIXEL.get(model, model)
    check_model(model)
    albedo = np.asarray(albedo, np.float32)
    n = np.asarray(normals, np.float32)
    if model == "lambert":
        return albedo * (0.2 + 0.8 * np.abs(n[..., 2:3]))
    if model == "phong":
        nf = np.where(n[..., 2:3] < 0, -n, n)
        diffuse = 0.25 + 0.75 * np.maximum(nf @ KEY_LIGHT.astype(np.float32), 0)[..., None]
        specular = 0.3 * np.maximum(nf @ _HALFWAY.astype(np.float32), 0) ** 40
        return (albedo * diffuse + specular[..., None]).astype(np.float32)
    if model == "normals":
        return 0.5 * n + 0.5
    if model == "depth":
        t = np.clip((np.asarray(depth, np.float32) - near) / max(far - near, 1e-12), 0, 1)
        return np.repeat((1 - t)[..., None], 3, axis=-1).astype(np.float32)
    return albedo


_KEY = tuple(np.float32(c) for c in KEY_LIGHT)  # float32 constants: the kernels compute in float32
_HALF = tuple(np.float32(c) for c in _HALFWAY)


@numba.njit(inline="always", fastmath=True)
def shade_pixel(model: int, r, g, b, nx, ny, nz, depth, near, far):  # pragma: no cover - compiled
    """`shade` of one albedo (r, g, b), unit eye normal and eye depth, for numba kernels:
    `model` is a MODEL_IDS value. Returns the shaded (r, g, b)."""
    if model == 0:  # lambert
        k = np.float32(0.2) + np.float32(0.8) * abs(nz)
        return r * k, g * k, b * k
    if model == 1:  # phong: two-sided
        if nz < 0:
            nx, ny, nz = -nx, -ny, -nz
        lit = max(nx * _KEY[0] + ny * _KEY[1] + nz * _KEY[2], np.float32(0.0))
        highlight = max(nx * _HALF[0] + ny * _HALF[1] + nz * _HALF[2], np.float32(0.0))
        diffuse = np.float32(0.25) + np.float32(0.75) * lit
        specular = np.float32(0.3) * highlight ** 40
        return r * diffuse + specular, g * diffuse + specular, b * diffuse + specular
    if model == 3:  # normals
        return np.float32(0.5) * nx + np.float32(0.5), np.float32(0.5) * ny + np.float32(0.5), \
            np.float32(0.5) * nz + np.float32(0.5)
    if model == 4:  # depth
        t = min(max((depth - near) / max(far - near, np.float32(1e-12)), np.float32(0.0)), np.float32(1.0))
        return np.float32(1.0) - t, np.float32(1.0) - t, np.float32(1.0) - t
    return r, g, b  # none
