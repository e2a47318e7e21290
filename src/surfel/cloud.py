"""The point cloud: positions, the geometry splatting and ray tracing need, and attributes.

Positions stay float64 so georeferenced data (LiDAR coordinates near 10^6 m) keeps its
precision; renderers subtract `local_origin` before converting to float32 for the GPU.
Attributes keep their own dtype and are described by `cloud.schema` (surfel.attributes).

A cloud never changes: every array it holds is read-only (caches of radii, trees and GPU
buffers are keyed by the cloud, so an array changed in place would leave them stale).
Arrays handed to the constructor are used as they are when their dtype and layout fit, and
are then marked read-only in place; changing a cloud means making a new one (`with_`).
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from functools import cached_property

import numba
import numpy as np

from .attributes import (
    CONTINUOUS,
    DERIVED,
    DERIVED_DTYPE,
    DERIVED_LENGTHS,
    DERIVED_SHAPES,
    GEOMETRY,
    INFINITE_LENGTH,
    KINDS,
    Schema,
)
from .errors import InputError, points_have


def read_only(array: np.ndarray) -> np.ndarray:
    """`array`, made read-only (in place), as every array of a cloud is."""
    array.setflags(write=False)
    return array


# ids of the arrays whose values a valid cloud holds (or a subset of them), while `with_` or
# `take` constructs a cloud from them: their values are not checked again, only their shapes
_CHECKED: ContextVar[frozenset[int]] = ContextVar("checked", default=frozenset())


@contextmanager
def _checked(arrays):
    token = _CHECKED.set(frozenset(id(array) for array in arrays if array is not None))
    try:
        yield
    finally:
        _CHECKED.reset(token)


def corners(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) corners of points (N, 3), column by column: numpy reduces a strided column
    several times faster than axis 0 of an (N, 3) array."""
    columns = [points[:, axis] for axis in range(3)]
    return np.array([column.min() for column in columns]), np.array([column.max() for column in columns])


def any_per_row(mask: np.ndarray) -> np.ndarray:
    """mask.any(axis=1) of a boolean (N, m) array, column by column: numpy reduces each short
    row on its own, several times slower (20 ms against 3 for 1.4M rows of 3)."""
    rows = mask[:, 0].copy()
    for column in range(1, mask.shape[1]):
        rows |= mask[:, column]
    return rows


def stable_order(keys: np.ndarray) -> np.ndarray:
    """np.argsort(keys, kind="stable") of non-negative int64 keys, an order of magnitude
    faster where each key and its index fit in 63 bits together (the keys of occupied cells
    span far fewer than 63 bits): the sort of the distinct key << b | index, b the bits of an
    index, is the stable order, unpacked from its low bits."""
    bits = max(len(keys) - 1, 1).bit_length()
    if len(keys) == 0 or int(keys.max()).bit_length() + bits > 63:
        return np.argsort(keys, kind="stable")
    packed = (keys << bits) | np.arange(len(keys), dtype=np.int64)
    # keys mostly in order (points sorted by Morton code, as the out-of-core build's partitions
    # are, or in a scanner's order): timsort merges their runs, three times as fast as
    # quicksort; in no order, 15% slower than it
    packed.sort(kind="stable" if np.count_nonzero(keys[1:] < keys[:-1]) < len(keys) // 4 else "quicksort")
    return packed & ((1 << bits) - 1)


def take_rows(values: np.ndarray, index) -> np.ndarray:
    """values[index] along the first axis (index: integers, a mask or a slice). Integer
    indices go through np.take, which gathers the rows of an (N, 3) array about three times
    faster than numpy's fancy indexing; anything else (a mask, an empty list) is indexed."""
    integers = None if isinstance(index, slice) else np.asarray(index)
    if integers is None or integers.dtype.kind not in "iu":
        return values[index]
    return np.take(values, integers, axis=0)


def scatter_rows(values: np.ndarray, destination: np.ndarray) -> np.ndarray:
    """values with row i moved to row destination[i] (a permutation of the rows). It reads the
    rows in order: where the destination keeps runs of rows together (siblings in a tree,
    points of one cell), it takes half the time of gathering them (`take_rows` with the
    inverse), whose every run is a cache miss the next load waits for."""
    values = np.ascontiguousarray(values)
    moved = np.empty_like(values)
    row_bytes = values.itemsize * math.prod(values.shape[1:])

    def as_bytes(array: np.ndarray) -> np.ndarray:
        return array.reshape(-1).view(np.uint8).reshape(len(array), row_bytes)

    _scatter_bytes(as_bytes(values), np.asarray(destination, np.int64), as_bytes(moved))
    return moved


@numba.njit(cache=True)
def _scatter_bytes(rows, destination, out):  # pragma: no cover - compiled
    """out[destination[i]] = rows[i], the rows as raw bytes: one kernel for every dtype."""
    width = rows.shape[1]
    for i in range(len(rows)):
        to = destination[i]
        for byte in range(width):
            out[to, byte] = rows[i, byte]


def _contiguous(value, dtype) -> np.ndarray:
    """`value` as a C-contiguous array of `dtype`: the caller's array itself when it is one."""
    array = np.asarray(value, dtype=dtype)
    return array if array.flags.c_contiguous else np.ascontiguousarray(array)


def file_normals(normals) -> np.ndarray | None:
    """Normals as a file gives them, under the one policy of every reader (so that `render`
    and `lod build`, in memory or out of core, agree on a file): a zero vector is the "no
    normal" placeholder some exporters write, and a file holding any counts as having no
    normals; they are then estimated, as for a file without any. Other values (NaN) are left
    for PointCloud to refuse."""
    if normals is None:
        return None
    normals = np.asarray(normals)
    if normals.ndim != 2:
        return normals if normals.any(axis=1).all() else None
    # column by column: numpy reduces along the rows of an (N, 3) array several times slower
    nonzero = np.zeros(len(normals), bool)
    for column in normals.T:
        nonzero |= column != 0
    return normals if nonzero.all() else None


# Bounding radii surfel renders: depths and splat sizes are float32 (up to 3.4e38, normal
# down to 1.2e-38), with eight orders of magnitude to spare for splats much smaller than the
# cloud and for what is computed from them.
EXTENT_RANGE = (1e-30, 1e30)
# The coarsest float64 step between coordinates, relative to the bounding radius, that still
# renders the cloud faithfully: Spot moved 1e12 units from the origin (steps of 1.2e-4 of its
# radius) renders within 54 dB of Spot at the origin, 1e13 (2e-3) within 36 dB.
RESOLUTION = 2.0 ** -10

# Extents (bounding radii) at which every method renders as at unit scale, measured on Spot
# scaled by powers of ten: object-space EWA, the most sensitive, holds from 1e-7 to 1e9.
# Clouds outside are rendered at unit scale (`render_unit`).
UNIT_RANGE = (2.0 ** -16, 2.0 ** 16)


def render_unit(radius: float) -> float:
    """1, or for a bounding radius outside UNIT_RANGE the power of two nearest it: the length
    a renderer divides every length by to work at unit scale (exactly: see PointCloud.scaled)."""
    if radius == 0 or UNIT_RANGE[0] <= radius <= UNIT_RANGE[1]:
        return 1.0
    return 2.0 ** round(math.log2(radius))


def framing_sphere(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and radius of the sphere auto framing fits (docs/conventions.md): the bounding box's
    centre and half its diagonal, whatever its scale; for a single point (or coincident
    ones) a radius of 1e-9 of the point's distance from the origin, at least 1e-9, so that it
    can still be framed."""
    center = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo)) / 2
    return center, radius if radius > 0 else 1e-9 * max(float(np.abs(center).max()), 1.0)


@dataclass(frozen=True, eq=False)
class PointCloud:
    """N points with optional attributes; validated on construction.

    positions : (N, 3) float64
    normals   : (N, 3) float32 unit vectors, or None
    colors    : (N, 3) float32 RGB in [0, 1] (uint8 0 to 255 is divided by 255), or None
                (renders white)
    radii     : (N,) float32 splat radius in world units, or None
    axes      : (N, 2, 3) float32 tangent axes u, v of an elliptical splat, each scaled to
                its ellipse semi-axis length (a circular splat has |u| = |v| = radius), or None
    faces     : (F, 3) int64 triangle indices when the input was a mesh, or None
    attributes: every other per-point array, (N, ...) keyed by name, in its own numeric dtype
                (scanner fields such as intensity or classification, which may hold NaN where a
                value is missing; surfel's derived arrays, float32 and finite, under the
                reserved names of surfel.attributes.DERIVED)
    kinds     : the kind ("categorical" or "continuous") of attributes whose reader knows
                it; the others' are resolved by surfel.attributes.resolve_kind. Kinds of
                names the cloud does not hold are dropped.
    geospatial: True for LAS/LAZ-like data, whose up axis is +Z
    source    : file the cloud came from, for messages
    sensors   : (S, 3) float64 positions of the scanners that measured the points (E57 poses,
                --sensor), or None. With one, every point's; with several, point i's is
                sensors[attributes["scan"][i]]. Estimated normals face them, and the spacing
                bound grows with the range from them (surfel.preprocess).
    """

    positions: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    radii: np.ndarray | None = None
    axes: np.ndarray | None = None
    faces: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)
    geospatial: bool = False
    source: str | None = None
    sensors: np.ndarray | None = None

    def __post_init__(self):
        src = self.source
        checked = _CHECKED.get()

        def known(value, arr) -> bool:  # values a valid cloud holds: only the shape is checked
            return arr is value and id(value) in checked

        pos = _contiguous(self.positions, np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise InputError(src, f"positions must have shape (N, 3), got {pos.shape}")
        n = len(pos)
        if n == 0:
            raise InputError(src, "no points")
        if not known(self.positions, pos) and not np.isfinite(pos).all():
            bad = ~np.isfinite(pos).all(axis=1)
            nan = int(np.isnan(pos).any(axis=1).sum())
            what = "NaN" if nan == int(bad.sum()) else "NaN or infinite"
            raise InputError(src, f"{points_have(int(bad.sum()))} {what} coordinates")

        def per_point(name, value, tail, dtype=np.float32, finite=True):
            if value is None:
                return None
            arr = _contiguous(value, dtype)
            if arr.shape != (n, *tail):
                raise InputError(src, f"{name} must have shape {(n, *tail)}, got {arr.shape}")
            if known(value, arr):
                return arr
            if finite and arr.dtype.kind == "f" and not np.isfinite(arr).all():
                count = int((~np.isfinite(arr.reshape(n, -1))).any(axis=1).sum())
                raise InputError(src, f"{points_have(count)} NaN or infinite {name}")
            return arr

        def attribute(name, value):
            if not isinstance(name, str) or not name or name in GEOMETRY:
                raise InputError(src, f"{name!r} cannot name an attribute (a geometry field, or not a name)")
            value = np.asarray(value)
            if value.dtype.kind not in "biuf" or value.dtype.fields is not None:
                raise InputError(src, f"attribute '{name}' is not numeric ({value.dtype})")
            if name in DERIVED:
                return per_point(name, value, DERIVED_SHAPES[name], DERIVED_DTYPE)
            dtype = value.dtype if value.dtype.isnative else value.dtype.newbyteorder("=")
            # a scanner's measurement may be missing (a LAS extra-bytes field holding NaN): kept,
            # and shown in a neutral colour (surfel.colors); surfel's own estimates are finite
            return per_point(name, value, value.shape[1:], dtype, finite=False)

        normals = per_point("normals", self.normals, (3,))
        if normals is not None and not known(self.normals, normals):
            # Rescale only what is not already unit length, so that unit normals survive a
            # write/read round trip bit for bit; those few in float64, where huge inputs whose
            # float32 squares overflow cannot.
            length2 = np.einsum("ij,ij->i", normals, normals)
            off = np.flatnonzero(~(np.abs(length2 - 1) <= 2e-6))
            if len(off):
                length = np.linalg.norm(normals[off].astype(np.float64), axis=1)
                zero = length < 1e-12
                if zero.any():
                    raise InputError(src, f"{points_have(int(zero.sum()))} zero-length normals")
                normals = normals.copy()
                normals[off] = (normals[off] / length[:, None]).astype(np.float32)
        given_colors = self.colors
        if given_colors is not None and np.asarray(given_colors).dtype == np.uint8:  # as images and meshes hold them
            given_colors = np.asarray(given_colors, np.float32) / np.float32(255)
        colors = per_point("colors", given_colors, (3,))
        if colors is not None and not known(given_colors, colors) and (colors.min() < 0 or colors.max() > 1):
            raise InputError(src, "colors must lie in [0, 1] (or be uint8, 0 to 255)")
        radii = per_point("radii", self.radii, ())
        if radii is not None and not known(self.radii, radii) and not (radii > 0).all():
            raise InputError(src, f"{points_have(int((radii <= 0).sum()))} non-positive radii")
        axes = per_point("axes", self.axes, (2, 3))
        faces = self.faces
        if faces is not None:
            faces = _contiguous(faces, np.int64)
            if faces.ndim != 2 or faces.shape[1] != 3:
                raise InputError(src, f"faces must have shape (F, 3), got {faces.shape}")
            if len(faces) and (faces.min() < 0 or faces.max() >= n):
                raise InputError(src, "faces index vertices that do not exist")
        attributes = {name: attribute(name, value) for name, value in dict(self.attributes).items()}
        kinds = {name: kind for name, kind in dict(self.kinds).items() if name in attributes}
        for name, kind in kinds.items():
            if kind not in KINDS:
                raise InputError(src, f"attribute '{name}': kind {kind!r} is not one of {', '.join(KINDS)}")
            if name in DERIVED and kind != CONTINUOUS:
                raise InputError(src, f"attribute '{name}' is derived, hence continuous, not {kind}")
        sensors = self.sensors
        if sensors is not None:
            sensors = _contiguous(sensors, np.float64)
            if sensors.ndim != 2 or sensors.shape[1] != 3 or not len(sensors) or not np.isfinite(sensors).all():
                raise InputError(src, f"sensors must be finite positions of shape (S, 3), got {sensors.shape}")
            scan = attributes.get("scan")
            if len(sensors) > 1 and (scan is None or scan.ndim != 1 or scan.dtype.kind not in "iu"
                                     or scan.min() < 0 or scan.max() >= len(sensors)):
                raise InputError(src, f"{len(sensors)} sensors need an integer attribute 'scan' indexing them")
        for array in (pos, normals, colors, radii, axes, faces, sensors, *attributes.values()):
            if array is not None:
                read_only(array)
        for name, value in [("positions", pos), ("normals", normals), ("colors", colors), ("radii", radii),
                            ("axes", axes), ("faces", faces), ("attributes", attributes), ("kinds", kinds),
                            ("sensors", sensors)]:
            object.__setattr__(self, name, value)
        self._check_scale()

    def _check_scale(self) -> None:
        """Refuse a cloud no renderer can draw faithfully (EXTENT_RANGE, RESOLUTION)."""
        lo, hi = self.bounds
        with np.errstate(over="ignore"):
            radius = float(np.linalg.norm(hi - lo)) / 2
        largest = float(np.abs(np.concatenate([lo, hi])).max())
        if radius == 0:  # one point, or coincident ones: framed by framing_sphere's floor
            if framing_sphere(lo, hi)[1] > EXTENT_RANGE[1]:
                raise InputError(self.source, f"its points coincide at coordinates as large as {largest:.3g}; "
                                              f"surfel frames such a cloud only within {EXTENT_RANGE[1] * 1e9:g} "
                                              "of the origin")
            return
        if not EXTENT_RANGE[0] <= radius <= EXTENT_RANGE[1]:
            raise InputError(self.source, f"the cloud is {2 * radius:.3g} units across; surfel renders clouds "
                                          f"{2 * EXTENT_RANGE[0]:g} to {2 * EXTENT_RANGE[1]:g} units across "
                                          "(depths and splat sizes are float32)")
        step = float(np.spacing(largest))
        if step > RESOLUTION * radius:
            raise InputError(self.source, f"coordinates as large as {largest:.3g} are resolved only to {step:.3g} "
                                          f"in float64, too coarse for a cloud {2 * radius:.3g} units across "
                                          f"(at most {RESOLUTION:g} of its radius)")

    def __len__(self) -> int:
        return len(self.positions)

    def with_(self, **changes) -> PointCloud:
        """A copy with some fields replaced (validated again: the arrays kept from this cloud
        only for their shapes, their values having been checked)."""
        with _checked([self.positions, self.normals, self.colors, self.radii, self.axes,
                       *self.attributes.values()]):
            return replace(self, **changes)

    def scaled(self, factor: float) -> PointCloud:
        """The same cloud with every length multiplied by `factor`: positions (about the
        coordinate origin), radii, axes and the LOD errors. With a power of two every value
        scales exactly, so that a renderer may work at unit scale (`render_unit`)."""
        def lengths(values):
            return None if values is None else values * np.asarray(factor, values.dtype)

        def errors(values):  # scaled but for the stand-in for infinity
            scaled = values.copy()
            finite = values != INFINITE_LENGTH
            scaled[finite] *= np.float32(factor)
            return scaled

        attributes = {name: errors(values) if name in DERIVED_LENGTHS else values
                      for name, values in self.attributes.items()}
        return replace(self, positions=self.positions * factor, radii=lengths(self.radii), axes=lengths(self.axes),
                       attributes=attributes, kinds=self.schema.kinds)

    def take(self, index: np.ndarray) -> PointCloud:
        """The points at `index` (indices or a mask) with all their attributes;
        the faces are dropped, since they refer to the old numbering."""
        def pick(value):
            return None if value is None else take_rows(value, index)

        picked = {"positions": take_rows(self.positions, index), "normals": pick(self.normals),
                  "colors": pick(self.colors), "radii": pick(self.radii), "axes": pick(self.axes)}
        attributes = {name: take_rows(value, index) for name, value in self.attributes.items()}
        # values picked from this cloud's are valid: only the shapes and the scale are checked
        with _checked([*picked.values(), *attributes.values()]):
            return PointCloud(**picked, attributes=attributes, kinds=self.schema.kinds, geospatial=self.geospatial,
                              source=self.source, sensors=self.sensors)

    def sensor_positions(self) -> np.ndarray | None:
        """(N, 3) float64: the sensor position of every point, or None when none is known."""
        if self.sensors is None:
            return None
        if len(self.sensors) == 1:
            return np.broadcast_to(self.sensors[0], self.positions.shape)
        return self.sensors[self.attributes["scan"]]

    @cached_property
    def schema(self) -> Schema:
        """The attributes' names, dtypes, per-point shapes and kinds (surfel.attributes)."""
        return Schema.of(self.attributes, self.kinds)

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners; computed once, since renderers ask every frame."""
        lo, hi = corners(self.positions)
        return read_only(lo), read_only(hi)

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
