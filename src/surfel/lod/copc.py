"""COPC (Cloud-Optimized Point Cloud, https://copc.io) as a lazy LOD source: `CopcSource`.

A COPC file is a LAS 1.4 LAZ file (point format 6, 7 or 8) whose points are stored as an
octree: the COPC info VLR (first VLR) gives the root cube (centre c, half size h) and the
root spacing s_0; node (d, x, y, z) is the cube of side 2h / 2^d at c - h + (x, y, z) 2h / 2^d,
and its points form one variable-size LAZ chunk. The hierarchy EVLR holds pages of 32-byte
entries (key d, x, y, z int32; offset uint64; byte size int32; point count int32, -1 meaning
"a child hierarchy page at offset"). The octree is ADDITIVE: every point is stored once, in the
coarsest node whose sampling picked it, so the union of the nodes down to depth d is a sample
of spacing about

    s_d = s_0 / 2^d.

This is the LOD idea of sequential point trees (Dachsbacher, Vogelgsang & Stamminger 2003;
survey section 2.2) on a file format other tools share, and like QSplat (Rusinkiewicz & Levoy
2000) the hierarchy is walked from the root and refined where a node's spacing projects to more
than eps pixels:

    refine(node) <=> s_d * k / z_min(node) > eps,   k = fy (perspective; z_min the nearest eye
                                                     depth of the cube) or H / ortho_height,

skipping nodes whose cube (grown by the largest splat it can hold) lies outside the view
frustum. Nodes are visited coarsest level first and nearest first, so a point budget stops the
refinement where it does least harm; the error actually reached is reported as epsilon_used.
Only the hierarchy pages and the chunks of the selected nodes are read from the file.

Splat sizes. A point whose deepest loaded node at its location is at depth D lies in a sample
of spacing s_D: every occupied cell of side s_D holds a sample, so every surface point is
within sqrt(3) s_D of one (within sqrt(2) s_D on a horizontal surface). The splat radius is

    r = max(r_own, COVER * s_D)    (s_D = 0 where the file holds no finer points there),

r_own the stored radius (extra-bytes dimension "radius"), for files that have one. Normals
come from the extra-bytes dimensions normal_x/y/z when present.

Files without them are estimated (`surfel.preprocess.complete`: PCA normals propagated, each
part facing up (+Z), or facing the sensor given by `sensors`; screen-facing points; covering
radii bounded by the sampling), node by node, and what a view estimated is kept in the source,
so that later views (an orbit, a batch) estimate only the nodes they load for the first time. A
node of depth d is estimated on the sample of its level: its points with the loaded points of
depth <= d within CONTEXT_SPACINGS node spacings s_d of them, never the deeper ones. That sample
is the cut wherever the node is the finest loaded, in any view, so there its points keep their
own radius; a point whose location holds a finer loaded node Y takes Y's typical radius (the
median of its points', estimated on Y's level, which includes that point), the size of the
sample it is drawn in. The sampling bound's reference spacing (spacing.py) is, for a node the
hierarchy lists no children of (its level's sample is the full one), the survey's
(`survey_spacing`: the median horizontal nearest-neighbour distance among the points of the
deepest nodes the hierarchy lists, SURVEY_NODES of them with their ancestors' points in their
cubes, read once per source); for a node with children, whose level is a subsample, the median
horizontal nearest-neighbour distance of its level's sample. A node's nominal s_d would not do:
one that holds all the points left in its cube is as dense as the survey, one over water
sparser, and some writers state spacings far finer than their points.
Colours: RGB (16-bit fields; divided by 255 when no value exceeds 255), else none, as
`surfel.io.las` reads a LAS file: the default colour mode is then elevation whether a tile is
LAZ or COPC, and intensity is an attribute (`--color intensity`).
Every other dimension of the loaded nodes is decoded and becomes an attribute, as
`surfel.io.las` reads a LAS file (the surfel VLR's schema when the file has one); kinds that
the file does not state are fixed by the first cut, so that they do not change between views.

`write_copc` (copc_write.py) writes a surfel cloud as COPC with these extra bytes.
"""

from __future__ import annotations

import io
import math
import os
import struct
from dataclasses import dataclass

import laspy
import lazrs
import numpy as np
from scipy.spatial import cKDTree

from ..attributes import INFINITE_LENGTH
from ..camera import Camera
from ..cloud import PointCloud, framing_sphere
from ..errors import InputError
from ..io.las import LAZ_MAX_POINTS_PER_BYTE, check_header, las_layout, layout_values

VLR_HEADER = struct.Struct("<H16sHH32s")     # reserved, user id, record id, length, description
EVLR_HEADER = struct.Struct("<H16sHQ32s")
INFO = struct.Struct("<3dddQQdd88x")         # centre, halfsize, spacing, root page offset/size, gps
ENTRY = struct.Struct("<4iQii")              # key d, x, y, z; offset; byte size; point count
COVER = math.sqrt(3)                         # splat radius / spacing that covers a cell's diagonal
CONTEXT_SPACINGS = 4.0                       # node spacings around new nodes whose loaded points join
                                             # their estimation (a 16-neighbourhood reaches about 2.3)
SURVEY_NODES = 3                             # deepest nodes whose points give the survey's spacing
INACTIVE_CLIP = (0.0, 0.0, 1.0)              # a u + b v <= 1 cuts nothing (surfel.preprocess)
# every field is an attribute of the cut, so every layer of LAZ 1.4 is decoded
_DECODE = lazrs.DecompressionSelection(lazrs.SELECTIVE_DECOMPRESS_ALL)
_KEY_BITS = 20                               # per coordinate in the packed key codes: depth <= 20
_CHILD_BITS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0],   # a child's offsets in its parent
                        [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]], np.int64)


def key_code(d: np.ndarray | int, x, y, z) -> np.ndarray:
    """Pack octree keys into int64 codes (depth in the top bits) for set lookups."""
    d, x, y, z = (np.asarray(v, np.int64) for v in (d, x, y, z))
    return (d << (3 * _KEY_BITS)) | (x << (2 * _KEY_BITS)) | (y << _KEY_BITS) | z


@dataclass(frozen=True)
class NodeEstimate:
    """What `surfel.preprocess.complete` estimated for one node's points, in their file order."""
    normals: np.ndarray      # (n, 3) float32
    radii: np.ndarray        # (n,) float32, bounded by the sampling
    derived: dict[str, np.ndarray]  # the derived attributes estimated with them (screen_facing, clip_lines)

    @property
    def typical_radius(self) -> float:
        """The median radius: the size of the node's level's sample, for shallower points there."""
        return float(np.median(self.radii))


@dataclass(frozen=True)
class Entry:
    """One hierarchy entry: a node's chunk (count > 0), a child page (count -1), or empty."""
    offset: int
    byte_size: int
    point_count: int


class _CountingFile:
    """A read-only binary file that counts the bytes it returns (a context manager)."""

    def __init__(self, path: str):
        self._file = open(path, "rb")  # noqa: SIM115 - closed by __exit__
        self.bytes_read = 0

    def __enter__(self) -> _CountingFile:
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()

    def read_at(self, offset: int, size: int) -> bytes:
        self._file.seek(offset)
        data = self._file.read(size)
        self.bytes_read += len(data)
        return data


class CopcSource:
    """A COPC file opened lazily: header, info VLR and root hierarchy page only.

    The LodSource protocol of surfel.lod.source: `select(camera, epsilon, point_budget)`
    returns the view's cut as a PointCloud ready for any splat method, and stats.
    """

    geospatial = True  # LAS: +Z up, unless a surfel VLR says otherwise

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        check_header(self.path)  # the sanity checks of plain LAS/LAZ: sizes, (E)VLR bounds
        self.size = os.path.getsize(self.path)
        self.bytes_read = 0
        self._entries: dict[int, Entry] = {}
        self._codes = np.zeros(0, np.int64)
        with _CountingFile(self.path) as file:
            self._read_header(file)
            self._read_page(file, self.info_root_offset, self.info_root_size)
        self.bytes_read += file.bytes_read
        if key_code(0, 0, 0, 0).item() not in self._entries:
            raise InputError(self.path, "COPC hierarchy has no root node")
        self._rgb_scale: float | None = None      # 255 or 65535, fixed by the first cut
        self._kinds: dict[str, str] | None = None  # the attributes' kinds, fixed by the first cut
        self._estimates: dict[int, NodeEstimate] = {}  # by key code: what earlier views estimated
        self._survey_spacing: float | None = None  # read once, when first estimating
        self.sensors: np.ndarray | None = None     # (S, 3) scanner positions, for the estimation

    # ---- opening --------------------------------------------------------------------------
    def _read_header(self, file: _CountingFile) -> None:
        head = file.read_at(0, 375)
        if head[24:26] != b"\x01\x04":
            raise InputError(self.path, "not a COPC file (COPC needs LAS 1.4)")
        header_size, point_offset = struct.unpack_from("<HI", head, 94)
        vlr_data = file.read_at(0, point_offset)
        try:
            self.header = laspy.LasHeader.read_from(io.BytesIO(vlr_data))
        except Exception as error:  # laspy raises many types; all mean a bad header here
            raise InputError(self.path, f"cannot read the LAS header: {_first_line(error)}") from error
        user, record = (VLR_HEADER.unpack_from(vlr_data, header_size)[1:3]
                        if len(vlr_data) >= header_size + VLR_HEADER.size + INFO.size else (b"", 0))
        if user.rstrip(b"\0") != b"copc" or record != 1:
            raise InputError(self.path, "not a COPC file (the first VLR is not the COPC info VLR)")
        info = INFO.unpack_from(vlr_data, header_size + VLR_HEADER.size)
        self.octree_center = np.array(info[:3])
        self.halfsize, self.spacing = float(info[3]), float(info[4])
        self.info_root_offset, self.info_root_size = int(info[5]), int(info[6])
        if not (self.halfsize > 0 and self.spacing > 0):
            raise InputError(self.path, "COPC info VLR has a non-positive half size or spacing")
        laszip = [v for v in self.header.vlrs if v.user_id == "laszip encoded"]
        if not laszip:
            raise InputError(self.path, "not a COPC file (no LAZ VLR: points are not compressed)")
        self._laszip = laszip[0].record_data
        self.point_format = self.header.point_format
        # a surfel VLR keeps the written cloud's up axis (+Y for meshes) and attribute schema
        self.layout = las_layout(self.point_format, self.header.vlrs, self.path)
        self.geospatial = self.layout.geospatial
        self.total_points = int(self.header.point_count)
        if self.total_points == 0:
            raise InputError(self.path, "COPC file holds no points")
        lo, hi = np.asarray(self.header.mins, np.float64), np.asarray(self.header.maxs, np.float64)
        self.bounds = (lo, hi)
        self.center, self.bounding_radius = framing_sphere(lo, hi)

    def _read_page(self, file: _CountingFile, offset: int, size: int) -> None:
        if size % ENTRY.size or offset + size > self.size or size <= 0:
            raise InputError(self.path, f"COPC hierarchy page at {offset} ({size} bytes) does not fit the file")
        data = file.read_at(offset, size)
        for d, x, y, z, off, nbytes, count in ENTRY.iter_unpack(data):
            if count > 0 and (off + nbytes > self.size or nbytes <= 0):
                raise InputError(self.path, f"COPC node {d}-{x}-{y}-{z} points past the end of the file "
                                            f"(truncated?)")
            if count > min(self.total_points, nbytes * LAZ_MAX_POINTS_PER_BYTE):
                raise InputError(self.path, f"COPC node {d}-{x}-{y}-{z} claims {count} points in {nbytes} bytes, "
                                            f"more than the file or LAZ can hold")
            if count == -1 and (off + nbytes > self.size or nbytes % ENTRY.size):
                raise InputError(self.path, f"COPC hierarchy page of node {d}-{x}-{y}-{z} does not fit the file")
            if not 0 <= d <= _KEY_BITS or min(x, y, z) < 0 or max(x, y, z) >= 1 << d:
                raise InputError(self.path, f"COPC hierarchy has an invalid key {d}-{x}-{y}-{z}")
            self._entries[key_code(d, x, y, z).item()] = Entry(off, nbytes, count)

    # ---- LodSource ---------------------------------------------------------------------------
    def describe(self) -> dict:
        """What `surfel info` shows: counts and the octree, without reading any points."""
        depths = [code >> (3 * _KEY_BITS) for code, e in self._entries.items() if e.point_count]
        return {"format": "COPC", "points": self.total_points, "point_format": self.point_format.id,
                "file_bytes": self.size, "spacing": self.spacing, "halfsize": self.halfsize,
                "nodes_in_root_page": len(self._entries), "depth": max(depths) if depths else 0,
                "normals": self.layout.normals is not None, "radii": self.layout.radius is not None,
                "attributes": [spec.name for spec, _ in self.layout.attributes]}

    # ---- selection ------------------------------------------------------------------------
    def select(self, camera: Camera, epsilon: float, point_budget: int | None = None
               ) -> tuple[PointCloud, dict]:
        """The cut for this view at `epsilon` pixels (see the module docstring) and its stats."""
        if not epsilon > 0:
            raise ValueError(f"epsilon must be positive, got {epsilon}")
        with _CountingFile(self.path) as file:
            nodes, epsilon_used = self._cut(file, camera, float(epsilon), point_budget)
            keys, counts, records = self._read_points(file, nodes)
        bytes_read = file.bytes_read
        self.bytes_read += bytes_read
        cloud, estimated = self._cloud(keys, counts, records)
        stats = {"nodes_loaded": len(nodes), "bytes_read": bytes_read, "file_bytes": self.size,
                 "points_selected": len(cloud), "epsilon_used": epsilon_used,
                 "depth_loaded": int(keys[:, 0].max())}
        stats.update(estimated)
        return cloud, stats

    def _cut(self, file: _CountingFile, camera: Camera, epsilon: float, budget: int | None
             ) -> tuple[list[tuple[tuple[int, int, int, int], Entry]], float]:
        """Breadth-first refinement: (key, entry) of the nodes to load, and the eps reached."""
        frontier = np.zeros((1, 4), np.int64)
        selected: list[tuple[tuple[int, int, int, int], Entry]] = []
        total = 0
        epsilon_used = epsilon
        k = camera.pixel_scale()
        while len(frontier):
            depth = int(frontier[0, 0])
            spacing = self.spacing / 2.0 ** depth
            side = 2 * self.halfsize / 2.0 ** depth
            lo = self.octree_center - self.halfsize + frontier[:, 1:] * side
            # the node's cube, shrunk to the data's bounds, grown by the splats it can hold
            pad = COVER * spacing
            visible, z_min = _frustum(camera, np.maximum(lo, self.bounds[0]) - pad,
                                      np.minimum(lo + side, self.bounds[1]) + pad)
            if camera.ortho_height is None:
                pixels = spacing * k / np.maximum(z_min, 1e-12)
            else:
                pixels = np.full(len(frontier), spacing * k)
            order = np.flatnonzero(visible)[np.argsort(z_min[visible], kind="stable")]
            refine = []
            for position, i in enumerate(order):
                entry = self._entry(file, frontier[i])  # culled nodes' pages are never read
                if budget is not None and selected and total + entry.point_count > budget:
                    # Where the nodes left out would go, their parents are the finest data:
                    # a parent's spacing is twice theirs and it is no farther away.
                    epsilon_used = max(epsilon_used, float(2 * pixels[order[position:]].max()))
                    return selected, epsilon_used
                if entry.point_count > 0:
                    selected.append((tuple(int(v) for v in frontier[i]), entry))
                    total += entry.point_count
                if pixels[i] > epsilon:
                    refine.append(frontier[i])
            frontier = self._existing_children(np.array(refine, np.int64).reshape(-1, 4))
        if not selected:  # nothing in view: the coarsest nodes, so that the cut is not empty
            selected = self._coarsest(file)
        return selected, epsilon_used

    def _coarsest(self, file: _CountingFile) -> list[tuple[tuple[int, int, int, int], Entry]]:
        """The nodes holding points at the coarsest depth that has any (pages read as needed)."""
        level = np.zeros((1, 4), np.int64)
        while len(level):
            entries = [(tuple(int(v) for v in key), self._entry(file, key)) for key in level]
            holding = [(key, entry) for key, entry in entries if entry.point_count > 0]
            if holding:
                return holding
            level = self._existing_children(level)
        raise InputError(self.path, "COPC hierarchy has no node holding points")

    def _entry(self, file: _CountingFile, key: np.ndarray) -> Entry:
        """The entry of an existing key, reading its hierarchy page first if it has one."""
        code = key_code(*key).item()
        entry = self._entries[code]
        if entry.point_count == -1:
            self._read_page(file, entry.offset, entry.byte_size)
            entry = self._entries[code]
            if entry.point_count == -1:
                raise InputError(self.path, f"COPC hierarchy page for node {'-'.join(map(str, key))} "
                                            f"does not describe that node")
        return entry

    def _leaves(self, keys: np.ndarray) -> np.ndarray:
        """(M,) bool: the nodes of `keys` (M, 4) the hierarchy lists no children of."""
        child = (keys[:, None, 1:] * 2 + _CHILD_BITS[None]).reshape(-1, 3)
        codes = key_code(np.repeat(keys[:, 0] + 1, 8), *child.T)
        return ~self._exists(codes).reshape(len(keys), 8).any(axis=1)

    def _existing_children(self, parents: np.ndarray) -> np.ndarray:
        """The children (M, 4) of `parents` that the hierarchy lists."""
        if not len(parents):
            return parents
        xyz = (parents[:, None, 1:] * 2 + _CHILD_BITS[None]).reshape(-1, 3)
        children = np.column_stack([np.full(len(xyz), parents[0, 0] + 1), xyz])
        return children[self._exists(key_code(*children.T))]

    def _exists(self, codes: np.ndarray) -> np.ndarray:
        """Which key codes the hierarchy read so far lists (a child page's root is listed)."""
        if len(self._codes) != len(self._entries):
            self._codes = np.array(sorted(self._entries), np.int64)
        return _member(codes, self._codes)

    def _read_points(self, file: _CountingFile, nodes: list
                     ) -> tuple[np.ndarray, np.ndarray, laspy.ScaleAwarePointRecord]:
        """Read and decompress the chunks of `nodes` (contiguous ones in one read).

        Returns the node keys (M, 4) in file order, their point counts (M,) and the decoded
        point records (each node's points contiguous, in that order).
        """
        nodes = sorted(nodes, key=lambda node: node[1].offset)
        buffers, start, end = [], None, None
        for _, entry in nodes:
            if entry.offset != end:
                if start is not None:
                    buffers.append(file.read_at(start, end - start))
                start = entry.offset
            end = entry.offset + entry.byte_size
        buffers.append(file.read_at(start, end - start))
        compressed = b"".join(buffers)
        count = sum(entry.point_count for _, entry in nodes)
        if len(compressed) != sum(entry.byte_size for _, entry in nodes):
            raise InputError(self.path, "COPC point data is truncated")
        out = np.zeros(count * self.point_format.size, np.uint8)
        table = [(entry.point_count, entry.byte_size) for _, entry in nodes]
        try:
            lazrs.decompress_points_with_chunk_table(compressed, self._laszip, out, table, _DECODE)
        except BaseException as error:  # lazrs errors, or a Rust panic (a BaseException): bad data
            if not isinstance(error, Exception) and type(error).__name__ != "PanicException":
                raise
            raise InputError(self.path, f"cannot decompress COPC points: {_first_line(error)}") from error
        record = laspy.ScaleAwarePointRecord(np.frombuffer(out, self.point_format.dtype()), self.point_format,
                                             self.header.scales, self.header.offsets)
        keys = np.array([key for key, _ in nodes], np.int64)
        return keys, np.array([entry.point_count for _, entry in nodes]), record

    # ---- the cloud ------------------------------------------------------------------------
    def _cloud(self, keys: np.ndarray, counts: np.ndarray, record: laspy.ScaleAwarePointRecord
               ) -> tuple[PointCloud, dict]:
        scales, offsets = self.header.scales, self.header.offsets
        positions = np.column_stack([record["X"] * scales[0] + offsets[0], record["Y"] * scales[1] + offsets[1],
                                     record["Z"] * scales[2] + offsets[2]])
        if not np.isfinite(positions).all():
            raise InputError(self.path, "COPC points have non-finite coordinates")
        colors = self._colors(record)
        normals, radii, attributes = layout_values(record, self.layout)
        if normals is not None and (not np.isfinite(normals).all() or (np.linalg.norm(normals, axis=1) < 1e-6).any()):
            raise InputError(self.path, "COPC normals (extra bytes) are zero or not finite")
        if radii is not None and not (np.isfinite(radii).all() and (radii > 0).all()):
            raise InputError(self.path, "COPC radii (extra bytes) are not positive numbers")
        cloud = PointCloud(positions, normals=normals, colors=colors, radii=radii, attributes=attributes,
                           kinds=self.layout.kinds if self._kinds is None else self._kinds,
                           geospatial=self.geospatial, source=self.path, sensors=self.sensors)
        self._kinds = self._kinds or cloud.schema.kinds
        estimated: dict = {}
        if radii is None:
            cloud, estimated = self._estimated(cloud, keys, counts)
            radii = self._level_radii(cloud, keys, counts)
        else:  # the file's radii are for its full detail: grown to cover a coarser cut
            if normals is None:
                cloud, estimated = self._estimated(cloud, keys, counts)
            radii = np.maximum(cloud.radii, (COVER * self._region_spacing(positions, keys, counts)).astype(np.float32))
        own = cloud.radii
        extras = dict(cloud.attributes)
        if "clip_lines" in extras:
            # Clip lines cut a full-detail splat at a crease; a splat resized to cover the gaps
            # of a coarse sample must not be cut by them.
            extras["clip_lines"] = np.where((radii != own)[:, None, None], np.float32(INACTIVE_CLIP),
                                            extras["clip_lines"])
        if "thickness" in extras:  # nor capped by the thickness of a layer it now spans
            extras["thickness"] = np.where(radii != own, np.float32(INFINITE_LENGTH), extras["thickness"])
        from ..preprocess import (
            tangent_frames,  # (numba module: imported when first needed)
        )

        return cloud.with_(radii=radii, axes=tangent_frames(cloud.normals, radii), attributes=extras), estimated

    def _estimated(self, cloud: PointCloud, keys: np.ndarray, counts: np.ndarray) -> tuple[PointCloud, dict]:
        """The cut with normals, radii and their derived attributes, estimated for the nodes no
        earlier view loaded, each on its level's sample, and taken from the earlier estimates for
        the others (module docstring); and the stats of this view's estimation."""
        from ..preprocess import complete  # numba kernels: loaded only when needed
        from ..preprocess.spacing import horizontal_spacing

        codes = key_code(*keys.T).tolist()
        starts = np.concatenate([[0], np.cumsum(counts)])
        new = np.array([i for i, code in enumerate(codes) if code not in self._estimates], np.int64)
        stats: dict = {"estimated_points": int(counts[new].sum()), "reused_points": int(len(cloud) - counts[new].sum())}
        depth = np.repeat(keys[:, 0], counts)
        survey = self.survey_spacing() if self.geospatial and len(new) else None
        leaves = np.repeat(self._leaves(keys), counts)
        for level in np.unique(keys[new, 0]):
            nodes = new[keys[new, 0] == level]
            fresh = np.concatenate([np.arange(starts[i], starts[i + 1]) for i in nodes])
            sample = np.flatnonzero(depth <= level)
            reach = CONTEXT_SPACINGS * self.spacing / 2.0 ** level
            context = np.concatenate([fresh, _nearby(cloud.positions, fresh, np.setdiff1d(sample, fresh), reach)])
            reference = None
            if survey is not None:  # the full sample's spacing for leaves, the level's for the others
                level_spacing = horizontal_spacing(cloud.positions[context]) or survey
                reference = np.where(leaves[context], survey, max(level_spacing, survey))
            completed, stats["estimated"] = complete(cloud.take(context), progress=False,
                                                     reference_spacing=reference)
            derived = [name for name in completed.schema if completed.schema[name].derived]
            row = 0
            for i in nodes:
                rows = slice(row, row + int(counts[i]))
                self._estimates[codes[i]] = NodeEstimate(completed.normals[rows], completed.radii[rows],
                                                         {name: completed.attributes[name][rows] for name in derived})
                row = rows.stop
        estimates = [self._estimates[code] for code in codes]
        attributes = dict(cloud.attributes)
        for name in estimates[0].derived:
            attributes[name] = np.concatenate([estimate.derived[name] for estimate in estimates])
        return cloud.with_(normals=np.concatenate([estimate.normals for estimate in estimates]),
                           radii=np.concatenate([estimate.radii for estimate in estimates]),
                           attributes=attributes), stats

    def _level_radii(self, cloud: PointCloud, keys: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """Each point's own estimated radius where its node is the finest loaded at its
        location, else the typical radius of the finest loaded node there (module docstring)."""
        deepest = self._deepest_loaded(cloud.positions, keys, counts)
        own_depth = np.repeat(keys[:, 0], counts)
        radii = cloud.radii.copy()
        shallower = np.flatnonzero(deepest > own_depth)
        if len(shallower):
            unit = (cloud.positions[shallower] - (self.octree_center - self.halfsize)) / (2 * self.halfsize)
            level = deepest[shallower]
            cell = np.clip(np.floor(unit * (2.0 ** level)[:, None]), 0, (2 ** level - 1)[:, None]).astype(np.int64)
            finest = key_code(level, *cell.T)
            typical = {code: self._estimates[code].typical_radius for code in np.unique(finest).tolist()}
            radii[shallower] = np.array([typical[code] for code in finest.tolist()], np.float32)
        return radii

    def survey_spacing(self) -> float | None:
        """The horizontal point spacing of the full sample (module docstring), read once; None
        if those points have no distinct horizontal neighbours."""
        if self._survey_spacing is None:
            from ..preprocess.spacing import horizontal_spacing

            with _CountingFile(self.path) as file:
                listed = [(code, entry) for code, entry in self._entries.items() if entry.point_count > 0]
                deepest = max(code >> (3 * _KEY_BITS) for code, _ in listed)
                chosen = sorted((entry.point_count, code) for code, entry in listed
                                if code >> (3 * _KEY_BITS) == deepest)[-SURVEY_NODES:]
                spacings = []
                for _, code in chosen:
                    key = np.array(_decode(code))
                    chain = [(tuple(int(v) for v in ancestor), self._entry(file, ancestor))
                             for ancestor in (np.r_[d, key[1:] >> (key[0] - d)] for d in range(key[0] + 1))]
                    chain = [(k, e) for k, e in chain if e.point_count > 0]
                    _, _, record = self._read_points(file, chain)
                    scales, offsets = self.header.scales, self.header.offsets
                    xyz = np.column_stack([record[axis] * scales[a] + offsets[a] for a, axis in enumerate("XYZ")])
                    side = 2 * self.halfsize / 2.0 ** key[0]
                    lo = self.octree_center - self.halfsize + key[1:] * side
                    inside = ((xyz >= lo) & (xyz <= lo + side)).all(axis=1)
                    spacing = horizontal_spacing(xyz[inside]) if inside.sum() > 1 else None
                    if spacing is not None:
                        spacings.append(spacing)
            self.bytes_read += file.bytes_read
            self._survey_spacing = float(np.median(spacings)) if spacings else math.nan
        return None if math.isnan(self._survey_spacing) else self._survey_spacing

    def _region_spacing(self, positions: np.ndarray, keys: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """s_D of each point's deepest loaded node D, 0 where the file has nothing finer there.

        keys (M, 4), counts (M,): the loaded nodes, whose points follow each other in that order.
        """
        deepest = self._deepest_loaded(positions, keys, counts)
        unit = (positions - (self.octree_center - self.halfsize)) / (2 * self.halfsize)
        child = np.clip(np.floor(unit * (2.0 ** (deepest + 1))[:, None]), 0,
                        (2 ** (deepest + 1) - 1)[:, None]).astype(np.int64)
        finer = self._exists(key_code(deepest + 1, *child.T))
        return np.where(finer, self.spacing / 2.0 ** deepest, 0.0)

    def _deepest_loaded(self, positions: np.ndarray, keys: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """The depth (N,) of the deepest loaded node at each point's location (as _region_spacing)."""
        loaded = np.sort(key_code(*keys.T))
        top = int(keys[:, 0].max())
        # only points of nodes with a loaded descendant can lie in a deeper loaded node
        ancestors = [np.zeros(0, np.int64)]
        for level in range(top):
            deeper = keys[keys[:, 0] > level]
            ancestors.append(key_code(level, *(deeper[:, 1:] >> (deeper[:, :1] - level)).T))
        walk = np.flatnonzero(np.repeat(_member(key_code(*keys.T), np.unique(np.concatenate(ancestors))), counts))
        deepest = np.repeat(keys[:, 0], counts)
        unit = (positions - (self.octree_center - self.halfsize)) / (2 * self.halfsize)
        for depth in range(top, 0, -1):
            todo = walk[deepest[walk] < depth]
            cell = np.clip(np.floor(unit[todo] * 2 ** depth), 0, 2 ** depth - 1).astype(np.int64)
            deepest[todo[_member(key_code(depth, *cell.T), loaded)]] = depth
        return deepest

    def _colors(self, record: laspy.PackedPointRecord) -> np.ndarray | None:
        names = set(self.point_format.dimension_names)
        if {"red", "green", "blue"} <= names:
            rgb = np.column_stack([record["red"], record["green"], record["blue"]]).astype(np.float32)
            if self._rgb_scale is None and rgb.max() > 0:
                self._rgb_scale = 255.0 if rgb.max() <= 255 else 65535.0
            if self._rgb_scale is not None:
                return np.minimum(rgb / self._rgb_scale, 1.0)
        return None


def _frustum(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which boxes (M, 3) meet the view frustum (conservatively), and their nearest eye depth."""
    corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
    points = np.where(corners[None] == 1, hi[:, None], lo[:, None])          # (M, 8, 3)
    m = camera.world_to_eye
    eye = points @ m[:3, :3].T + m[:3, 3]
    depth = -eye[..., 2]
    x, y = eye[..., 0], eye[..., 1]
    w, h = camera.width, camera.height
    if camera.ortho_height is None:
        left, right = -camera.cx / camera.fx * depth, (w - camera.cx) / camera.fx * depth
        down, up = (camera.cy - h) / camera.fy * depth, camera.cy / camera.fy * depth
        ahead = (depth > 0).any(axis=1)
    else:
        s = camera.pixel_scale()
        left, right, down, up = -camera.cx / s, (w - camera.cx) / s, (camera.cy - h) / s, camera.cy / s
        ahead = np.ones(len(lo), bool)
    outside = ((x < left).all(1) | (x > right).all(1) | (y < down).all(1) | (y > up).all(1))
    # a box around the eye (or straddling its plane) has nearest depth 0: always refined
    z_min = np.where((depth > 0).all(axis=1), depth.min(axis=1), 0.0)
    return ahead & ~outside, z_min


def _nearby(positions: np.ndarray, fresh: np.ndarray, candidates: np.ndarray, reach: float) -> np.ndarray:
    """The `candidates` within `reach` of a `fresh` point: the neighbours their estimation needs."""
    group = positions[fresh]
    inside = candidates[((positions[candidates] >= group.min(axis=0) - reach)
                         & (positions[candidates] <= group.max(axis=0) + reach)).all(axis=1)]
    if not len(inside):
        return inside
    distance, _ = cKDTree(group).query(positions[inside], distance_upper_bound=reach, workers=-1)
    return inside[np.isfinite(distance)]


def _decode(code: int) -> tuple[int, int, int, int]:
    """The key (d, x, y, z) of a key code."""
    mask = (1 << _KEY_BITS) - 1
    return (code >> (3 * _KEY_BITS), (code >> (2 * _KEY_BITS)) & mask, (code >> _KEY_BITS) & mask, code & mask)


def _member(values: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """values in sorted_set, by binary search (no sort of the many values, unlike np.isin)."""
    if not len(sorted_set):
        return np.zeros(len(values), bool)
    index = np.minimum(np.searchsorted(sorted_set, values), len(sorted_set) - 1)
    return sorted_set[index] == values


def _first_line(error: Exception) -> str:
    return (str(error).splitlines() or [type(error).__name__])[0][:120]


__all__ = ["COVER", "CopcSource", "key_code"]
