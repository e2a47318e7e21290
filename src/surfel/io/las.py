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
stores them, are normals and splat radii instead.

A ``surfel`` VLR (written by surfel.lod.copc_write) holds JSON: ``geospatial`` (the up axis of
the cloud that was written) and ``attributes``, the schema of the written attributes (see
surfel.attributes) where each entry also lists under ``las`` the dimensions holding its
components; those attributes come back with their names, dtypes, shapes and kinds, and the
other dimensions (the defaults the writer had to fill in) are left out.

Before laspy sees the file, the public header (versions 1.0 to 1.4) is checked against the
file size: header size, offset to the point data, the VLRs and EVLRs it lists, and the point
count times the record length (for LAZ, where records are compressed, a bound on points per
byte). A header that lies is rejected at once, without allocating what it claims.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from typing import BinaryIO

import laspy
import numpy as np

from ..attributes import AttributeSpec, canonical_names
from ..cloud import PointCloud
from ..errors import InputError

_VLR_HEADER = 54  # bytes of a VLR header (its payload follows)
_EVLR_HEADER = 60
# Smallest header each minor version allows, and smallest record of each point format.
_HEADER_SIZE = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
_RECORD_SIZE = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
# Even a LAZ of identical points cannot pack more points than this into one byte.
_MAX_POINTS_PER_BYTE = 50
NORMAL_NAMES = (("normal_x", "normal_y", "normal_z"), ("NormalX", "NormalY", "NormalZ"))
RADIUS_NAMES = ("radius", "Radius")
COLOR_NAMES = ("red", "green", "blue")
SURFEL_VLR = "surfel"  # user id of the VLR holding surfel's JSON (module docstring)
SCAN_ANGLE_UNIT = 0.006  # degrees per unit of the scan_angle of point formats 6-10


def read_las(path: str) -> PointCloud:
    """Read a LAS or LAZ file (see the module docstring); errors raise InputError."""
    check_header(path)
    try:
        las = laspy.read(path)
        positions = np.asarray(las.xyz, dtype=np.float64)
        names = set(las.point_format.dimension_names)
        rgb = np.column_stack([las[name] for name in COLOR_NAMES]) if set(COLOR_NAMES) <= names else None
        layout = las_layout(las.point_format, las.header.vlrs, path)
        normals, radii, attributes = layout_values(las.points, layout)
    except InputError:
        raise
    except Exception as error:  # laspy and lazrs raise many types; all mean a bad file here
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        raise InputError(path, f"cannot decode LAS data: {message}") from error
    colors = None
    if rgb is not None and len(rgb) and rgb.max() > 0:
        colors = rgb / (255.0 if rgb.max() <= 255 else 65535.0)
    return PointCloud(positions=positions, normals=normals, colors=colors, radii=radii, attributes=attributes,
                      kinds=layout.kinds, geospatial=layout.geospatial, source=path)


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
    dimension = points.point_format.dimension_by_name(name)
    values = np.asarray(points[name])
    if dimension.is_standard and name in ("scan_angle", "scan_angle_rank"):
        return (values * (SCAN_ANGLE_UNIT if name == "scan_angle" else 1.0)).astype(np.float32)
    if dimension.kind == laspy.DimensionKind.BitField and dimension.num_bits == 1:
        return values.astype(bool)
    return values


def _dimension_dtype(dimension) -> np.dtype:
    if dimension.is_standard and dimension.name in ("scan_angle", "scan_angle_rank"):
        return np.dtype(np.float32)
    if dimension.kind == laspy.DimensionKind.BitField:
        return np.dtype(bool) if dimension.num_bits == 1 else np.dtype(np.uint8)
    if not dimension.is_standard and dimension.scales is not None:
        return np.dtype(np.float64)  # laspy applies the descriptor's scale and offset
    return np.dtype(dimension.dtype).base


def _dimension_shape(dimension) -> tuple[int, ...]:
    return () if dimension.num_elements == 1 else (dimension.num_elements,)


def check_header(path: str) -> None:
    """Check a LAS/LAZ public header against the file's size (module docstring); InputError if
    it lies."""
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
        _check_records(file, header_size, vlr_count, _VLR_HEADER, "<H", point_offset,
                       "VLR", "the start of the point data", path)

        point_format = format_id & 0x3F
        compressed = bool(format_id & 0xC0)  # LAZ sets bit 7 (older writers bit 6)
        if point_format not in _RECORD_SIZE:
            raise InputError(path, f"unknown LAS point format {point_format}")
        if record_length < _RECORD_SIZE[point_format]:
            raise InputError(path, f"LAS point format {point_format} needs records of at least "
                                   f"{_RECORD_SIZE[point_format]} bytes, the header says {record_length}")
        points_end = evlr_offset if evlr_count else size
        if compressed:
            if count > size * _MAX_POINTS_PER_BYTE:
                raise InputError(path, f"LAZ header claims {count} points, impossible in {size} bytes")
        elif point_offset + count * record_length > points_end:
            raise InputError(path, f"LAS header claims {count} points of {record_length} bytes, "
                                   f"more than the file holds")
        if evlr_count:
            if not point_offset <= evlr_offset <= size - evlr_count * _EVLR_HEADER:
                raise InputError(path, f"LAS header claims {evlr_count} EVLRs at offset "
                                       f"{evlr_offset}, outside the file")
            _check_records(file, evlr_offset, evlr_count, _EVLR_HEADER, "<Q", size,
                           "EVLR", "the end of the file", path)


def _check_records(file: BinaryIO, offset: int, count: int, header_size: int, length_format: str,
                   end: int, kind: str, limit: str, path: str) -> None:
    """Walk `count` (E)VLR headers from `offset`; each record must end by `end`.

    Both header kinds hold reserved (2 bytes), user id (16) and record id (2), then the
    payload length: 2 bytes in a VLR, 8 in an EVLR.
    """
    for index in range(count):
        file.seek(offset)
        record = file.read(header_size)
        if len(record) < header_size or offset + header_size > end:
            raise InputError(path, f"LAS {kind} {index + 1} of {count} runs past {limit}")
        (length,) = struct.unpack_from(length_format, record, 20)
        offset += header_size + length
        if offset > end:
            raise InputError(path, f"LAS {kind} {index + 1} of {count} runs past {limit}")
