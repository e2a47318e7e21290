"""Render results: the buffers of docs/conventions.md "Outputs" and how they are written."""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field

import numba
import numpy as np

from .edl import eye_dome_lighting
from .files import check_output, write_atomically, write_json
from .pinholes import fill_pinholes


@numba.njit(parallel=True, cache=True)
def _box_filter_categories(shaded, coverage, indices, s):  # pragma: no cover - compiled
    """Premultiplied colour (H, W, 3) of s x s blocks that never mixes categories: each output
    pixel takes the category of most coverage among its samples (ties: the first), and the
    coverage-weighted colour of that category's samples times the block's mean coverage."""
    h, w = coverage.shape[0] // s, coverage.shape[1] // s
    out = np.zeros((h, w, 3), np.float32)
    for y in numba.prange(h):
        for x in range(w):
            best, best_weight, alpha = -1, np.float32(0.0), np.float32(0.0)
            for a in range(s * s):
                ya, xa = y * s + a // s, x * s + a % s
                alpha += coverage[ya, xa]
                index = indices[ya, xa]
                if index < 0 or coverage[ya, xa] <= 0:
                    continue
                weight = np.float32(0.0)
                for b in range(s * s):
                    yb, xb = y * s + b // s, x * s + b % s
                    if indices[yb, xb] == index:
                        weight += coverage[yb, xb]
                if weight > best_weight:
                    best, best_weight = index, weight
            alpha /= s * s
            total = np.float32(0.0)
            color = np.zeros(3, np.float32)
            for a in range(s * s):
                ya, xa = y * s + a // s, x * s + a % s
                if coverage[ya, xa] <= 0 or (best >= 0 and indices[ya, xa] != best):
                    continue
                total += coverage[ya, xa]
                for c in range(3):
                    color[c] += coverage[ya, xa] * shaded[ya, xa, c]
            if total > 0:
                for c in range(3):
                    out[y, x, c] = color[c] / total * alpha
    return out


@numba.njit(parallel=True, cache=True)
def _box_filter(shaded, coverage, depth, normals, s, background, premult, given):  # pragma: no cover - compiled
    """s x s blocks of samples (s = 1: each sample) to output pixels: coverage (clamped to
    [0, 1]) averaged; colour averaged premultiplied by it (or `premult` where `given`) and
    composited over the background; the nearest covered depth (inf for none); the
    coverage-weighted mean normal made unit (0 for none)."""
    h, w = coverage.shape[0] // s, coverage.shape[1] // s
    color = np.empty((h, w, 3), np.float32)
    alpha = np.empty((h, w), np.float32)
    depth_out = np.empty((h, w), np.float32)
    normals_out = np.empty((h, w, 3), np.float32)
    samples = np.float32(s * s)
    zero, one = np.float32(0.0), np.float32(1.0)
    for y in numba.prange(h):
        for x in range(w):
            a = r = g = b = nx = ny = nz = zero
            nearest = np.float32(np.inf)
            # two loops, not one over s * s: its k // s and k % s were a third of a 1024 x 1024 frame's filter
            for ys in range(y * s, y * s + s):
                for xs in range(x * s, x * s + s):
                    c = min(max(coverage[ys, xs], zero), one)
                    if c <= 0:
                        continue
                    a += c
                    nearest = min(nearest, depth[ys, xs])
                    r += shaded[ys, xs, 0] * c
                    g += shaded[ys, xs, 1] * c
                    b += shaded[ys, xs, 2] * c
                    nx += normals[ys, xs, 0] * c
                    ny += normals[ys, xs, 1] * c
                    nz += normals[ys, xs, 2] * c
            a /= samples
            alpha[y, x] = a
            depth_out[y, x] = nearest
            if given:
                r, g, b = premult[y, x, 0], premult[y, x, 1], premult[y, x, 2]
            else:
                r, g, b = r / samples, g / samples, b / samples
            color[y, x, 0] = min(max(r + (1 - a) * background[0], zero), one)
            color[y, x, 1] = min(max(g + (1 - a) * background[1], zero), one)
            color[y, x, 2] = min(max(b + (1 - a) * background[2], zero), one)
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
            if length <= 1e-12:  # no sample covered: the zero normal
                length, nx, ny, nz = one, zero, zero, zero
            normals_out[y, x, 0], normals_out[y, x, 1], normals_out[y, x, 2] = nx / length, ny / length, nz / length
    return color, alpha, depth_out, normals_out


@dataclass(eq=False)
class RenderResult:
    """color (H, W, 3) composited over the background; alpha (H, W) coverage in [0, 1];
    depth (H, W) eye-space distance along the viewing axis, inf where empty; normals
    (H, W, 3) unit eye-space normals, 0 where empty; stats per docs/conventions.md."""

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    stats: dict = field(default_factory=dict)

    @classmethod
    def from_samples(cls, shaded, coverage, depth, normals, *, supersample: int, options, stats: dict,
                     indices=None, pinholes: bool = False) -> RenderResult:
        """The output buffers of a method's samples: with `pinholes` (the splatting methods),
        the samples through which the surface shows what lies behind it filled (surfel.pinholes;
        stats["pinholes"] counts them), then eye-dome lighting, then a box filter down to the
        output size, then compositing over the background.

        shaded (sH, sW, 3), coverage (sH, sW) in [0, 1], depth (sH, sW) (any value where
        coverage is 0), normals (sH, sW, 3), float32 of any strides (views are not copied);
        `options` (RenderOptions): the background, and the `edl` shading, whose term
        (surfel.edl, radius edl_radius output pixels) multiplies every sample's (unlit) colour.
        Colour is averaged premultiplied by coverage and then composited over the background;
        depth keeps the nearest sample, normals the coverage-weighted mean. `indices` (sH, sW):
        the palette index of each sample in a categorical colour mode (-1 where empty):
        categories are never mixed, a pixel takes the colour of the one covering most of it.
        """
        s = int(supersample)
        background = options.background
        if pinholes:
            shaded, coverage, depth, normals, indices, filled = fill_pinholes(shaded, coverage, depth, normals,
                                                                              indices, pixel=s)
            stats = dict(stats, pinholes=filled)
        if options.edl:
            term = eye_dome_lighting(np.where(coverage > 0, depth, np.inf), options.edl_radius * s,
                                     options.edl_strength)
            shaded = shaded * term[..., None]
            stats = dict(stats, edl={"strength": options.edl_strength, "radius": options.edl_radius})
        buffers = [np.asarray(a, np.float32) for a in (shaded, coverage, depth, normals)]
        background = np.asarray(background, np.float32)
        categories = indices is not None and s > 1  # a single sample has a single category
        premult = np.empty((0, 0, 3), np.float32)  # the box filter's own, unless categories pick it
        if categories:
            premult = _box_filter_categories(buffers[0], np.clip(buffers[1], 0, 1),
                                             np.ascontiguousarray(indices, np.int32), s)
        return cls(*_box_filter(*buffers, s, background, premult, categories), stats)

    @property
    def width(self) -> int:
        return self.alpha.shape[1]

    @property
    def height(self) -> int:
        return self.alpha.shape[0]

    def rgba8(self) -> np.ndarray:
        rgba = np.concatenate([self.color, self.alpha[..., None]], axis=-1)
        return np.round(np.clip(rgba, 0, 1) * 255).astype(np.uint8)

    def png_bytes(self) -> bytes:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(self.rgba8(), "RGBA").save(buf, format="PNG")
        return buf.getvalue()

    def _repr_png_(self) -> bytes:
        return self.png_bytes()

    def save(self, png=None, *, depth=None, normals=None, stats=None) -> None:
        """Write the requested files, each atomically (never a half-written file), after checking
        every location (a set written whole or not at all)."""
        for path, label in ((png, "png"), (depth, "depth"), (normals, "normals"), (stats, "stats")):
            if path is not None:
                check_output(os.fspath(path), label)
        if png is not None:
            write_atomically(png, self.png_bytes())
        if depth is not None:
            write_atomically(depth, _npy_bytes(self.depth.astype(np.float32)))
        if normals is not None:
            write_atomically(normals, _npy_bytes(self.normals.astype(np.float32)))
        if stats is not None:
            write_json(stats, self.stats)


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


