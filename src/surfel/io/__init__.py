"""Reading point clouds and meshes from files, and writing them as PLY.

`load` picks a reader by file extension (case-insensitive) or by an explicit `format`:

- ``.ply``: `surfel.io.ply` (ascii and binary, points or meshes; written by `surfel.io.ply_write`)
- ``.obj``: `surfel.io.obj` (meshes, or bare vertex lists)
- ``.stl``: `surfel.io.stl` (binary and ASCII meshes)
- ``.off``: `surfel.io.off` (text meshes and point sets)
- ``.las``, ``.laz``: `surfel.io.las` (LiDAR; the cloud is marked geospatial)
- ``.e57``: `surfel.io.e57` (terrestrial scans, merged by their poses; geospatial)
- ``.xyz``, ``.pts``, ``.txt``: `surfel.io.text` (one point per line)
- ``.npz``: `surfel.io.npz` (arrays by name; never unpickles)

Every problem with an input file raises `surfel.errors.InputError` naming the file.
`write_ply` writes everything a `PointCloud` holds, so `load` gives it back.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from .e57 import read_e57
from .las import read_las
from .mesh import area_weighted_vertex_normals
from .npz import read_npz
from .obj import read_obj
from .off import read_off
from .ply import read_ply
from .ply_write import write_ply
from .stl import read_stl
from .text import read_text

__all__ = ["load", "write_ply", "area_weighted_vertex_normals", "FORMATS"]

_READERS: dict[str, Callable[[str], PointCloud]] = {
    "ply": read_ply, "obj": read_obj, "stl": read_stl, "off": read_off,
    "las": read_las, "laz": read_las, "e57": read_e57,
    "xyz": read_text, "pts": read_text, "txt": read_text, "npz": read_npz,
}
FORMATS = tuple(_READERS)  # the accepted extensions and `format` names


def load(path: str | os.PathLike, *, format: str | None = None) -> PointCloud:
    """Read the point cloud or mesh at `path`.

    `format` (one of `FORMATS`) overrides the file extension. The cloud's `source` is
    `str(path)`. Raises InputError, naming the file, for anything that prevents reading it.
    """
    name = os.fspath(path)
    try:
        info = os.stat(name)
    except FileNotFoundError:
        raise InputError(name, "no such file") from None
    except OSError as error:
        raise InputError(name, f"cannot read: {error.strerror or error}") from None
    if stat.S_ISDIR(info.st_mode):
        raise InputError(name, "is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise InputError(name, "is not a regular file")
    if format is not None:
        kind = format.lower().lstrip(".")
        if kind not in _READERS:
            raise InputError(name, f"unknown format {format!r} (known: {', '.join(FORMATS)})")
    else:
        kind = os.path.splitext(name)[1].lower().lstrip(".")
        if kind not in _READERS:
            what = f"extension '.{kind}'" if kind else "no file extension"
            raise InputError(name, f"unknown format: {what} (known: {', '.join(FORMATS)})")
    if info.st_size == 0:
        raise InputError(name, "file is empty")
    try:
        # Absurd values (say 1e300 coordinates) can overflow in normal computations; the
        # cloud's validation reports what matters, so numpy's warnings would only be noise.
        with np.errstate(over="ignore", invalid="ignore"):
            return _READERS[kind](name)
    except OSError as error:
        raise InputError(name, f"cannot read: {error.strerror or error}") from error
    except MemoryError:
        raise InputError(name, f"out of memory reading its {info.st_size} bytes") from None
