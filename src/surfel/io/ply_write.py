"""Writing PLY point clouds and meshes: `write_ply`, whose files `read_ply` (ply.py) reads back.

`write_ply` writes x y z (double), nx ny nz (float), red green blue (uchar), radius,
ux uy uz vx vy vz (float), each only when the cloud has it, and every attribute in the PLY
type of its dtype (bool as uchar; 64-bit integers, which PLY lacks, as double when every
value is exact there), an (N,) array as NAME, an (N, k) one as NAME_0 .. NAME_{k-1}, higher
ranks flattened likewise, each declared by a surfel_attribute comment; and the faces as
``vertex_indices`` lists of 3 ints. The geospatial flag becomes a surfel_geospatial comment,
each sensor position a surfel_sensor comment.
"""

from __future__ import annotations

import os
import re
from typing import BinaryIO

import numpy as np

from ..cloud import PointCloud
from ..errors import SurfelError
from ..files import write_atomically
from .ply import (
    _ATTRIBUTE_COMMENT,
    _AXES,
    _COLOR,
    _GEOSPATIAL_COMMENT,
    _NORMAL,
    _POSITION,
    _RESERVED,
    _SENSOR_COMMENT,
)

_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
               "f4": "float", "f8": "double"}
# The PLY type an attribute of each numpy type is written as (PLY has no bool, 64-bit integer
# or half float; those are declared with their own dtype and converted back on reading).
_WRITTEN_AS = {"b1": "u1", "i1": "i1", "u1": "u1", "i2": "i2", "u2": "u2", "i4": "i4", "u4": "u4",
               "i8": "f8", "u8": "f8", "f2": "f4", "f4": "f4", "f8": "f8"}
_EXACT_IN_DOUBLE = 2 ** 53


def write_ply(cloud: PointCloud, path: str | os.PathLike, *, binary: bool = True) -> None:
    """Write `cloud` as PLY (binary little-endian by default), atomically.

    Everything the cloud holds is written (see the module docstring), so `read_ply` gives it
    back: positions bit-exact, attributes exact in their own dtype and kind, colours quantised
    to 8 bits. The file appears complete or not at all: it is written to a temporary file
    beside it and renamed. Raises SurfelError, naming the file, for an attribute that cannot be
    a PLY property (its name, or 64-bit integers beyond 2^53) and when the file cannot be
    written.
    """
    n = len(cloud)
    columns: list[tuple[str, str, np.ndarray]] = [
        (name, "f8", cloud.positions[:, k]) for k, name in enumerate(_POSITION)]
    if cloud.normals is not None:
        columns += [(name, "f4", cloud.normals[:, k]) for k, name in enumerate(_NORMAL)]
    if cloud.colors is not None:
        rgb = np.round(cloud.colors * 255).astype(np.uint8)
        columns += [(name, "u1", rgb[:, k]) for k, name in enumerate(_COLOR)]
    if cloud.radii is not None:
        columns.append(("radius", "f4", cloud.radii))
    if cloud.axes is not None:
        flat_axes = cloud.axes.reshape(n, 6)
        columns += [(name, "f4", flat_axes[:, k]) for k, name in enumerate(_AXES)]
    comments = ["written by surfel"]
    if cloud.geospatial:
        comments.append(_GEOSPATIAL_COMMENT)
    comments += [f"{_SENSOR_COMMENT} {x:.17g} {y:.17g} {z:.17g}" for x, y, z in
                 (() if cloud.sensors is None else cloud.sensors)]
    for spec in cloud.schema.values():
        name, value = spec.name, cloud.attributes[spec.name]
        if not re.fullmatch(r"[!-~]+", name) or name in _RESERVED:
            raise SurfelError(f"{path}: attribute {name!r} cannot be a PLY property name")
        code = _WRITTEN_AS[value.dtype.kind + str(value.dtype.itemsize)]
        if value.dtype.kind in "iu" and value.dtype.itemsize == 8 and value.size and \
                max(-int(value.min()), int(value.max())) > _EXACT_IN_DOUBLE:
            raise SurfelError(f"{path}: attribute {name!r} holds 64-bit integers that PLY cannot store exactly")
        comments.append(" ".join([_ATTRIBUTE_COMMENT, name, spec.dtype.name, spec.kind, *map(str, spec.shape)]))
        if not spec.shape:
            columns.append((name, code, value))
        else:
            flat = value.reshape(n, -1)
            columns += [(f"{name}_{i}", code, flat[:, i]) for i in range(flat.shape[1])]
    names = [name for name, _, _ in columns]
    if len(set(names)) != len(names):
        raise SurfelError(f"{path}: attribute names give duplicate PLY property names")

    faces = cloud.faces if cloud.faces is not None and len(cloud.faces) else None
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    lines += [f"comment {comment}" for comment in comments]
    lines.append(f"element vertex {n}")
    lines += [f"property {_TYPE_NAMES[code]} {name}" for name, code, _ in columns]
    if faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")

    def write_body(file: BinaryIO) -> None:
        file.write(header)
        if binary:
            records = np.empty(n, dtype=[(name, "<" + code) for name, code, _ in columns])
            for name, _, values in columns:
                records[name] = values
            records.tofile(file)
            if faces is not None:
                face_records = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
                face_records["n"] = 3
                face_records["v"] = faces
                face_records.tofile(file)
        else:
            # 17 significant digits read back to the same double, 9 to the same float.
            formats = {"f8": "%.17g", "f4": "%.9g", **dict.fromkeys(("i1", "u1", "i2", "u2", "i4", "u4"), "%d")}
            table = np.column_stack([values.astype(np.float64) for _, _, values in columns])
            np.savetxt(file, table, fmt=[formats[code] for _, code, _ in columns])
            if faces is not None:
                np.savetxt(file, np.column_stack([np.full(len(faces), 3), faces]), fmt="%d")

    write_atomically(path, write_body)
