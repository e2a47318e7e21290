"""Lazy reading of an out-of-core sequential point tree (the directory `outofcore` writes).

Dachsbacher, Vogelgsang & Stamminger 2003 (survey section 2.2.2): each partition's nodes are
stored by r_max decreasing, so a view needs only a prefix of each partition's arrays. For a
partition whose leaves lie in the box B, every node centre lies in B too (inner nodes are
weighted means of their leaves), so with r_B the eye's distance to B the prefix is the
sequential.py bound evaluated at r_near = r_B: the first j with

    ceil(lod_emax[j]) k + lod_dsuffix[j] <= r_B,        k = f / eps

found by binary search over memory-mapped arrays (touching log n pages). Only that prefix
of the per-node test arrays (positions, lod_emin, lod_emax, lod_dparent) is read; the test

    e_g(node) k <= r     and     r - d_parent < e_g(parent) k                         (2)

selects nodes, and only the selected rows of normals, radii, axes, colours and every
attribute (the manifest's schema, surfel.attributes) are gathered.
Partitions whose box, grown by their largest disk radius, lies outside the view frustum are
skipped. The top-tree nodes above the partitions are few and always tested.

Point budget: if more than point_budget nodes pass (2), eps is doubled until the count fits,
then bisected (the count is non-increasing in eps) over the already-read prefixes, which
only shrink as eps grows; the eps used is reported.

Cache: the test-array prefixes read are kept in an LRU cache bounded by `memory` bytes, so
that successive views (a viewer, a turntable) re-read only what changed.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..attributes import Schema
from ..camera import Camera
from ..cloud import PointCloud, framing_sphere
from ..errors import InputError
from .outofcore import DIR_FORMAT, DIR_VERSION, MANIFEST, attribute_key
from .sequential import lod_scale, lod_selected, prefix_length

TEST_ARRAYS = ("positions", "lod_emin", "lod_emax", "lod_dparent")
BISECTION_STEPS = 12


@dataclass
class _Partition:
    name: str
    points: int
    nodes: int
    lo: np.ndarray
    hi: np.ndarray
    max_radius: float


@dataclass
class _Prefix:
    """The first `count` rows of a partition's test arrays."""

    count: int
    positions: np.ndarray
    emin: np.ndarray
    emax: np.ndarray
    dparent: np.ndarray

    @property
    def nbytes(self) -> int:
        return self.positions.nbytes + self.emin.nbytes + self.emax.nbytes + self.dparent.nbytes


def is_lod_dir(path: str | os.PathLike) -> bool:
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, MANIFEST))


class LazyHierarchy:
    """A LodSource over a hierarchy directory: nodes are read when a view selects them."""

    def __init__(self, path: str | os.PathLike, memory: int = 1 << 30):
        self.path = os.fspath(path)
        self.memory = memory
        manifest = _Manifest(self.path)
        self.geospatial = manifest.field("geospatial", bool)
        self.total_points = manifest.count("total_points")
        self.nodes = manifest.count("nodes")
        self.has_colors = manifest.field("colors", bool)
        try:
            self.schema = Schema.from_json(manifest.field("attributes", list))
        except ValueError as error:
            raise InputError(self.path, f"the LOD manifest's attribute schema is invalid: {error}") from None
        lo, hi = manifest.bounds(manifest.data, "bounds")
        self.bounds = (lo, hi)
        self.center, self.bounding_radius = framing_sphere(lo, hi)
        self.partitions = [manifest.partition(entry) for entry in manifest.field("partitions", list)]
        if not self.partitions:
            raise InputError(self.path, "the LOD manifest lists no partitions")
        self._rows = {part.name: part.nodes for part in self.partitions}
        self._rows["top"] = manifest.count("top_nodes")
        self.top = self._read_all("top") if self._rows["top"] else None
        self._cache: OrderedDict[str, _Prefix] = OrderedDict()

    def __len__(self) -> int:
        return self.total_points

    def describe(self) -> dict:
        """What `surfel info` reports besides the LodSource fields."""
        return {"nodes": self.nodes, "partitions": len(self.partitions),
                "top_nodes": 0 if self.top is None else len(self.top["positions"]),
                "attributes": ["normals", "radii", "axes"] + (["colors"] if self.has_colors else []) + [
                    f"{spec.name} ({spec.dtype.name}, {spec.kind})" for spec in self.schema.values()]}

    def _array(self, part: str, name: str) -> np.ndarray:
        """A partition's (or the top tree's) array, memory-mapped, with the rows the manifest
        gives it and the per-node shape and type its name calls for."""
        try:
            array = np.load(Path(self.path) / part / f"{name}.npy", mmap_mode="r")
        except (OSError, ValueError) as error:
            reason = getattr(error, "strerror", None) or error
            raise InputError(self.path, f"cannot read {part}/{name}.npy ({reason})") from None
        tail, dtype = self._layout(name)
        expected = (self._rows[part], *tail)
        if array.shape != expected or (array.dtype != dtype if dtype is not None else array.dtype.kind != "f"):
            raise InputError(self.path, f"{part}/{name}.npy holds {array.dtype} {array.shape}; the manifest calls for "
                                        f"{dtype or 'float'} {expected}")
        return array

    def _layout(self, name: str) -> tuple[tuple[int, ...], np.dtype | None]:
        """The per-node shape of an array, and its dtype (attributes; None: any float)."""
        if name.startswith("attribute-"):
            spec = list(self.schema.values())[int(name.removeprefix("attribute-"))]
            return spec.shape, spec.dtype
        return {"positions": (3,), "normals": (3,), "colors": (3,), "axes": (2, 3)}.get(name, ()), None

    def _geometry(self) -> tuple[str, ...]:
        """The per-node arrays a cut holds besides positions: file names, attributes by index."""
        return ("normals", "radii", "axes") + (("colors",) if self.has_colors else ()) + tuple(
            attribute_key(i) for i in range(len(self.schema)))

    def _read_all(self, part: str) -> dict[str, np.ndarray]:
        names = ("positions", "lod_emin", "lod_emax", "lod_dparent") + self._geometry()
        return {name: np.array(self._array(part, name)) for name in names}

    # --- selection ----------------------------------------------------------------------

    def select(self, camera: Camera, epsilon: float, point_budget: int | None = None
               ) -> tuple[PointCloud, dict]:
        """The cut for this view (see the module docstring) and its stats."""
        k = lod_scale(camera, epsilon)
        ortho = camera.ortho_height is not None
        visible = [p for p in self.partitions if _in_frustum(camera, p.lo - p.max_radius, p.hi + p.max_radius)]
        r_near = {p.name: 1.0 if ortho else _box_distance(camera.eye, p.lo, p.hi) for p in visible}
        bytes_read = 0
        prefixes: dict[str, _Prefix] = {}
        for part in visible:
            count = self._prefix_count(part.name, r_near[part.name], k, ortho)
            if count:
                prefixes[part.name], read = self._prefix(part.name, count)
                bytes_read += read
        eps = epsilon
        masks = self._masks(prefixes, camera, k)
        if point_budget is not None and _total(masks) > point_budget:
            eps, masks = self._fit_budget(prefixes, camera, epsilon, point_budget)
        pieces = [self._gather(name, mask) for name, mask in masks.items() if name != "top" and mask.any()]
        bytes_read += sum(piece.pop("bytes") for piece in pieces)
        if self.top is not None and masks["top"].any():
            pieces.append({key: value[masks["top"]] for key, value in self.top.items()})
        if not pieces:  # nothing in view: one root keeps the cloud valid (it is off screen)
            pieces.append({key: np.array(self._array(self.partitions[0].name, key)[:1])
                           for key in ("positions", *self._geometry())})

        def joined(key: str) -> np.ndarray:
            return np.concatenate([p[key] for p in pieces])

        cloud = PointCloud(joined("positions"), normals=joined("normals"),
                           colors=joined("colors") if self.has_colors else None,
                           radii=joined("radii"), axes=joined("axes"),
                           attributes={name: joined(attribute_key(i)) for i, name in enumerate(self.schema)},
                           kinds=self.schema.kinds, geospatial=self.geospatial, source=self.path)
        self._trim_cache(keep=set(prefixes))
        stats = {"nodes_loaded": sum(p.count for p in prefixes.values()), "bytes_read": int(bytes_read),
                 "points_selected": len(cloud), "epsilon_used": float(eps),
                 "partitions_visible": len(visible), "partitions": len(self.partitions)}
        return cloud, stats

    def _prefix_count(self, name: str, r_near: float, k: float, ortho: bool) -> int:
        """First j with ceil(emax[j]) k + dsuffix[j] <= r_near (binary search, mapped pages)."""
        return prefix_length(self._array(name, "lod_emax"), self._array(name, "lod_dsuffix"), r_near, k,
                             orthographic=ortho)

    def _prefix(self, name: str, count: int) -> tuple[_Prefix, int]:
        """The first `count` rows of the test arrays, from the cache or read; bytes read."""
        cached = self._cache.get(name)
        if cached is not None and cached.count >= count:
            self._cache.move_to_end(name)
            return _Prefix(count, cached.positions[:count], cached.emin[:count], cached.emax[:count],
                           cached.dparent[:count]), 0
        arrays = [np.array(self._array(name, key)[:count]) for key in TEST_ARRAYS]
        prefix = _Prefix(count, *arrays)
        self._cache[name] = prefix
        self._cache.move_to_end(name)
        return prefix, prefix.nbytes

    def _trim_cache(self, keep: set[str]) -> None:
        """Drop least recently used prefixes beyond the memory budget (not this view's)."""
        total = sum(p.nbytes for p in self._cache.values())
        for name in list(self._cache):
            if total <= self.memory:
                break
            if name not in keep:
                total -= self._cache.pop(name).nbytes

    def _masks(self, prefixes: dict[str, _Prefix], camera: Camera, k: float) -> dict[str, np.ndarray]:
        masks = {name: _test(p.positions, p.emin, p.emax, p.dparent, camera, k) for name, p in prefixes.items()}
        if self.top is not None:
            t = self.top
            masks["top"] = _test(t["positions"], t["lod_emin"], t["lod_emax"], t["lod_dparent"], camera, k)
        return masks

    def _fit_budget(self, prefixes: dict[str, _Prefix], camera: Camera, epsilon: float,
                    budget: int) -> tuple[float, dict[str, np.ndarray]]:
        """The smallest eps (to BISECTION_STEPS halvings) whose cut has at most `budget` nodes."""
        ortho = camera.ortho_height is not None

        def masks_at(eps: float) -> dict[str, np.ndarray]:
            k = lod_scale(camera, eps)
            shrunk = {}
            for name, p in prefixes.items():
                r_near = 1.0 if ortho else _box_distance(camera.eye, *self._box(name))
                count = self._prefix_count(name, r_near, k, ortho)
                shrunk[name] = _Prefix(count, p.positions[:count], p.emin[:count], p.emax[:count],
                                       p.dparent[:count])
            return self._masks(shrunk, camera, k)

        low, high = epsilon, epsilon * 2
        best = masks_at(high)
        while _total(best) > budget and high < epsilon * 2 ** 40:
            low, high = high, high * 2
            best = masks_at(high)
        for _ in range(BISECTION_STEPS):
            mid = (low + high) / 2
            masks = masks_at(mid)
            if _total(masks) <= budget:
                high, best = mid, masks
            else:
                low = mid
        # pad shorter prefixes' masks to the read prefix length for gathering
        return high, {name: np.pad(mask, (0, prefixes[name].count - len(mask))) if name in prefixes else mask
                      for name, mask in best.items()}

    def _box(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        part = next(p for p in self.partitions if p.name == name)
        return part.lo, part.hi

    def _gather(self, name: str, mask: np.ndarray) -> dict[str, np.ndarray]:
        """The selected rows' attributes (a prefix mask), read from the mapped arrays."""
        rows = np.flatnonzero(mask)
        cached = self._cache[name]
        out = {"positions": cached.positions[rows]}
        read = 0
        for key in self._geometry():
            array = self._array(name, key)
            out[key] = np.asarray(array[rows])
            read += out[key].nbytes
        out["bytes"] = read
        return out


class _Manifest:
    """The manifest of a hierarchy directory, read and checked field by field (InputError,
    naming the directory, for anything `outofcore` would not have written)."""

    def __init__(self, path: str):
        self.path = path
        try:
            self.data = json.loads((Path(path) / MANIFEST).read_text())
        except (OSError, ValueError) as error:
            reason = getattr(error, "strerror", None) or error
            raise InputError(path, f"unreadable LOD manifest ({reason})") from None
        if not isinstance(self.data, dict):
            raise InputError(path, f"the LOD manifest is a JSON {type(self.data).__name__}, not an object")
        if self.data.get("format") != DIR_FORMAT or self.data.get("version") != DIR_VERSION:
            raise InputError(path, f"not a surfel LOD directory of version {DIR_VERSION}")

    def field(self, key: str, kind: type, entry: dict | None = None, where: str = ""):
        container = self.data if entry is None else entry
        if key not in container:
            raise InputError(self.path, f"the LOD manifest lacks {where}'{key}'")
        value = container[key]
        # JSON's true and false are no counts, nor are counts true or false
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise InputError(self.path, f"the LOD manifest's {where}'{key}' is not {_KIND_NAMES[kind]}: {value!r}")
        return value

    def count(self, key: str, entry: dict | None = None, where: str = "", least: int = 0) -> int:
        value = self.field(key, int, entry, where)
        if value < least:
            raise InputError(self.path, f"the LOD manifest's {where}'{key}' must be at least {least}, got {value}")
        return value

    def bounds(self, entry: dict, key: str, where: str = "") -> tuple[np.ndarray, np.ndarray]:
        value = self.field(key, list, entry, where)
        try:
            lo, hi = (np.array(corner, np.float64) for corner in value)
        except (TypeError, ValueError):
            lo = hi = np.zeros(0)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise InputError(self.path, f"the LOD manifest's {where}'{key}' is not two corners of 3 finite numbers")
        return lo, hi

    def partition(self, entry) -> _Partition:
        if not isinstance(entry, dict):
            raise InputError(self.path, f"the LOD manifest lists a partition that is not an object: {entry!r}")
        name = self.field("name", str, entry, "partition ")
        where = f"partition {name!r}: "
        # a name is one directory inside the hierarchy: never a path out of it
        if not _PARTITION_NAME.fullmatch(name) or name == "top" or not (Path(self.path) / name).is_dir():
            raise InputError(self.path, f"the LOD manifest names partition {name!r}, which is no directory of it")
        lo, hi = self.bounds(entry, "bounds", where)
        radius = self.field("max_radius", (int, float), entry, where)
        if not (math.isfinite(radius) and radius >= 0):
            raise InputError(self.path, f"the LOD manifest's {where}'max_radius' is not a number >= 0: {radius!r}")
        return _Partition(name, self.count("points", entry, where, 1), self.count("nodes", entry, where, 1),
                          lo, hi, float(radius))


_KIND_NAMES = {bool: "true or false", int: "a whole number", list: "a list", str: "a name",
               (int, float): "a number"}
_PARTITION_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")


def _total(masks: dict[str, np.ndarray]) -> int:
    return int(sum(int(m.sum()) for m in masks.values()))


def _test(positions, emin, emax, dparent, camera: Camera, k: float) -> np.ndarray:
    """Test (2) of sequential.py over the given rows (orthographic: r = 1, no d_parent)."""
    emin = emin.astype(np.float64)
    emax = emax.astype(np.float64)
    if camera.ortho_height is not None:
        return lod_selected(1.0, emin, emax, 0.0, k)
    r = np.linalg.norm(positions - camera.eye, axis=1)
    return lod_selected(r, emin, emax, dparent.astype(np.float64), k)


def _box_distance(point: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Euclidean distance from `point` to the box [lo, hi] (0 inside)."""
    return float(np.linalg.norm(np.maximum(np.maximum(lo - point, point - hi), 0.0)))


def _in_frustum(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> bool:
    """False only if the box lies wholly outside one side of the view frustum.

    With eye coordinates (X, Y, Z), depth d = -Z, and x = cx + fx X / d, y = cy - fy Y / d,
    the image is 0 <= x <= w, 0 <= y <= h, d >= 0: five half-spaces, linear in (X, Y, d)
    (orthographic: x = cx + s X, y = cy - s Y, no depth limit)."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    m = camera.view_matrix()
    p = corners @ m[:3, :3].T + m[:3, 3]
    X, Y, d = p[:, 0], p[:, 1], -p[:, 2]
    w, h = camera.width, camera.height
    if camera.ortho_height is not None:
        s = camera.pixel_scale()
        sides = [camera.cx + s * X, w - camera.cx - s * X, camera.cy - s * Y, h - camera.cy + s * Y]
    else:
        sides = [camera.cx * d + camera.fx * X, (w - camera.cx) * d - camera.fx * X,
                 camera.cy * d - camera.fy * Y, (h - camera.cy) * d + camera.fy * Y, d]
    return all((side >= 0).any() for side in sides)
