"""LAS and LAZ LiDAR point clouds: `read_las`, and the per-point fields of LAS records.

Decoding is laspy's (LAZ through the lazrs backend); positions are its scaled X/Y/Z as
float64, offsets and scales applied, so georeferenced coordinates keep full precision. The
``red green blue`` dimensions (point formats 2, 3, 5, 7, 8, 10) become colours: they are
16-bit fields, but many writers store 8-bit values in them, so when no value exceeds 255
they are divided by 255, otherwise by 65535. Colour fields that are all zero (formats with
colour written by software that had none) count as no colours. The cloud is marked
geospatial (up axis +Z).

Every other dimension becomes an attribute (`las_layout`, `layout_values`; ASPRS LAS 1.4 R15,
tables 7 to 17), with laspy's names and dtypes: intensity (uint16), return_number,
number_of_returns, classification, user_data, scanner_channel (uint8), point_source_id
(uint16), gps_time (float64), the one-bit flags (synthetic, key_point, withheld, overlap,
scan_direction_flag, edge_of_flight_line) as bool, and ``scan_angle`` in degrees (float32:
formats 0-5 store whole degrees as scan_angle_rank, formats 6-10 units of 0.006 degrees).
Extra-bytes dimensions keep their type and element count (an array type gives an (N, k)
attribute) and their name, spelled as `surfel.attributes.canonical_names` makes it. Extra
bytes named normal_x/y/z (or NormalX/Y/Z) and radius (or Radius), as surfel's COPC writer
stores them, are normals and splat radii instead (zero normals: see `cloud.file_normals`).

A ``surfel`` VLR (written by surfel.lod.copc_write) holds JSON: ``geospatial`` (the up axis of
the cloud that was written) and ``attributes``, the schema of the written attributes (see
surfel.attributes) where each entry also lists under ``las`` the dimensions holding its
components; those attributes come back with their names, dtypes, shapes and kinds, and the
other dimensions (the defaults the writer had to fill in) are left out.

Before laspy sees the file, the public header (versions 1.0 to 1.4) is checked against the
file size: header size, offset to the point data, the VLRs and EVLRs it lists, and the point
count times the record length. A LAZ file's records are compressed, and a run of identical
points packs about 150 into a byte, so its size bounds nothing useful; its chunk table
(LASzip: an int64 offset at the start of the point data, then version, number of chunks and
each chunk's point and byte counts) does. The count must fit the chunks, each holding the
LASzip VLR's chunk size (or its own count, for variable-size chunks) but at most
LAZ_MAX_POINTS_PER_BYTE points a byte; their bytes must fit between the point data's start
and the table. A header that lies is rejected at once, without allocating what it claims.
What is left to a lie (chunks that hold fewer points than they claim) ends when the decoder
runs out of data: points are decoded in pieces of PIECE_POINTS, so memory grows only with
the points the file really holds.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from ..attributes import AttributeSpec, canonical_names
from ..cloud import PointCloud, file_normals
from ..errors import InputError

if TYPE_CHECKING:
    import laspy

_VLR_HEADER = 54  # bytes of a VLR header (its payload follows)
_EVLR_HEADER = 60
# Smallest header each minor version allows, and smallest record of each point format.
_HEADER_SIZE = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
_RECORD_SIZE = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
_LASZIP_VLR = ("laszip encoded", 22204)  # user id and record id of the LASzip VLR
_LASZIP_CHUNK_SIZE = struct.Struct("<I")  # at byte 12 of its payload (0: no chunks)
_CHUNK_TABLE_HEADER = struct.Struct("<II")  # version, number of chunks
# LASzip's adaptive arithmetic coder saturates on repeated points: 4 million identical ones
# take 148 points a byte (point format 0), 100 (format 6); no chunk holds more than this.
LAZ_MAX_POINTS_PER_BYTE = 256
PIECE_POINTS = 1_000_000  # points decoded at a time
NORMAL_NAMES = (("normal_x", "normal_y", "normal_z"), ("NormalX", "NormalY", "NormalZ"))
RADIUS_NAMES = ("radius", "Radius")
COLOR_NAMES = ("red", "green", "blue")
SURFEL_VLR = "surfel"  # user id of the VLR holding surfel's JSON (module docstring)
SCAN_ANGLE_UNIT = 0.006  # degrees per unit of the scan_angle of point formats 6-10


def read_las(path: str) -> PointCloud:
    """Read a LAS or LAZ file (see the module docstring); errors raise InputError."""
    count = check_header(path)
    geometry: dict[str, list[np.ndarray]] = {"positions": [], "normals": [], "radii": [], "rgb": []}
    scanned: dict[str, list[np.ndarray]] = {}
    import laspy  # here, not at the top: laspy (with requests) costs every surfel process 0.1 s to import

    try:
        with laspy.open(path) as reader:
            has_rgb = set(COLOR_NAMES) <= set(reader.header.point_format.dimension_names)
            layout = las_layout(reader.header.point_format, reader.header.vlrs, path)
            for points in reader.chunk_iterator(PIECE_POINTS):
                normals, radii, attributes = layout_values(points, layout)
                rgb = np.column_stack([points[name] for name in COLOR_NAMES]) if has_rgb else None
                positions = np.column_stack([points.x, points.y, points.z]).astype(np.float64)
                for key, value in (("positions", positions), ("normals", normals), ("radii", radii), ("rgb", rgb)):
                    if value is not None:
                        geometry[key].append(value)
                for name, value in attributes.items():
                    scanned.setdefault(name, []).append(value)
    except InputError:
        raise
    except Exception as error:  # laspy and lazrs raise many types; all mean a bad file here
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        if "failed to fill whole buffer" in message:  # lazrs (Rust's UnexpectedEof): the data ran out
            raise InputError(path, f"the point data ends before the {count} points the header claims") from None
        raise InputError(path, f"cannot decode LAS data: {message}") from error
    decoded = sum(len(piece) for piece in geometry["positions"])
    if decoded != count:
        raise InputError(path, f"LAS header claims {count} points, the file holds {decoded}")
    # joined one field at a time, each field's pieces freed as it goes
    positions, normals, radii, rgb = (_joined(geometry[key]) for key in ("positions", "normals", "radii", "rgb"))
    attributes = {name: _joined(pieces) for name, pieces in scanned.items()}
    colors = None
    if rgb is not None and len(rgb) and rgb.max() > 0:
        colors = rgb / (255.0 if rgb.max() <= 255 else 65535.0)
    return PointCloud(positions=positions, normals=file_normals(normals), colors=colors, radii=radii,
                      attributes=attributes, kinds=layout.kinds, geospatial=layout.geospatial, source=path)


def _joined(pieces: list[np.ndarray]) -> np.ndarray | None:
    if not pieces:
        return None
    joined = pieces[0] if len(pieces) == 1 else np.concatenate(pieces)
    pieces.clear()
    return joined


@dataclass(frozen=True)
class LasLayout:
    """Where a cloud's normals, radii and attributes lie among a point format's dimensions.

    attributes: (spec, dimensions) pairs; the dimensions hold the spec's components in order
    (one dimension may hold them all: an extra-bytes array). Specs give the dtype and shape
    the attribute is read as; `kinds` holds the kinds a surfel VLR stated (the others are
    resolved by the cloud, surfel.attributes.resolve_kind).
    """

    normals: tuple[str, str, str] | None
    radius: str | None
    attributes: tuple[tuple[AttributeSpec, tuple[str, ...]], ...]
    kinds: dict[str, str]
    geospatial: bool


def las_layout(point_format: laspy.PointFormat, vlrs, path: str) -> LasLayout:
    """The layout of `point_format` (module docstring), from the surfel VLR among `vlrs` when
    there is one. Raises InputError for a surfel VLR that is not what surfel writes."""
    names = list(point_format.dimension_names)
    normals = next((triple for triple in NORMAL_NAMES if set(triple) <= set(names)), None)
    radius = next((name for name in RADIUS_NAMES if name in names), None)
    stated = surfel_metadata(vlrs, path)
    geospatial = bool(stated.get("geospatial", True))
    if "attributes" in stated:
        try:
            pairs = tuple((AttributeSpec.from_json(entry), tuple(entry.get("las", ())))
                          for entry in stated["attributes"])
        except (ValueError, TypeError, AttributeError) as error:
            raise InputError(path, f"the surfel VLR's attribute schema is invalid: {error}") from None
        for spec, dims in pairs:
            if not set(dims) <= set(names) or not dims or spec.components % len(dims):
                raise InputError(path, f"the surfel VLR places attribute '{spec.name}' in dimensions "
                                       f"the point format lacks")
        return LasLayout(normals, radius, pairs, {spec.name: spec.kind for spec, _ in pairs}, geospatial)
    skip = {"X", "Y", "Z", *COLOR_NAMES, *(normals or ()), radius}
    standard = [d.name for d in point_format.dimensions if d.is_standard and d.name not in skip]
    extra = [d.name for d in point_format.dimensions if not d.is_standard and d.name not in skip]
    standard_names = ["scan_angle" if name == "scan_angle_rank" else name for name in standard]
    extra_names = canonical_names([name or f"extra_{i}" for i, name in enumerate(extra)], taken=standard_names)
    pairs = []
    for name, dim in zip(standard_names + extra_names, standard + extra, strict=True):
        dimension = point_format.dimension_by_name(dim)
        pairs.append((AttributeSpec(name, _dimension_dtype(dimension), _dimension_shape(dimension)), (dim,)))
    return LasLayout(normals, radius, tuple(pairs), {}, geospatial)


def surfel_metadata(vlrs, path: str) -> dict:
    """The JSON of the surfel VLR among `vlrs` ({} without one); InputError if it is not JSON."""
    record = next((vlr for vlr in vlrs if vlr.user_id == SURFEL_VLR), None)
    if record is None:
        return {}
    try:
        data = json.loads(record.record_data)
    except (ValueError, UnicodeDecodeError):
        data = None
    if not isinstance(data, dict) or not isinstance(data.get("geospatial"), bool):
        raise InputError(path, "the surfel VLR is not valid JSON with 'geospatial'")
    return data


def layout_values(points, layout: LasLayout) -> tuple[np.ndarray | None, np.ndarray | None, dict]:
    """(normals, radii, attributes) of laspy `points` (a record or LasData) placed by `layout`."""
    normals = None
    if layout.normals is not None:
        normals = np.column_stack([np.asarray(points[name], np.float64) for name in layout.normals])
    radii = None if layout.radius is None else np.asarray(points[layout.radius], np.float32)
    attributes = {}
    for spec, dims in layout.attributes:
        columns = [dimension_values(points, dim) for dim in dims]
        values = columns[0] if len(columns) == 1 else np.column_stack(columns)
        attributes[spec.name] = values.reshape(len(values), *spec.shape).astype(spec.dtype, copy=False)
    return normals, radii, attributes


def dimension_values(points, name: str) -> np.ndarray:
    """The values of dimension `name` as the attribute holds them: flags as bool, scan angles
    in degrees, extra bytes scaled and offset as their descriptor says."""
    import laspy

    dimension = points.point_format.dimension_by_name(name)
    values = np.asarray(points[name])
    if dimension.is_standard and name in ("scan_angle", "scan_angle_rank"):
        return (values * (SCAN_ANGLE_UNIT if name == "scan_angle" else 1.0)).astype(np.float32)
    if dimension.kind == laspy.DimensionKind.BitField and dimension.num_bits == 1:
        return values.astype(bool)
    return values


def _dimension_dtype(dimension) -> np.dtype:
    import laspy

    if dimension.is_standard and dimension.name in ("scan_angle", "scan_angle_rank"):
        return np.dtype(np.float32)
    if dimension.kind == laspy.DimensionKind.BitField:
        return np.dtype(bool) if dimension.num_bits == 1 else np.dtype(np.uint8)
    if not dimension.is_standard and dimension.scales is not None:
        return np.dtype(np.float64)  # laspy applies the descriptor's scale and offset
    return np.dtype(dimension.dtype).base


def _dimension_shape(dimension) -> tuple[int, ...]:
    return () if dimension.num_elements == 1 else (dimension.num_elements,)


def check_header(path: str) -> int:
    """Check a LAS/LAZ public header against the file's size and, for LAZ, its chunk table
    (module docstring); InputError if it lies. Returns the point count."""
    size = os.path.getsize(path)
    with open(path, "rb") as file:
        head = file.read(375)
        if len(head) < _HEADER_SIZE[0]:
            raise InputError(path, "too short for a LAS header")
        if head[:4] != b"LASF":
            raise InputError(path, "not a LAS file (no LASF signature)")
        major, minor = head[24], head[25]
        if major != 1 or minor not in _HEADER_SIZE:
            raise InputError(path, f"unsupported LAS version {major}.{minor}")
        header_size, point_offset, vlr_count, format_id, record_length, count = \
            struct.unpack_from("<HIIBHI", head, 94)
        if minor >= 4:
            if len(head) < _HEADER_SIZE[4]:
                raise InputError(path, "too short for a LAS 1.4 header")
            evlr_offset, evlr_count, count = struct.unpack_from("<QIQ", head, 235)
        else:
            evlr_offset = evlr_count = 0
        if not _HEADER_SIZE[minor] <= header_size <= point_offset <= size:
            raise InputError(path, f"LAS header size ({header_size}) or offset to point data "
                                   f"({point_offset}) does not fit a {size}-byte file")
        if vlr_count * _VLR_HEADER > point_offset - header_size:
            raise InputError(path, f"LAS header claims {vlr_count} VLRs but there is room "
                                   f"for at most {(point_offset - header_size) // _VLR_HEADER}")
        vlrs = _check_records(file, header_size, vlr_count, _VLR_HEADER, "<H", point_offset,
                              "VLR", "the start of the point data", path)

        point_format = format_id & 0x3F
        compressed = bool(format_id & 0xC0)  # LAZ sets bit 7 (older writers bit 6)
        if point_format not in _RECORD_SIZE:
            raise InputError(path, f"unknown LAS point format {point_format}")
        if record_length < _RECORD_SIZE[point_format]:
            raise InputError(path, f"LAS point format {point_format} needs records of at least "
                                   f"{_RECORD_SIZE[point_format]} bytes, the header says {record_length}")
        points_end = evlr_offset if evlr_count else size
        if evlr_count:
            if not point_offset <= evlr_offset <= size - evlr_count * _EVLR_HEADER:
                raise InputError(path, f"LAS header claims {evlr_count} EVLRs at offset "
                                       f"{evlr_offset}, outside the file")
            _check_records(file, evlr_offset, evlr_count, _EVLR_HEADER, "<Q", size,
                           "EVLR", "the end of the file", path)
        if compressed:
            laszip = vlrs.get(_LASZIP_VLR)
            if laszip is None:
                raise InputError(path, "LAZ point format but no LASzip VLR")
            capacity = _chunk_capacity(file, laszip, point_offset, points_end, record_length, path)
            if capacity is not None and count > capacity:
                raise InputError(path, f"LAZ header claims {count} points, but its chunk table holds at most "
                                       f"{capacity}")
        elif point_offset + count * record_length > points_end:
            raise InputError(path, f"LAS header claims {count} points of {record_length} bytes, "
                                   f"more than the file holds")
    return count


def _chunk_capacity(file: BinaryIO, laszip: tuple[int, int], point_offset: int, points_end: int,
                    record_length: int, path: str) -> int | None:
    """The most points the chunk table of a LAZ file allows (module docstring), or None for
    the rare files without one (LASzip's pointwise compressor: chunk size 0)."""
    offset, length = laszip
    if length < 16:
        raise InputError(path, "LASzip VLR is too short")
    file.seek(offset + 12)
    (chunk_size,) = _LASZIP_CHUNK_SIZE.unpack(file.read(4))
    if chunk_size == 0:
        return None
    file.seek(point_offset)
    head = file.read(8)
    (table_offset,) = struct.unpack("<q", head) if len(head) == 8 else (-2,)
    if table_offset == -1:  # a writer that could not seek back put it in the last 8 bytes
        file.seek(points_end - 8)
        (table_offset,) = struct.unpack("<q", file.read(8))
    if not point_offset + 8 <= table_offset <= points_end - _CHUNK_TABLE_HEADER.size:
        raise InputError(path, f"LAZ chunk table offset {table_offset} lies outside the point data")
    file.seek(table_offset)
    _, chunks = _CHUNK_TABLE_HEADER.unpack(file.read(_CHUNK_TABLE_HEADER.size))
    # each chunk starts with one uncompressed record
    room = table_offset - point_offset - 8
    if chunks * record_length > room:
        raise InputError(path, f"LAZ chunk table lists {chunks} chunks, more than {room} bytes of points can hold")
    import lazrs

    try:
        file.seek(offset)
        vlr = lazrs.LazVlr(file.read(length))
        file.seek(point_offset)
        table = lazrs.read_chunk_table(file, vlr)  # fixed-size chunks: (chunk size, bytes) each
    except Exception as error:  # lazrs reports a damaged table in several types
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        raise InputError(path, f"LAZ chunk table is damaged: {message}") from None
    if sum(chunk_bytes for _, chunk_bytes in table) > room:
        raise InputError(path, "LAZ chunk table lists chunks larger than the point data")
    return sum(min(points, chunk_bytes * LAZ_MAX_POINTS_PER_BYTE) for points, chunk_bytes in table)


def _check_records(file: BinaryIO, offset: int, count: int, header_size: int, length_format: str,
                   end: int, kind: str, limit: str, path: str) -> dict[tuple[str, int], tuple[int, int]]:
    """Walk `count` (E)VLR headers from `offset`; each record must end by `end`. Returns
    where each record's payload lies, (offset, length), by (user id, record id).

    Both header kinds hold reserved (2 bytes), user id (16) and record id (2), then the
    payload length: 2 bytes in a VLR, 8 in an EVLR.
    """
    records = {}
    for index in range(count):
        file.seek(offset)
        record = file.read(header_size)
        if len(record) < header_size or offset + header_size > end:
            raise InputError(path, f"LAS {kind} {index + 1} of {count} runs past {limit}")
        (length,) = struct.unpack_from(length_format, record, 20)
        user_id = record[2:18].split(b"\0", 1)[0].decode("latin-1")
        (record_id,) = struct.unpack_from("<H", record, 18)
        records.setdefault((user_id, record_id), (offset + header_size, length))
        offset += header_size + length
        if offset > end:
            raise InputError(path, f"LAS {kind} {index + 1} of {count} runs past {limit}")
    return records
