"""Render results: the buffers of CONVENTIONS.md "Outputs" and how they are written."""

from __future__ import annotations

import io
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(eq=False)
class RenderResult:
    """color (H, W, 3) composited over the background; alpha (H, W) coverage in [0, 1];
    depth (H, W) eye-space distance along the viewing axis, inf where empty; normals
    (H, W, 3) unit eye-space normals, 0 where empty; stats per CONVENTIONS.md."""

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    stats: dict = field(default_factory=dict)

    @classmethod
    def from_samples(cls, shaded, coverage, depth, normals, *, supersample: int, background,
                     stats: dict) -> "RenderResult":
        """Box-filter supersampled buffers down to the output size.

        shaded (sH, sW, 3), coverage (sH, sW) in [0, 1], depth (sH, sW) (inf empty),
        normals (sH, sW, 3). Colour is averaged premultiplied by coverage and then composited
        over the background; depth keeps the nearest sample, normals the coverage-weighted mean.
        """
        s = int(supersample)
        cov = np.clip(coverage.astype(np.float32), 0, 1)
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        if s == 1:  # nothing to filter: composite and mask, without the block reductions
            covered = cov > 0
            color = shaded * cov[..., None] + (1 - cov[..., None]) * bg
            depth_out = np.where(covered, depth, np.inf).astype(np.float32)
            length = np.linalg.norm(normals, axis=-1, keepdims=True)
            normals_out = np.where(covered[..., None] & (length > 1e-12), normals / np.maximum(length, 1e-12), 0)
            return cls(np.clip(color, 0, 1).astype(np.float32), cov, depth_out,
                       normals_out.astype(np.float32), stats)
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
            _atomic_write(png, self.png_bytes())
        if depth is not None:
            _atomic_write(depth, _npy_bytes(self.depth.astype(np.float32)))
        if normals is not None:
            _atomic_write(normals, _npy_bytes(self.normals.astype(np.float32)))
        if stats is not None:
            _atomic_write(stats, (json.dumps(self.stats, indent=2) + "\n").encode())


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def _atomic_write(path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
