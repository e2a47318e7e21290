"""The point cloud: positions and the per-point attributes splatting and ray tracing need.

Positions stay float64 so georeferenced data (LiDAR coordinates near 10^6 m) keeps its
precision; renderers subtract `local_origin` before converting to float32 for the GPU.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from .errors import InputError


def framing_sphere(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and radius of the sphere auto framing fits (CONVENTIONS.md): the bounding box's
    centre and half its diagonal (never 0, so a single point can still be framed)."""
    return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-9)


@dataclass(frozen=True, eq=False)
class PointCloud:
    """N points with optional attributes; validated on construction.

    positions : (N, 3) float64
    normals   : (N, 3) float32 unit vectors, or None
    colors    : (N, 3) float32 RGB in [0, 1], or None (renders white)
    radii     : (N,) float32 splat radius in world units, or None
    axes      : (N, 2, 3) float32 tangent axes u, v of an elliptical splat, each scaled to
                its ellipse semi-axis length (a circular splat has |u| = |v| = radius), or None
    faces     : (F, 3) int64 triangle indices when the input was a mesh, or None
    attributes: further per-point arrays keyed by name (scanner fields, Phong normal-field slopes, ...)
    geospatial: True for LAS/LAZ-like data, whose up axis is +Z
    source    : file the cloud came from, for messages
    """

    positions: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    radii: np.ndarray | None = None
    axes: np.ndarray | None = None
    faces: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    geospatial: bool = False
    source: str | None = None

    def __post_init__(self):
        src = self.source
        pos = np.ascontiguousarray(np.asarray(self.positions, dtype=np.float64))
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise InputError(src, f"positions must have shape (N, 3), got {pos.shape}")
        n = len(pos)
        if n == 0:
            raise InputError(src, "no points")
        bad = ~np.isfinite(pos).all(axis=1)
        if bad.any():
            nan = int(np.isnan(pos).any(axis=1).sum())
            what = "NaN" if nan == int(bad.sum()) else "NaN or infinite"
            raise InputError(src, f"{int(bad.sum())} points have {what} coordinates")
        object.__setattr__(self, "positions", pos)

        def per_point(name, value, tail, dtype=np.float32):
            if value is None:
                return None
            arr = np.ascontiguousarray(np.asarray(value, dtype=dtype))
            if arr.shape != (n, *tail):
                raise InputError(src, f"{name} must have shape {(n, *tail)}, got {arr.shape}")
            if not np.isfinite(arr).all():
                count = int((~np.isfinite(arr.reshape(n, -1))).any(axis=1).sum())
                raise InputError(src, f"{count} points have NaN or infinite {name}")
            return arr

        normals = per_point("normals", self.normals, (3,))
        if normals is not None:
            # Rescale only what is not already unit length, so that unit normals survive a
            # write/read round trip bit for bit; those few in float64, where huge inputs whose
            # float32 squares overflow cannot.
            length2 = np.einsum("ij,ij->i", normals, normals)
            off = np.flatnonzero(~(np.abs(length2 - 1) <= 2e-6))
            if len(off):
                length = np.linalg.norm(normals[off].astype(np.float64), axis=1)
                zero = length < 1e-12
                if zero.any():
                    raise InputError(src, f"{int(zero.sum())} points have zero-length normals")
                normals = normals.copy()
                normals[off] = (normals[off] / length[:, None]).astype(np.float32)
        colors = per_point("colors", self.colors, (3,))
        if colors is not None and (colors.min() < 0 or colors.max() > 1):
            raise InputError(src, "colors must lie in [0, 1]")
        radii = per_point("radii", self.radii, ())
        if radii is not None and not (radii > 0).all():
            raise InputError(src, f"{int((radii <= 0).sum())} points have non-positive radii")
        axes = per_point("axes", self.axes, (2, 3))
        faces = self.faces
        if faces is not None:
            faces = np.ascontiguousarray(np.asarray(faces, dtype=np.int64))
            if faces.ndim != 2 or faces.shape[1] != 3:
                raise InputError(src, f"faces must have shape (F, 3), got {faces.shape}")
            if len(faces) and (faces.min() < 0 or faces.max() >= n):
                raise InputError(src, "faces index vertices that do not exist")
        attributes = {k: per_point(k, v, np.shape(v)[1:]) for k, v in dict(self.attributes).items()}
        for name, value in [("normals", normals), ("colors", colors), ("radii", radii),
                            ("axes", axes), ("faces", faces), ("attributes", attributes)]:
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.positions)

    def with_(self, **changes) -> PointCloud:
        """A copy with some fields replaced (validated again)."""
        return replace(self, **changes)

    def take(self, index: np.ndarray) -> PointCloud:
        """The points at `index` (indices or a mask) with all their attributes;
        the faces are dropped, since they refer to the old numbering."""
        def pick(value):
            return None if value is None else value[index]

        return PointCloud(self.positions[index], normals=pick(self.normals), colors=pick(self.colors),
                          radii=pick(self.radii), axes=pick(self.axes),
                          attributes={name: value[index] for name, value in self.attributes.items()},
                          geospatial=self.geospatial, source=self.source)

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners; computed once, since renderers ask every frame."""
        return self.positions.min(axis=0), self.positions.max(axis=0)

    @cached_property
    def max_splat_radius(self) -> float:
        """The longest tangent semi-axis (or radius): how far splats reach past their centres."""
        if self.axes is not None:
            return float(np.sqrt((self.axes.astype(np.float32) ** 2).sum(axis=2)).max())
        return float(self.radii.max()) if self.radii is not None else 0.0

    @property
    def center(self) -> np.ndarray:
        return framing_sphere(*self.bounds)[0]

    @property
    def bounding_radius(self) -> float:
        return framing_sphere(*self.bounds)[1]

    @property
    def local_origin(self) -> np.ndarray:
        """The float64 point GPU paths subtract before going to float32."""
        return self.center

    def local_positions(self) -> np.ndarray:
        """Positions relative to `local_origin`, as float32."""
        return (self.positions - self.local_origin).astype(np.float32)

    @property
    def is_mesh(self) -> bool:
        return self.faces is not None and len(self.faces) > 0

    def attribute_names(self) -> list[str]:
        names = [n for n in ("normals", "colors", "radii", "axes", "faces") if getattr(self, n) is not None]
        return names + sorted(self.attributes)
