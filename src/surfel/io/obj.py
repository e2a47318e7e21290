"""Wavefront OBJ meshes and point sets: `read_obj`.

Supported:

- ``v x y z`` vertices, with the common per-vertex colour extension ``v x y z r g b``
  (colours used only when every vertex has them; 0..1, or 0..255 when a value exceeds 1);
  a fourth value ``w`` (``v x y z w``) is ignored;
- ``f`` faces with ``a``, ``a/b``, ``a/b/c`` or ``a//c`` corners, 1-based or negative
  (relative to the vertices defined so far) indices; polygons are fan-triangulated;
- ``#`` comments, also at the end of a statement.

With faces, the file is a mesh: only the vertices the faces reference are kept, with
area-weighted vertex normals as the rendering contract says (``vn`` lines are ignored, and
so are ``vt``, groups, materials and other statements). Without faces, every vertex is a
point and no normals are set.

Lines are classified by their first two bytes and their numbers parsed with numpy, one pass
per statement kind, never line by line in Python: million-vertex files load in seconds.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ._parse import numbers_by_line, unit_colors
from .mesh import mesh_normals, referenced_vertices, triangles_from_polygons

_COMMENT = re.compile(rb"#[^\n]*")
_INDENT = re.compile(rb"^[ \t]+", re.MULTILINE)
_SLASH_TO_SPACE = bytes.maketrans(b"/", b" ")


def read_obj(path: str) -> PointCloud:
    """Read an OBJ file (see the module docstring); errors raise InputError."""
    text = Path(path).read_bytes()
    if b"\n" not in text:
        text = text.replace(b"\r", b"\n")  # classic Mac line ends
    if text[:1] in (b" ", b"\t") or b"\n " in text or b"\n\t" in text:
        text = _INDENT.sub(b"", text)  # rare: indented statements
    # Each line's first two bytes say what it is; "\n\n" pads the last line.
    codes = np.frombuffer(text + b"\n\n", dtype=np.uint8)
    line_starts = np.concatenate(([0], np.flatnonzero(codes[:len(text)] == ord("\n")) + 1))
    separated = (codes[line_starts + 1] == ord(" ")) | (codes[line_starts + 1] == ord("\t"))
    is_vertex = separated & (codes[line_starts] == ord("v"))
    is_face = separated & (codes[line_starts] == ord("f"))
    if not is_vertex.any():
        raise InputError(path, "OBJ file has no vertices ('v' lines)")

    values, per_line, _ = numbers_by_line(_statements(text, line_starts, is_vertex), np.float64, path)
    if per_line.min() < 3:
        raise InputError(path, f"{int((per_line < 3).sum())} OBJ vertices have fewer than 3 coordinates")
    first = np.cumsum(per_line) - per_line
    positions = values[first[:, None] + np.arange(3)]
    colors = None
    if per_line.min() >= 6:
        colors = unit_colors(values[first[:, None] + np.arange(3, 6)])
    if not is_face.any():
        return PointCloud(positions=positions, colors=colors, source=path)

    # Slashes become spaces, so "a/b/c" reads as three numbers; a corner's vertex index is
    # the number that does not follow a slash.
    corners = _statements(text, line_starts, is_face)
    numbers = numbers_by_line(corners.translate(_SLASH_TO_SPACE), np.int64, path)
    corner_codes = np.frombuffer(corners, dtype=np.uint8)
    is_index = (numbers.starts == 0) | (corner_codes[numbers.starts - 1] != ord("/"))
    face_of_number = np.repeat(np.arange(len(numbers.per_line)), numbers.per_line)
    counts = np.bincount(face_of_number[is_index], minlength=len(numbers.per_line))
    indices = numbers.values[is_index]
    if (indices == 0).any():
        raise InputError(path, "an OBJ face uses vertex index 0 (indices start at 1)")
    if (indices < 0).any():
        # -1 is the last vertex defined before the face's line, not the last in the file.
        defined_before = np.cumsum(is_vertex)[is_face]
        indices = np.where(indices < 0, np.repeat(defined_before, counts) + indices, indices - 1)
    else:
        indices = indices - 1
    n = len(positions)
    faces = triangles_from_polygons(counts, indices, n, path)
    keep, faces = referenced_vertices(faces, n)
    positions = positions[keep]
    if colors is not None:
        colors = colors[keep]
    normals = mesh_normals(positions, faces)
    return PointCloud(positions=positions, normals=normals, colors=colors, faces=faces, source=path)


def _statements(text: bytes, line_starts: np.ndarray, selected: np.ndarray) -> bytes:
    """The selected lines, one per line, with their keyword blanked and comments removed.

    Statements of one kind usually come in long runs of consecutive lines, so the text is
    cut once per run rather than once per line.
    """
    lines = np.flatnonzero(selected)
    run_starts = np.concatenate(([True], np.diff(lines) != 1))
    run_ends = np.concatenate((run_starts[1:], [True]))
    line_ends = np.append(line_starts[1:] - 1, len(text))  # each line's "\n" (or the file end)
    pieces = [text[begin:end] for begin, end in
              zip(line_starts[lines[run_starts]].tolist(), line_ends[lines[run_ends]].tolist(),
                                 strict=True)]
    joined = bytearray(b"\n".join(pieces))
    # Where each selected line starts in `joined`: its run's start, plus its offset in the run.
    run = np.cumsum(run_starts) - 1
    run_offsets = np.cumsum([0] + [len(piece) + 1 for piece in pieces[:-1]])
    offsets = run_offsets[run] + line_starts[lines] - line_starts[lines[run_starts]][run]
    np.frombuffer(joined, dtype=np.uint8)[offsets] = ord(" ")
    return _COMMENT.sub(b"", joined) if b"#" in joined else bytes(joined)
