"""Render results: the buffers of docs/conventions.md "Outputs" and how they are written."""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numba
import numpy as np

from .files import write_atomically, write_json


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
    def from_samples(cls, shaded, coverage, depth, normals, *, supersample: int, background,
                     stats: dict) -> RenderResult:
        """Box-filter supersampled buffers down to the output size.

        shaded (sH, sW, 3), coverage (sH, sW) in [0, 1], depth (sH, sW) (inf empty),
        normals (sH, sW, 3). Colour is averaged premultiplied by coverage and then composited
        over the background; depth keeps the nearest sample, normals the coverage-weighted mean.
        """
        s = int(supersample)
        if s == 1:  # nothing to filter: composite and mask in one pass
            buffers = (np.ascontiguousarray(a, np.float32) for a in (shaded, coverage, depth, normals))
            return cls(*_composite_over(*buffers, np.asarray(background, np.float32)), stats)
        cov = np.clip(coverage.astype(np.float32), 0, 1)
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        h, w = coverage.shape[0] // s, coverage.shape[1] // s

        def blocks(a):
            return a.reshape(h, s, w, s, *a.shape[2:])

        alpha = blocks(cov).mean(axis=(1, 3))
        premult = blocks(shaded * cov[..., None]).mean(axis=(1, 3))
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


