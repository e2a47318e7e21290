"""NumPy .npz point clouds: `read_npz`.

Arrays, by key:

- ``positions`` (or ``points``, or ``xyz``): (N, 3), required;
- ``normals`` (N, 3) (with zero vectors among them: none, `cloud.file_normals`); ``radii``
  (N,); ``axes`` (N, 2, 3);
- ``colors`` (N, 3): floats in [0, 1], or integers: 0..65535 for 16-bit types, 0..255 for
  the others (uint8 above all);
- ``faces`` (F, 3) integer vertex indices. An NPZ is a container for a cloud, not a mesh
  format, so faces are kept as stored: no vertices dropped, no normals computed;
- ``geospatial``: an optional boolean scalar (as LOD files store it) marking the cloud
  geospatial (up axis +Z);
- any other numeric array whose first dimension is N becomes ``attributes[key]``, in its own
  dtype; anything else (other scalars, metadata) is ignored, except under the names of
  surfel's own arrays (`surfel.attributes.DERIVED`: LOD errors, clip lines, normal fields),
  which must have their own shape;
- ``surfel_schema``: an optional string scalar, the JSON of the attributes' schema
  (`surfel.attributes.Schema.to_json`), giving the kinds of the attributes it names.

`cloud_arrays` gives the arrays of a cloud in this layout (what `np.savez` needs to write it).

Pickles are never loaded: arrays are read with ``allow_pickle=False``, and an object array
is refused with InputError before numpy reads it.

Allocations are bounded by what the archive can hold. Every member's .npy header is read
first (a few decompressed bytes) and checked against the member's sizes in the archive, so a
crafted shape cannot make numpy allocate more than the member holds; only the arrays this
layout uses are then decompressed, streamed into their arrays. Deflate can expand data about
1000 times, so a 1 MB archive may honestly hold a gigabyte of zeros; point data never
compresses like that (measured with np.savez_compressed: aerial LiDAR with all its fields
4 times, a perfect integer grid in float64 13 times, with constant normals and colours 21),
so the arrays read may together expand at most MAX_EXPANSION times their compressed size
(beyond SMALL_ARRAYS bytes, which any file may hold): more is a decompression bomb.
"""

from __future__ import annotations

import math
import os
import zipfile

import numpy as np

from ..attributes import DERIVED, Schema
from ..cloud import PointCloud, file_normals
from ..errors import InputError, SurfelError

_POSITION_KEYS = ("positions", "points", "xyz")
_ATTRIBUTE_KEYS = {"normals", "colors", "radii", "axes", "faces"}
SCHEMA_KEY = "surfel_schema"
GEOSPATIAL_KEY = "geospatial"
# Deflate cannot expand data more than about 1032 times.
_DEFLATE_EXPANSION = 1100
MAX_EXPANSION = 64  # how much the arrays read may expand, together (module docstring)
SMALL_ARRAYS = 16 << 20
_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0,
                   (2, 0): np.lib.format.read_array_header_2_0}


def read_npz(path: str) -> PointCloud:
    """Read an NPZ point cloud (see the module docstring); errors raise InputError."""
    try:
        arrays = _read_arrays(path)
    except InputError:
        raise
    except Exception as error:  # zipfile, its decompressors and numpy raise many types for damaged archives
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        raise InputError(path, f"cannot read NPZ: {message}") from error
    for key, value in arrays.items():
        if value.dtype.kind not in "biuf" and (key in _ATTRIBUTE_KEYS or key in _POSITION_KEYS):
            raise InputError(path, f"NPZ array '{key}' is not numeric ({value.dtype})")
    position_key = next((key for key in _POSITION_KEYS if key in arrays), None)
    if position_key is None:
        raise InputError(path, "NPZ has no 'positions' array")
    positions = arrays[position_key]
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise InputError(path, f"NPZ positions must have shape (N, 3), got {positions.shape}")
    n = len(positions)
    colors = arrays.get("colors")
    if colors is not None and colors.dtype.kind in "iu":
        colors = colors / (65535.0 if colors.dtype.itemsize == 2 else 255.0)
    faces = arrays.get("faces")
    if faces is not None and faces.dtype.kind not in "iu":
        raise InputError(path, f"NPZ faces must be integers, got {faces.dtype}")
    flag = arrays.get(GEOSPATIAL_KEY)
    geospatial = flag is not None and flag.shape == () and flag.dtype.kind in "biu" and bool(flag)
    attributes = {key: value for key, value in arrays.items()
                  if key not in _ATTRIBUTE_KEYS and key not in _POSITION_KEYS
                  and (key in DERIVED or value.dtype.kind in "biuf" and value.ndim >= 1 and len(value) == n)}
    kinds = {}
    stated = arrays.get(SCHEMA_KEY)
    if stated is not None:
        try:
            if stated.shape != () or stated.dtype.kind != "U":
                raise ValueError("not a string")
            kinds = {name: kind for name, kind in Schema.from_json(str(stated)).kinds.items() if name in attributes}
        except ValueError as error:
            raise InputError(path, f"NPZ '{SCHEMA_KEY}' is not an attribute schema: {error}") from None
    normals = arrays.get("normals")
    if normals is not None and normals.ndim == 2:
        normals = file_normals(normals)
    return PointCloud(positions=positions, normals=normals, colors=colors,
                      radii=arrays.get("radii"), axes=arrays.get("axes"), faces=faces,
                      attributes=attributes, kinds=kinds, geospatial=geospatial, source=path)


def cloud_arrays(cloud: PointCloud) -> dict[str, np.ndarray]:
    """The arrays of `cloud` by NPZ key (module docstring); SurfelError for an attribute whose
    name this layout gives another meaning."""
    arrays = {"positions": cloud.positions, GEOSPATIAL_KEY: np.bool_(cloud.geospatial),
              SCHEMA_KEY: np.str_(cloud.schema.to_json())}
    for key in ("normals", "colors", "radii", "axes", "faces"):
        if getattr(cloud, key) is not None:
            arrays[key] = getattr(cloud, key)
    for name, values in cloud.attributes.items():
        if name in arrays or name in _POSITION_KEYS:
            raise SurfelError(f"attribute {name!r} cannot be stored in an NPZ: the layout gives the name "
                              f"another meaning")
        arrays[name] = values
    return arrays


def _read_arrays(path: str) -> dict[str, np.ndarray]:
    """The arrays of the archive that this layout uses (module docstring), by key."""
    size = os.path.getsize(path)
    with zipfile.ZipFile(path) as archive:
        members = {}
        for info in archive.infolist():
            if not info.filename.endswith(".npy"):
                continue  # numpy writes only .npy members; anything else is not ours
            key = info.filename[:-len(".npy")]
            if (info.header_offset + info.compress_size > size
                    or info.file_size > _DEFLATE_EXPANSION * max(info.compress_size, 1)):
                raise InputError(path, f"NPZ member '{key}' claims more data than the file holds")
            with archive.open(info) as member:
                read_header = _HEADER_READERS.get(np.lib.format.read_magic(member))
                if read_header is None:
                    raise InputError(path, f"NPZ array '{key}' has an unsupported .npy version")
                shape, _, dtype = read_header(member)
            if dtype.hasobject:
                raise InputError(path, f"NPZ array '{key}' holds Python objects, which are "
                                       f"never unpickled")
            if math.prod(shape) * dtype.itemsize > info.file_size:
                raise InputError(path, f"NPZ array '{key}' is truncated")
            members[key] = (info, shape, dtype)
        used = _used_members(members)
        expanded = sum(math.prod(shape) * dtype.itemsize for _, shape, dtype in used.values())
        compressed = sum(info.compress_size for info, _, _ in used.values())
        if expanded > max(SMALL_ARRAYS, MAX_EXPANSION * compressed):
            raise InputError(path, f"NPZ arrays would expand {compressed} compressed bytes {expanded // compressed} "
                                   f"times, far beyond what point data compresses (at most {MAX_EXPANSION} times): "
                                   "a decompression bomb")
        arrays = {}
        for key, (info, _, _) in used.items():
            with archive.open(info) as member:  # read in pieces into the array numpy allocates
                arrays[key] = np.lib.format.read_array(member, allow_pickle=False)
    return arrays


def _used_members(members: dict[str, tuple]) -> dict[str, tuple]:
    """The members `read_npz` reads (module docstring), from their (info, shape, dtype)."""
    position_key = next((key for key in _POSITION_KEYS if key in members), None)
    if position_key is None:
        return {}
    shape = members[position_key][1]
    n = shape[0] if shape else None
    used = {}
    for key, member in members.items():
        _, shape, dtype = member
        scalar = shape == () and key in (GEOSPATIAL_KEY, SCHEMA_KEY)
        attribute = key not in _POSITION_KEYS and len(shape) >= 1 and shape[0] == n and dtype.kind in "biuf"
        if key == position_key or key in _ATTRIBUTE_KEYS or key in DERIVED or scalar or attribute:
            used[key] = member  # geometry and surfel's own arrays whatever their shape: PointCloud reports it
    return used
