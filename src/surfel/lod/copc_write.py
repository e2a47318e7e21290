"""Write a point cloud as COPC (https://copc.io): `write_copc`.

The octree (format in copc.py) is a cube from the bounds' minimum corner, half size h (half the
largest extent), centre c = min + h (as Untwine, PDAL's COPC writer, places it), with root
spacing s_0 = 2h / G. G, the root grid's cells per side, is the largest power of two up to
MAX_ROOT_CELLS (Untwine's 128) whose occupied cells number at most a ROOT_SHARE of the points,
so the root of a small model is a coarse preview, not most of the file. It is built top-down
and additively: at depth d every node lays a grid of cells of side

    s_d = s_0 / 2^d

over its cube and keeps, of the points no coarser node took, the one nearest each occupied
cell's centre (a Poisson-like subsample of spacing s_d, as Potree and Untwine do); the points
it does not keep go down to its children. A node whose remaining points number at most
LEAF_POINTS, or that reaches MAX_DEPTH, keeps them all and has no children. So every point is
stored exactly once, and the nodes down to depth d are a sample of spacing about s_d (what the
reader's splat radii assume). Node membership is decided on the quantized (stored) coordinates,
so a reader recomputing a point's node from its decoded position finds the same one.

The file: LAS 1.4, point format 7 (with RGB, 16-bit: round(65535 c)) or 6; VLRs: COPC info
(first, as the spec requires), LAZ (variable-size chunks, one per node, coarse levels first so a
far view reads one contiguous prefix), extra bytes normal_x, normal_y, normal_z, radius
(float32: what COPC lacks and splatting needs) and the attributes' (below); a "surfel" VLR with
JSON {"geospatial": bool, "attributes": schema} (a mesh or scan with +Y up stays +Y up: COPC
readers otherwise assume +Z; surfel.io.las reads it); after the points and the LAZ chunk table,
the hierarchy EVLR with one page holding every node's entry. The file is written to a temporary
name beside the target and renamed at the end.

Attributes (surfel.attributes). A scanner attribute that a LAS 1.4 standard dimension of the
format can hold without loss is stored there (ASPRS LAS 1.4 R15, table 15): intensity,
return_number, number_of_returns, classification, user_data, point_source_id,
scanner_channel, the flags, gps_time (as float64) and scan_angle (degrees, stored in units of
0.006 degrees: quantised to that). Any other attribute, or one whose values the standard
field cannot hold (a float intensity, a return number above 15), is stored as extra bytes of
its own type (bool as uint8, float16 as float32), one scalar dimension per component, under
its name (made unique, ASCII, at most 32 bytes). Of the derived arrays only clip_lines,
screen_facing and thickness are written: lod_* describe another hierarchy and Phong slopes
splats of other sizes. Fields the format requires but the cloud lacks get defaults (return 1
of 1); the schema in the surfel VLR names which dimensions hold attributes, so readers leave
the defaults out. laspy's CopcReader gives the same values back under the dimensions' names.
"""

from __future__ import annotations

import json
import math
import os
import struct
import time
from collections.abc import Callable

import laspy
import lazrs
import numpy as np

from ..attributes import AttributeSpec
from ..cloud import PointCloud, framing_sphere
from ..errors import SurfelError
from ..files import write_atomically, write_json
from ..io.las import SCAN_ANGLE_UNIT, SURFEL_VLR
from .copc import ENTRY, EVLR_HEADER, INFO, VLR_HEADER

MAX_ROOT_CELLS = 128      # most grid cells per side of the root node (s_0 = 2h / cells)
ROOT_SHARE = 1 / 8        # the root grid occupies at most this share of the points ...
MIN_ROOT_CELLS = 8        # ... unless coarser than this
LEAF_POINTS = 8192        # a node with at most this many points left keeps them all
MAX_DEPTH = 12            # keeps cell indices (root cells * 2^d per axis) well inside int64
HEADER_SIZE = 375
EXTRA_NAMES = ("normal_x", "normal_y", "normal_z", "radius")
# attribute -> (standard dimension of point formats 6 and 7, least and greatest value it holds)
STANDARD_FIELDS = {
    "intensity": ("intensity", 0, 65535), "return_number": ("return_number", 0, 15),
    "number_of_returns": ("number_of_returns", 0, 15), "classification": ("classification", 0, 255),
    "user_data": ("user_data", 0, 255), "point_source_id": ("point_source_id", 0, 65535),
    "scanner_channel": ("scanner_channel", 0, 3), "synthetic": ("synthetic", 0, 1),
    "key_point": ("key_point", 0, 1), "withheld": ("withheld", 0, 1), "overlap": ("overlap", 0, 1),
    "scan_direction_flag": ("scan_direction_flag", 0, 1), "edge_of_flight_line": ("edge_of_flight_line", 0, 1),
    "scan_angle": ("scan_angle", -32768 * SCAN_ANGLE_UNIT, 32767 * SCAN_ANGLE_UNIT),
    "gps_time": ("gps_time", -np.inf, np.inf),
}
_WRITTEN_DERIVED = {"clip_lines", "screen_facing", "thickness"}
_EXTRA_BYTES = struct.Struct("<2xBB32s4x24x24x24x24x24x32s")  # one extra-bytes descriptor: 192
# LAS extra-bytes data types (LAS 1.4 R15, table 24) of the numpy types they hold
_EXTRA_TYPES = {"u1": 1, "i1": 2, "u2": 3, "i2": 4, "u4": 5, "i4": 6, "u8": 7, "i8": 8, "f4": 9, "f8": 10}
_STORED_AS = {"b1": "u1", "f2": "f4"}  # types extra bytes lack, and the one each is stored as


def write_copc(cloud: PointCloud, path: str | os.PathLike, *, leaf_points: int = LEAF_POINTS,
               progress: Callable[[int, int], None] | None = None) -> dict:
    """Write `cloud` (with normals and radii) as a COPC file; returns {points, nodes, depth, bytes}.

    leaf_points: a node with at most this many points left keeps them all (module docstring).
    progress(done, total) is called with points written so far after every node.
    """
    if cloud.normals is None or cloud.radii is None:
        raise ValueError("write_copc needs normals and radii (complete the cloud first)")
    scales, offsets = _quantization(cloud.positions)
    ints = np.round((cloud.positions - offsets) / scales).astype(np.int64)
    stored = ints * scales + offsets
    lo, hi = stored.min(axis=0), stored.max(axis=0)
    # the cube starts at the data's minimum corner, as Untwine's (PDAL's COPC writer) does
    # (a single point's cube: the radius framing gives it, so that it scales with the data)
    halfsize = (float((hi - lo).max()) / 2 or framing_sphere(lo, hi)[1]) * (1 + 1e-6)
    center = lo + halfsize
    unit = (stored - lo) / (2 * halfsize)   # in [0, 1)
    root_cells = _root_cells(unit)
    spacing = 2 * halfsize / root_cells
    keys, order = _octree(unit, root_cells, leaf_points)
    fmt = laspy.PointFormat(7 if cloud.colors is not None else 6)
    placement = _placement(cloud, fmt)
    extra = [(name, np.dtype(np.float32), description) for name, description in
             zip(EXTRA_NAMES, ("unit normal x", "unit normal y", "unit normal z", "splat radius"), strict=True)]
    extra += [(dim, _extra_type(spec.dtype), spec.name) for spec, dims in placement for dim in dims
              if dim not in fmt.dimension_names]
    for name, dtype, _ in extra:
        fmt.add_extra_dimension(laspy.ExtraBytesParams(name=name, type=dtype))
    record = _records(cloud, ints, fmt, placement)
    laz = lazrs.LazVlr.new_for_compression(fmt.id, fmt.num_extra_bytes, True)
    metadata = {"geospatial": cloud.geospatial, "attributes": [{**spec.to_json(), "las": list(dims)}
                                                               for spec, dims in placement]}
    vlrs = [_vlr(b"copc", 1, b"COPC info", bytes(INFO.size)),
            _vlr(b"laszip encoded", 22204, b"lazrs variable chunks", laz.record_data()),
            _vlr(b"LASF_Spec", 4, b"surfel normals, radii, attributes", _extra_bytes_payload(extra)),
            _vlr(SURFEL_VLR.encode(), 1, b"surfel cloud", _payload(json.dumps(metadata).encode()))]
    point_offset = HEADER_SIZE + sum(len(v) for v in vlrs)
    summary: dict = {}

    def write(file) -> None:
        file.write(bytes(point_offset))
        compressor = lazrs.LasZipCompressor(file, laz)
        compressor.reserve_offset_to_chunk_table()
        entries = []
        starts = np.flatnonzero(np.r_[True, np.any(keys[order][1:] != keys[order][:-1], axis=1)])
        ends = np.r_[starts[1:], len(order)]
        for number, (start, end) in enumerate(zip(starts, ends, strict=True)):
            offset = file.tell()
            compressor.compress_many(record[order[start:end]].tobytes())
            if number + 1 < len(starts):  # done() closes the last chunk (no empty chunk after it)
                compressor.finish_current_chunk()
                entries.append((*keys[order[start]], offset, file.tell() - offset, end - start))
            if progress is not None:
                progress(int(end), len(order))
        compressor.done()
        # the last chunk ends where done() wrote the chunk table; read the table's offset
        file.seek(point_offset)
        (table_offset,) = struct.unpack("<q", file.read(8))
        entries.append((*keys[order[starts[-1]]], offset, table_offset - offset, len(order) - starts[-1]))
        file.seek(0, os.SEEK_END)
        evlr_offset = file.tell()
        page = b"".join(ENTRY.pack(*(int(v) for v in entry)) for entry in entries)
        file.write(EVLR_HEADER.pack(0, b"copc", 1000, len(page), b"COPC hierarchy") + page)
        info = INFO.pack(*center, halfsize, spacing, evlr_offset + EVLR_HEADER.size, len(page), 0.0, 0.0)
        vlrs[0] = _vlr(b"copc", 1, b"COPC info", info)
        file.seek(0)
        file.write(_header(fmt, len(vlrs), point_offset, len(cloud), scales, offsets, lo, hi, evlr_offset))
        file.write(b"".join(vlrs))
        summary.update(points=len(cloud), nodes=len(entries), depth=int(keys[:, 0].max()),
                       bytes=evlr_offset + EVLR_HEADER.size + len(page))

    write_atomically(path, write)  # opened for reading too: the chunk table's offset is patched in
    return summary


def build_command(in_path: str | os.PathLike, out_path: str | os.PathLike,
                  stats_path: str | os.PathLike | None = None) -> dict:
    """`surfel lod build IN -o OUT.copc.laz [--stats FILE.json]`: load, complete, write COPC.

    Stats: points, nodes, depth, bytes (of the file), ms (building the octree and compressing;
    not reading the input or estimating its attributes), and what was estimated.
    """
    from ..io import load
    from ..preprocess import complete

    cloud, estimated = complete(load(in_path))
    start = time.perf_counter()
    stats = write_copc(cloud, out_path)
    stats["ms"] = round((time.perf_counter() - start) * 1000, 3)
    if estimated:
        stats["estimated"] = estimated
    if stats_path is not None:
        write_json(stats_path, stats)
    return stats


def _quantization(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LAS scale and offset: a power of ten that keeps 9 digits of the extent in int32."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    offsets = np.round((lo + hi) / 2, 2)
    span = float(np.abs(positions - offsets).max()) or framing_sphere(lo, hi)[1]  # any scale, whatever the size
    scale = 10.0 ** math.ceil(math.log10(span / 1e9))
    return np.full(3, scale), offsets


def _root_cells(unit: np.ndarray) -> int:
    """G of the module docstring, for positions `unit` scaled to the unit cube."""
    cells = MAX_ROOT_CELLS
    while cells > MIN_ROOT_CELLS:
        cell = np.minimum(np.floor(unit * cells), cells - 1).astype(np.int64)
        occupied = len(np.unique((cell[:, 0] * cells + cell[:, 1]) * cells + cell[:, 2]))
        if occupied <= ROOT_SHARE * len(unit):
            break
        cells //= 2
    return cells


def _octree(unit: np.ndarray, root_cells: int, leaf_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Node keys (N, 4) of the additive octree (module docstring) of positions `unit` in the
    unit cube, and the write order: points grouped by node, nodes by depth, then x, y, z."""
    n = len(unit)
    keys = np.full((n, 4), -1, np.int64)
    remaining = np.arange(n)
    for depth in range(MAX_DEPTH + 1):
        if not len(remaining):
            break
        u = unit[remaining]
        node = np.clip(np.floor(u * 2 ** depth), 0, 2 ** depth - 1).astype(np.int64)
        cells = root_cells << depth
        cell = np.clip(np.floor(u * cells), 0, cells - 1).astype(np.int64)
        # nodes with few points left (or at the deepest level) keep them all
        node_code = (node[:, 0] * (1 << depth) + node[:, 1]) * (1 << depth) + node[:, 2]
        _, inverse, counts = np.unique(node_code, return_inverse=True, return_counts=True)
        keep = (counts[inverse] <= leaf_points) | (depth == MAX_DEPTH)
        # elsewhere the point nearest each occupied cell's centre
        cell_code = (cell[:, 0] * cells + cell[:, 1]) * cells + cell[:, 2]
        off_centre = ((u * cells - cell - 0.5) ** 2).sum(axis=1)
        by_cell = np.lexsort((off_centre, cell_code))
        first = by_cell[np.r_[True, cell_code[by_cell][1:] != cell_code[by_cell][:-1]]]
        keep[first] = True
        keys[remaining[keep]] = np.column_stack([np.full(int(keep.sum()), depth), node[keep]])
        remaining = remaining[~keep]
    order = np.lexsort((keys[:, 3], keys[:, 2], keys[:, 1], keys[:, 0]))
    return keys, order


def _placement(cloud: PointCloud, fmt: laspy.PointFormat) -> list[tuple[AttributeSpec, tuple[str, ...]]]:
    """Each written attribute's spec and the dimensions that will hold its components
    (module docstring): a standard one where it fits, else new extra-bytes names."""
    taken = set(fmt.dimension_names) | set(EXTRA_NAMES)
    out = []
    for spec in cloud.schema.values():
        if spec.derived and spec.name not in _WRITTEN_DERIVED:
            continue
        values = cloud.attributes[spec.name]
        standard = STANDARD_FIELDS.get(spec.name)
        if standard is not None and not spec.shape and _fits(values, *standard[1:],
                                                             integer=standard[0] not in ("scan_angle", "gps_time")):
            out.append((spec, (standard[0],)))
            continue
        names = [spec.name] if not spec.shape else [f"{spec.name}_{i}" for i in range(spec.components)]
        dims = tuple(_unique_name(name, taken) for name in names)
        taken.update(dims)
        out.append((spec, dims))
    return out


def _fits(values: np.ndarray, lowest: float, highest: float, *, integer: bool) -> bool:
    """Whether a standard field holding whole numbers (or any) in [lowest, highest] holds `values`."""
    if integer and values.dtype.kind not in "biu":
        return False
    return not len(values) or bool(lowest <= values.min() and values.max() <= highest)


def _unique_name(name: str, taken: set[str]) -> str:
    """An ASCII extra-bytes name of at most 32 bytes, not in `taken`."""
    base = name.encode("ascii", "replace").decode()[:32]
    candidate, number = base, 1
    while candidate in taken:
        suffix = f"_{number}"
        candidate, number = base[:32 - len(suffix)] + suffix, number + 1
    return candidate


def _extra_type(dtype: np.dtype) -> np.dtype:
    code = dtype.kind + str(dtype.itemsize)
    return np.dtype(_STORED_AS.get(code, code))


def _records(cloud: PointCloud, ints: np.ndarray, fmt: laspy.PointFormat,
             placement: list[tuple[AttributeSpec, tuple[str, ...]]]) -> np.ndarray:
    """The LAS point records (structured array) in the input order."""
    n = len(cloud)
    record = laspy.PackedPointRecord.zeros(n, fmt)
    for axis, name in enumerate("XYZ"):
        record[name] = ints[:, axis].astype(np.int32)
    record["return_number"] = np.ones(n, np.uint8)
    record["number_of_returns"] = np.ones(n, np.uint8)
    if cloud.colors is not None:
        rgb = np.round(cloud.colors.astype(np.float64) * 65535).astype(np.uint16)
        for axis, name in enumerate(("red", "green", "blue")):
            record[name] = rgb[:, axis]
    for axis, name in enumerate(EXTRA_NAMES[:3]):
        record[name] = cloud.normals[:, axis]
    record["radius"] = cloud.radii
    for spec, dims in placement:
        values = cloud.attributes[spec.name].reshape(n, -1)
        for column, dim in enumerate(dims):
            if dim == "scan_angle":  # the standard field: units of SCAN_ANGLE_UNIT degrees
                record[dim] = np.round(values[:, column].astype(np.float64) / SCAN_ANGLE_UNIT).astype(np.int16)
            else:
                record[dim] = values[:, column]
    return record.array


def _vlr(user: bytes, record_id: int, description: bytes, payload: bytes) -> bytes:
    return VLR_HEADER.pack(0, user, record_id, len(payload), description) + payload


def _extra_bytes_payload(extra: list[tuple[str, np.dtype, str]]) -> bytes:
    """The extra-bytes VLR: one descriptor per (name, type, description)."""
    return b"".join(_EXTRA_BYTES.pack(_EXTRA_TYPES[dtype.kind + str(dtype.itemsize)], 0, name.encode(),
                                      description.encode("ascii", "replace")[:32])
                    for name, dtype, description in extra)


def _payload(data: bytes) -> bytes:
    if len(data) > 0xFFFF:  # a VLR's length is 16 bits
        raise SurfelError(f"the attribute schema ({len(data)} bytes of JSON) does not fit a LAS VLR")
    return data


def _header(fmt: laspy.PointFormat, vlr_count: int, point_offset: int, count: int, scales: np.ndarray,
            offsets: np.ndarray, lo: np.ndarray, hi: np.ndarray, evlr_offset: int) -> bytes:
    """The LAS 1.4 public header block (375 bytes)."""
    head = struct.pack("<4sHH16sBB32s32sHHHIIBHI5I", b"LASF", 0, 0x10, bytes(16), 1, 4,
                       b"surfel", b"surfel COPC writer", 1, 2026, HEADER_SIZE, point_offset,
                       vlr_count, fmt.id | 0x80, fmt.size, 0, 0, 0, 0, 0, 0)
    head += struct.pack("<3d3d6d", *scales, *offsets, hi[0], lo[0], hi[1], lo[1], hi[2], lo[2])
    head += struct.pack("<QQIQ15Q", 0, evlr_offset, 1, count, count, *([0] * 14))
    assert len(head) == HEADER_SIZE
    return head


__all__ = ["LEAF_POINTS", "build_command", "write_copc"]
