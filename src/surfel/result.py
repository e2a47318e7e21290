"""Render results: the buffers of docs/conventions.md "Outputs" and how they are written."""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numba
import numpy as np

from .edl import eye_dome_lighting
from .files import write_atomically, write_json
from .pinholes import fill_pinholes


@numba.njit(parallel=True, cache=True)
def _composite_over(shaded, coverage, depth, normals, background):  # pragma: no cover - compiled
    """One-sample-per-pixel buffers: colour over the background, coverage clamped to [0, 1],
    depth inf and normals 0 where nothing is covered, normals unit."""
    h, w = coverage.shape
    color = np.empty((h, w, 3), np.float32)
    alpha = np.empty((h, w), np.float32)
    depth_out = np.empty((h, w), np.float32)
    normals_out = np.zeros((h, w, 3), np.float32)
    for y in numba.prange(h):
        for x in range(w):
            a = min(max(coverage[y, x], np.float32(0.0)), np.float32(1.0))
            alpha[y, x] = a
            for c in range(3):
                over = shaded[y, x, c] * a + (1 - a) * background[c]
                color[y, x, c] = min(max(over, np.float32(0.0)), np.float32(1.0))
            depth_out[y, x] = depth[y, x] if a > 0 else np.inf
            length = np.sqrt(normals[y, x, 0] ** 2 + normals[y, x, 1] ** 2 + normals[y, x, 2] ** 2)
            if a > 0 and length > 1e-12:
                for c in range(3):
                    normals_out[y, x, c] = normals[y, x, c] / length
    return color, alpha, depth_out, normals_out


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

        shaded (sH, sW, 3), coverage (sH, sW) in [0, 1], depth (sH, sW) (inf empty),
        normals (sH, sW, 3); `options` (RenderOptions): the background, and the `edl`
        shading, whose term (surfel.edl, radius edl_radius output pixels) multiplies every
        sample's (unlit) colour. Colour is averaged premultiplied by coverage and then
        composited over the background; depth keeps the nearest sample, normals the
        coverage-weighted mean. `indices` (sH, sW): the palette index of each sample in a
        categorical colour mode (-1 where empty): categories are never mixed, a pixel takes
        the colour of the one covering most of it.
        """
        s = int(supersample)
        background = options.background
        if pinholes:
            shaded, coverage, depth, normals, indices, filled = fill_pinholes(shaded, coverage, depth, normals,
                                                                              indices)
            stats = dict(stats, pinholes=filled)
        if options.edl:
            term = eye_dome_lighting(np.where(coverage > 0, depth, np.inf), options.edl_radius * s,
                                     options.edl_strength)
            shaded = shaded * term[..., None]
            stats = dict(stats, edl={"strength": options.edl_strength, "radius": options.edl_radius})
        if s == 1:  # nothing to filter: composite and mask in one pass
            buffers = (np.ascontiguousarray(a, np.float32) for a in (shaded, coverage, depth, normals))
            return cls(*_composite_over(*buffers, np.asarray(background, np.float32)), stats)
        cov = np.clip(coverage.astype(np.float32), 0, 1)
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        h, w = coverage.shape[0] // s, coverage.shape[1] // s

        def blocks(a):
            return a.reshape(h, s, w, s, *a.shape[2:])

        alpha = blocks(cov).mean(axis=(1, 3))
        if indices is None:
            premult = blocks(shaded * cov[..., None]).mean(axis=(1, 3))
        else:
            premult = _box_filter_categories(np.ascontiguousarray(shaded, np.float32), cov,
                                             np.ascontiguousarray(indices, np.int32), s)
        color = premult + (1 - alpha[..., None]) * bg
        d = np.where(cov > 0, depth, np.inf).astype(np.float32)
        depth_out = blocks(d).min(axis=(1, 3))
        nsum = blocks(normals * cov[..., None]).sum(axis=(1, 3))
        length = np.linalg.norm(nsum, axis=-1, keepdims=True)
        normals_out = np.where(length > 1e-12, nsum / np.maximum(length, 1e-12), 0).astype(np.float32)
        return cls(np.clip(color, 0, 1).astype(np.float32), alpha.astype(np.float32), depth_out,
                   normals_out, stats)

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
        """Write the requested files, each atomically (never a half-written file)."""
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


