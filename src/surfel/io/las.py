"""LAS and LAZ LiDAR point clouds: `read_las`.

Decoding is laspy's (LAZ through the lazrs backend); positions are its scaled X/Y/Z as
float64, offsets and scales applied, so georeferenced coordinates keep full precision. The
``red green blue`` dimensions (point formats 2, 3, 5, 7, 8, 10) become colours: they are
16-bit fields, but many writers store 8-bit values in them, so when no value exceeds 255
they are divided by 255, otherwise by 65535. Colour fields that are all zero (formats with
colour written by software that had none) count as no colours. The cloud is marked
geospatial (up axis +Z).

Before laspy sees the file, the public header (versions 1.0 to 1.4) is checked against the
file size: header size, offset to the point data, the VLRs and EVLRs it lists, and the point
count times the record length (for LAZ, where records are compressed, a bound on points per
byte). A header that lies is rejected at once, without allocating what it claims.
"""

from __future__ import annotations

import os
import struct
from typing import BinaryIO

import laspy
import numpy as np

from ..cloud import PointCloud
from ..errors import InputError

_VLR_HEADER = 54  # bytes of a VLR header (its payload follows)
_EVLR_HEADER = 60
# Smallest header each minor version allows, and smallest record of each point format.
_HEADER_SIZE = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
_RECORD_SIZE = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
# Even a LAZ of identical points cannot pack more points than this into one byte.
_MAX_POINTS_PER_BYTE = 50


def read_las(path: str) -> PointCloud:
    """Read a LAS or LAZ file (see the module docstring); errors raise InputError."""
    _check_header(path)
    try:
        las = laspy.read(path)
        positions = np.asarray(las.xyz, dtype=np.float64)
        names = set(las.point_format.dimension_names)
        rgb = (np.column_stack([las.red, las.green, las.blue])
               if {"red", "green", "blue"} <= names else None)
    except Exception as error:  # laspy and lazrs raise many types; all mean a bad file here
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        raise InputError(path, f"cannot decode LAS data: {message}") from error
    colors = None
    if rgb is not None and len(rgb) and rgb.max() > 0:
        colors = rgb / (255.0 if rgb.max() <= 255 else 65535.0)
    return PointCloud(positions=positions, colors=colors, geospatial=True, source=path)


def _check_header(path: str) -> None:
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
