"""OFF meshes and point sets (Geomview's Object File Format, that of the Princeton Shape
Benchmark and ModelNet): `read_off`.

Text only. The first line is the keyword, ``OFF`` with the optional prefixes ``C`` (vertex
colours) and ``N`` (vertex normals), as ``COFF``, ``NOFF`` or ``CNOFF``; ModelNet's files
often have the counts on the same line (``OFF1024 2048 0``). Then the counts ``V F E`` (E is
not used), V vertex lines ``x y z [nx ny nz] [r g b [a]]`` and F face lines ``k i_1 .. i_k
[colour]`` (0-based indices; a face's colour is not used). ``#`` starts a comment, blank lines
are skipped.

With faces, the file is a mesh: as for every mesh (the rendering contract), only the vertices
the faces reference are kept, their normals the file's (NOFF) or else area-weighted from the
faces; polygons are fan-triangulated. Without faces, every vertex is a point. Colours are
0..1, or 0..255 when a value exceeds 1.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, file_normals
from ..errors import InputError
from ._parse import numbers_by_line, ragged_arange, unit_colors
from .mesh import mesh_normals, referenced_vertices, triangles_from_polygons

_KEYWORD = re.compile(rb"\s*(C?)(N?)OFF(?=\s|\d)")
_COMMENT = re.compile(rb"#[^\n]*")
_BINARY = re.compile(rb"\s*BINARY\b")


def read_off(path: str) -> PointCloud:
    """Read an OFF file (see the module docstring); errors raise InputError."""
    text = Path(path).read_bytes()
    if b"\n" not in text:
        text = text.replace(b"\r", b"\n")
    if b"#" in text:
        text = _COMMENT.sub(b"", text)
    keyword = _KEYWORD.match(text)
    if keyword is None:
        first = text.split(maxsplit=1)[:1]
        what = repr(first[0][:20].decode("latin-1")) if first else "nothing"
        raise InputError(path, f"not an OFF file: it begins with {what}, not OFF, COFF, NOFF or CNOFF")
    colored, with_normals = bool(keyword.group(1)), bool(keyword.group(2))
    if _BINARY.match(text, keyword.end()):
        raise InputError(path, "binary OFF is not supported; write it as text")
    numbers = numbers_by_line(text[keyword.end():], np.float64, path)
    per_line = numbers.per_line[numbers.per_line > 0]  # one record per non-blank line
    firsts = np.cumsum(per_line) - per_line
    if not len(per_line) or per_line[0] < 2:
        raise InputError(path, "OFF file lacks its vertex and face counts")
    counts = numbers.values[:2]
    if not ((counts >= 0) & (counts == np.round(counts))).all():
        raise InputError(path, f"OFF counts {counts[0]:g} {counts[1]:g} are not whole numbers")
    n, faces_count = int(counts[0]), int(counts[1])
    if n + faces_count > len(per_line) - 1:
        raise InputError(path, f"OFF file is truncated: its header counts {n} + {faces_count} vertex and "
                               f"face lines, and {len(per_line) - 1} follow it")
    if n == 0:
        raise InputError(path, "OFF file has no vertices")
    width = 3 + 3 * with_normals + 3 * colored  # the numbers a vertex line must hold
    vertex_lines = per_line[1:n + 1]
    if (vertex_lines < width).any():
        raise InputError(path, f"{int((vertex_lines < width).sum())} OFF vertex lines hold fewer than "
                               f"{width} numbers")
    vertex_values = numbers.values[firsts[1:n + 1, None] + np.arange(width)]
    positions = vertex_values[:, :3]
    normals = file_normals(vertex_values[:, 3:6].astype(np.float32)) if with_normals else None
    colors = unit_colors(vertex_values[:, width - 3:]) if colored else None
    if faces_count == 0:
        return PointCloud(positions=positions, normals=normals, colors=colors, source=path)

    face_lines, face_firsts = per_line[n + 1:n + 1 + faces_count], firsts[n + 1:n + 1 + faces_count]
    sizes = numbers.values[face_firsts]
    if not ((sizes >= 0) & (sizes == np.round(sizes)) & (sizes <= face_lines - 1)).all():
        raise InputError(path, "an OFF face line does not hold as many indices as its first number says")
    sizes = sizes.astype(np.int64)
    corners = np.repeat(face_firsts + 1, sizes) + ragged_arange(sizes)
    triangles = triangles_from_polygons(sizes, numbers.values[corners], n, path)
    keep, triangles = referenced_vertices(triangles, n)
    positions = positions[keep]
    normals, colors = (None if a is None else a[keep] for a in (normals, colors))
    if normals is None:
        normals = mesh_normals(positions, triangles)
    return PointCloud(positions=positions, normals=normals, colors=colors, faces=triangles, source=path)
