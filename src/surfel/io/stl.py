"""STL meshes (the exchange format of CAD and 3D printing): `read_stl`.

Binary STL: an 80-byte header, a little-endian uint32 triangle count, then 50 bytes per
triangle (a facet normal, three corners as float32, a 16-bit attribute). A file whose size is
exactly that of its count is binary even where its header begins with "solid", as some
exporters write it. ASCII STL: ``solid``, then ``facet normal ... outer loop`` with three
``vertex x y z`` lines per facet.

STL stores each triangle's corners apart; corners at the same position are one vertex
(exact float equality, -0 and +0 alike), which makes the shared vertices of the mesh. Then,
as for every mesh (the rendering contract), the points are those vertices with normals
area-weighted from the triangles; the facet normals and attribute bytes are not used.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ._parse import numbers_by_line
from .mesh import merged_vertices, mesh_normals

_HEADER = 80
_TRIANGLE = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
_SOLID = re.compile(rb"\s*solid", re.IGNORECASE)  # an ASCII STL's first word (matched without copying the file)
_VERTEX_LINE = re.compile(rb"^[ \t]*vertex[ \t]+([^\n]*)", re.MULTILINE)


def read_stl(path: str) -> PointCloud:
    """Read a binary or ASCII STL mesh (see the module docstring); errors raise InputError."""
    data = Path(path).read_bytes()
    count = int(np.frombuffer(data, "<u4", 1, _HEADER)[0]) if len(data) >= _HEADER + 4 else -1
    binary_size = _HEADER + 4 + count * _TRIANGLE.itemsize
    if count >= 0 and len(data) == binary_size:
        corners = np.frombuffer(data, _TRIANGLE, count, _HEADER + 4)["corners"].reshape(-1, 3)
    elif _SOLID.match(data):
        corners = _ascii_corners(data, path)
    elif count < 0:
        raise InputError(path, f"not an STL file: {len(data)} bytes, shorter than a binary STL's header")
    else:
        raise InputError(path, f"binary STL size mismatch: {count} triangles need {binary_size} bytes, "
                               f"the file has {len(data)}")
    if not len(corners):
        raise InputError(path, "STL file has no triangles")
    keep, vertex = merged_vertices(corners)
    positions, faces = corners[keep].astype(np.float64), vertex.reshape(-1, 3)
    return PointCloud(positions=positions, normals=mesh_normals(positions, faces), faces=faces, source=path)


def _ascii_corners(data: bytes, path: str) -> np.ndarray:
    """(3F, 3) float64: the ``vertex`` lines of an ASCII STL, three to a facet."""
    if b"\n" not in data:
        data = data.replace(b"\r", b"\n")
    lines = _VERTEX_LINE.findall(data)
    if not lines:
        return np.empty((0, 3))
    numbers = numbers_by_line(b"\n".join(lines), np.float64, path)
    if (numbers.per_line != 3).any():
        raise InputError(path, f"{int((numbers.per_line != 3).sum())} ASCII STL vertex lines do not hold "
                               "3 coordinates")
    if len(lines) % 3:
        raise InputError(path, f"ASCII STL has {len(lines)} vertex lines, not 3 for each facet")
    return numbers.values.reshape(-1, 3)
