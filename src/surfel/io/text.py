"""Plain-text point lists (.xyz, .pts, .txt): `read_text`.

One point per line, numbers separated by whitespace or commas. Blank lines and lines
starting with ``#`` are skipped. A first line holding a single integer is a point count (as
PTS files start with) and must match the number of point lines. All lines must have the
same number of values.

A header line names the columns: the first line that is neither blank nor a ``#`` comment,
when it starts with ``//`` (as CloudCompare writes, ``//X Y Z R G B Intensity``) or holds
only words (``x y z intensity classification``). Names are matched ignoring case: ``x y z``
(required), ``nx ny nz`` normals, ``r g b``, ``red green blue`` or ``rf gf bf`` colours; every
other column is an attribute, named as `surfel.attributes.canonical_names` spells it
(``Intensity`` becomes ``intensity``), int32 when all its values are whole numbers that fit,
float64 otherwise.

Without a header, the meaning of the columns follows from how many each line has:

- 3: ``x y z``
- 4: ``x y z intensity``
- 6: ``x y z nx ny nz`` or ``x y z r g b``: normals if some value is negative or every row
  has unit length (within 1 %), colours otherwise
- 7: ``x y z intensity r g b`` (the Leica PTS layout, the common 7-column one whatever the
  extension)
- 9: ``x y z nx ny nz r g b``, or ``x y z r g b nx ny nz`` when only the second triple
  looks like normals by the 6-column rule

Colours are 0..1 floats, or 0..255 integers when a value exceeds 1 (0..65535 when one
exceeds 255). Normals that include zero vectors count as absent.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..attributes import canonical_names
from ..cloud import PointCloud, file_normals
from ..errors import InputError
from ._parse import numbers_by_line, unit_colors

_COMMENT = re.compile(rb"^[ \t]*#[^\n]*", re.MULTILINE)
_FIRST_LINE = re.compile(rb"^[ \t\r]*([^\s#][^\n]*)", re.MULTILINE)
_WORD = re.compile(r"[A-Za-z_][^\s,]*")
_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?|[-+]?(nan|inf|infinity)", re.IGNORECASE)
# Header names of the geometry columns, in their compact form (lower case, letters and digits).
_TRIPLES = {"positions": (("x", "y", "z"),),
            "normals": (("nx", "ny", "nz"), ("normalx", "normaly", "normalz")),
            "colors": (("r", "g", "b"), ("red", "green", "blue"), ("rf", "gf", "bf"))}


def read_text(path: str) -> PointCloud:
    """Read an XYZ/PTS/TXT point list (see the module docstring); errors raise InputError."""
    # Blanking comments keeps line numbers right for error messages.
    text = _COMMENT.sub(b"", Path(path).read_bytes())
    names = None
    first = _FIRST_LINE.search(text)
    if first is not None:
        names = _header(first.group(1).decode("latin-1"))
        if names is not None:  # blanked, like a comment
            text = text[:first.start(1)] + b" " * len(first.group(1)) + text[first.end(1):]
    text = text.replace(b",", b" ")
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
    if names is not None:
        return _named_columns(table, names, path)

    normals = colors = intensity = None
    if columns == 4:
        intensity = table[:, 3]
    elif columns == 6:
        if _looks_like_normals(table[:, 3:6]):
            normals = table[:, 3:6]
        else:
            colors = table[:, 3:6]
    elif columns == 7:
        intensity, colors = table[:, 3], table[:, 4:7]
    elif columns == 9:
        if _looks_like_normals(table[:, 6:9]) and not _looks_like_normals(table[:, 3:6]):
            colors, normals = table[:, 3:6], table[:, 6:9]
        else:
            normals, colors = table[:, 3:6], table[:, 6:9]
    elif columns != 3:
        raise InputError(path, f"{columns} values per line; expected 3, 4, 6, 7 or 9")
    if normals is not None and not np.linalg.norm(normals, axis=1).all():
        normals = None
    attributes = {} if intensity is None else {"intensity": _column(intensity)}
    return PointCloud(positions=table[:, :3], normals=file_normals(normals), attributes=attributes,
                      colors=None if colors is None else unit_colors(colors), source=path)


def _header(line: str) -> list[str] | None:
    """The column names of a header line, or None when `line` is data."""
    body = line[2:] if line.startswith("//") else line
    words = [word for word in re.split(r"[\s,]+", body.strip()) if word]
    if not words:
        return None
    if line.startswith("//") or all(_WORD.fullmatch(w) and not _NUMBER.fullmatch(w) for w in words):
        return words
    return None


def _named_columns(table: np.ndarray, names: list[str], path: str) -> PointCloud:
    """The cloud of a table whose columns a header names (module docstring)."""
    if len(names) != table.shape[1]:
        raise InputError(path, f"the header names {len(names)} columns but lines have {table.shape[1]} values")
    compact = [re.sub(r"[^0-9a-z]", "", name.lower()) for name in names]
    found = {}
    for field, spellings in _TRIPLES.items():
        for triple in spellings:
            if set(triple) <= set(compact):
                found[field] = [compact.index(name) for name in triple]
                break
    if "positions" not in found:
        raise InputError(path, f"the header names no x, y and z columns: {' '.join(names)[:80]}")
    normals = table[:, found["normals"]] if "normals" in found else None
    if normals is not None and not np.linalg.norm(normals, axis=1).all():
        normals = None
    colors = unit_colors(table[:, found["colors"]]) if "colors" in found else None
    used = {index for indices in found.values() for index in indices}
    rest = [index for index in range(len(names)) if index not in used]
    attribute_names = canonical_names([names[index] for index in rest])
    if len(set(attribute_names)) < len(attribute_names):
        raise InputError(path, "the header names a column twice")
    attributes = {name: _column(table[:, index]) for name, index in zip(attribute_names, rest, strict=True)}
    return PointCloud(positions=table[:, found["positions"]], normals=file_normals(normals), colors=colors,
                      attributes=attributes, source=path)


def _column(values: np.ndarray) -> np.ndarray:
    """int32 when every value is a whole number that fits, else float64 as read."""
    info = np.iinfo(np.int32)
    if np.isfinite(values).all() and (values == np.round(values)).all() \
            and values.min() >= info.min and values.max() <= info.max:
        return values.astype(np.int32)
    return values


def _looks_like_normals(triple: np.ndarray) -> bool:
    """Colours are never negative, and rarely all of unit length."""
    return bool((triple < 0).any() or np.allclose(np.linalg.norm(triple, axis=1), 1.0, atol=0.01))
