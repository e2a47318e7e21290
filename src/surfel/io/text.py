"""Plain-text point lists (.xyz, .pts, .txt): `read_text`.

One point per line, numbers separated by whitespace or commas. Blank lines and lines
starting with ``#`` are skipped. A first line holding a single integer is a point count (as
PTS files start with) and must match the number of point lines. The meaning of the columns
follows from how many each line has (all lines must have the same number):

- 3: ``x y z``
- 4: ``x y z intensity`` (intensity ignored)
- 6: ``x y z nx ny nz`` or ``x y z r g b``: normals if some value is negative or every row
  has unit length (within 1 %), colours otherwise
- 7: ``x y z intensity r g b`` (the Leica PTS layout, the common 7-column one whatever the
  extension; intensity ignored)
- 9: ``x y z nx ny nz r g b``, or ``x y z r g b nx ny nz`` when only the second triple
  looks like normals by the 6-column rule

Colours are 0..1 floats, or 0..255 integers when a value exceeds 1 (0..65535 when one
exceeds 255). Normals that include zero vectors count as absent.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ._parse import numbers_by_line, unit_colors

_COMMENT = re.compile(rb"^[ \t]*#[^\n]*", re.MULTILINE)


def read_text(path: str) -> PointCloud:
    """Read an XYZ/PTS/TXT point list (see the module docstring); errors raise InputError."""
    # Blanking comments keeps line numbers right for error messages.
    text = _COMMENT.sub(b"", Path(path).read_bytes()).replace(b",", b" ")
    values, per_line, _ = numbers_by_line(text, np.float64, path)
    lines = np.flatnonzero(per_line)
    counts = per_line[lines]
    declared = None
    if len(counts) and counts[0] == 1:
        declared, values, lines, counts = values[0], values[1:], lines[1:], counts[1:]
    if not len(counts):
        raise InputError(path, "no points")
    columns = int(counts[0])
    wrong = np.flatnonzero(counts != columns)
    if len(wrong):
        line = int(lines[wrong[0]])
        raise InputError(path, f"line {line + 1} has {per_line[line]} values, "
                               f"line {lines[0] + 1} has {columns}")
    table = values.reshape(-1, columns)
    if declared is not None and declared != len(table):
        raise InputError(path, f"the first line says {declared:g} points but there are {len(table)}")

    normals = colors = None
    if columns == 6:
        if _looks_like_normals(table[:, 3:6]):
            normals = table[:, 3:6]
        else:
            colors = table[:, 3:6]
    elif columns == 7:
        colors = table[:, 4:7]
    elif columns == 9:
        if _looks_like_normals(table[:, 6:9]) and not _looks_like_normals(table[:, 3:6]):
            colors, normals = table[:, 3:6], table[:, 6:9]
        else:
            normals, colors = table[:, 3:6], table[:, 6:9]
    elif columns not in (3, 4):
        raise InputError(path, f"{columns} values per line; expected 3, 4, 6, 7 or 9")
    if normals is not None and not np.linalg.norm(normals, axis=1).all():
        normals = None
    return PointCloud(positions=table[:, :3], normals=normals,
                      colors=None if colors is None else unit_colors(colors), source=path)


def _looks_like_normals(triple: np.ndarray) -> bool:
    """Colours are never negative, and rarely all of unit length."""
    return bool((triple < 0).any() or np.allclose(np.linalg.norm(triple, axis=1), 1.0, atol=0.01))
