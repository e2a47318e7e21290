"""Reading PLY point clouds and meshes: `read_ply`.

Bodies in ascii, binary_little_endian and binary_big_endian. The ``vertex`` element gives
the points; its properties, by name:

- ``x y z`` (required, any numeric type; kept as float64);
- ``nx ny nz``: normals. Files whose normals include zero vectors (the "no normal"
  placeholder some exporters write) count as having no normals (`cloud.file_normals`);
- ``red green blue``: colours. 8-bit integer types are divided by 255, 16-bit ones by
  65535, wider integers are read as 0..255 values, floats are taken as they are; all are
  clipped to [0, 1]. ``alpha`` is ignored;
- ``radius``: splat radii; ``ux uy uz vx vy vz``: splat tangent axes;
- every other scalar property is an attribute with the property's type (char .. double as
  int8 .. float64), named as `surfel.attributes.canonical_names` spells it (CloudCompare's
  ``scalar_Intensity`` becomes ``intensity``). A ``comment surfel_attribute NAME DTYPE KIND
  [D1 D2 ...]`` header line (as `write_ply` writes them) states an attribute's numpy dtype,
  kind and per-point shape (D1, D2, ...): it is read from the property NAME, or from
  NAME_0 .. NAME_{D1 D2 ... - 1} in C order, and keeps its name (``comment surfel_extra NAME
  [D1 D2 ...]``, from older versions of surfel, declares a float32 continuous one);
- list properties of the vertex element are skipped.

A ``face`` element with a list property ``vertex_indices`` (or ``vertex_index``) makes the
file a mesh: polygons are fan-triangulated, only the vertices the faces reference are kept,
and vertex normals are area-weighted from the faces unless the file has its own. So does a
``tristrips`` element (Stanford's and VCG's scans, as the Igea statue): its lists are
triangle strips, -1 ending each. Other elements (edges, materials, ...) are skipped. A
``comment surfel_geospatial`` header line marks the cloud geospatial (up axis +Z); each
``comment surfel_sensor X Y Z`` line is one of
the cloud's `sensors`, in order (the integer attribute ``scan`` says whose each point is).

Elements are decoded whole, with no per-point Python loop: binary ones through numpy
structured dtypes over a memory map of the file, ascii ones through one vectorised
tokenisation of the body. The one exception is a binary element with list properties whose
lengths differ between records (e.g. mixed triangles and quads): its record boundaries can
only be found record by record, by the compiled walks of `ply_records`. Every size a header
claims is checked against what the file holds before anything is decoded, so a lying header
cannot cause a large allocation.

`write_ply` (ply_write.py) writes what this reads.
"""

from __future__ import annotations

import mmap
import re
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..attributes import KINDS, AttributeSpec, canonical_names
from ..cloud import PointCloud, file_normals
from ..errors import InputError
from ._parse import numbers_by_line, ragged_arange
from .mesh import mesh_normals, referenced_vertices, triangles_from_polygons, triangles_from_strips
from .ply_records import NEGATIVE, RecordLayout, gather_records, walk_records

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": "ascii", "binary_little_endian": "<", "binary_big_endian": ">"}
_FACE_LISTS = ("vertex_indices", "vertex_index")
MESH_ELEMENTS = ("face", "tristrips")  # polygons; triangle strips
_ATTRIBUTE_COMMENT = "surfel_attribute"
_EXTRA_COMMENT = "surfel_extra"  # older writers' NAME [D1 ...]: float32, continuous
_GEOSPATIAL_COMMENT = "surfel_geospatial"
_SENSOR_COMMENT = "surfel_sensor"
_POSITION = ("x", "y", "z")
_NORMAL = ("nx", "ny", "nz")
_COLOR = ("red", "green", "blue")
_AXES = ("ux", "uy", "uz", "vx", "vy", "vz")
_RESERVED = {*_POSITION, *_NORMAL, *_COLOR, "radius", *_AXES}
_COUNT = re.compile(r"[0-9]+")


@dataclass(frozen=True)
class Property:
    name: str
    type: str  # numpy type code without byte order, e.g. "f4"
    length_type: str | None = None  # set for list properties: numpy code of the length

    @property
    def is_list(self) -> bool:
        return self.length_type is not None


@dataclass
class Element:
    name: str
    count: int
    properties: dict[str, Property] = field(default_factory=dict)


@dataclass
class Header:
    """A parsed PLY header; `parse_header` makes it."""

    format: str  # "ascii", or the byte order ("<" or ">") of a binary body
    elements: list[Element]
    declared: dict[str, AttributeSpec]  # the surfel_attribute comments, by name
    geospatial: bool
    body_offset: int
    sensors: list[tuple[float, float, float]] = field(default_factory=list)


@dataclass(frozen=True)
class VertexAttribute:
    """An attribute of the vertex element: its spec and the properties holding its components
    (C order). `stated` is true where a surfel_attribute comment gave the kind."""

    spec: AttributeSpec
    properties: tuple[str, ...]
    stated: bool


class _List(NamedTuple):
    """A list property of an element: each record's list length, and all items in order."""

    lengths: np.ndarray
    items: np.ndarray


_Columns = dict[str, "np.ndarray | _List"]


def read_ply(path: str) -> PointCloud:
    """Read a PLY point cloud or mesh (see the module docstring); errors raise InputError."""
    with open(path, "rb") as file:
        # Not closed explicitly: the map lives while arrays view it, and a traceback may
        # still hold such views when an error propagates.
        data = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
    header = parse_header(data, path)
    wanted = {"vertex", *MESH_ELEMENTS} & {element.name for element in header.elements}
    if header.format == "ascii":
        found = _read_ascii(data, header, wanted, path)
    else:
        found = _read_binary(data, header, wanted, path)
    return _cloud(header, found, path)


# --- header -----------------------------------------------------------------------------

def parse_header(data: mmap.mmap | bytes, path: str) -> Header:
    """The header at the start of `data` (a memory map, or enough leading bytes of the file);
    InputError for anything that is not a PLY header."""
    if data[:4] not in (b"ply\n", b"ply\r"):
        raise InputError(path, "not a PLY file (it does not start with 'ply')")
    end = data.find(b"\nend_header")
    if end < 0:
        raise InputError(path, "PLY header has no end_header line")
    body = end + len(b"\nend_header")
    if data[body:body + 2] == b"\r\n":
        body += 2
    elif data[body:body + 1] == b"\n":
        body += 1
    elif body != len(data):
        raise InputError(path, "malformed end_header line")

    fmt = None
    elements: list[Element] = []
    declared: dict[str, AttributeSpec] = {}
    geospatial = False
    sensors: list[tuple[float, float, float]] = []
    for line in data[:end].decode("latin-1").splitlines()[1:]:
        words = line.split()
        if not words or words[0] == "obj_info":
            continue
        keyword = words[0]
        if keyword == "comment":
            if words[1:2] == [_GEOSPATIAL_COMMENT]:
                geospatial = True
            elif words[1:2] == [_SENSOR_COMMENT]:
                try:
                    sensors.append(tuple(float(w) for w in words[2:]))
                except ValueError:
                    raise _bad_line(line, path) from None
                if len(sensors[-1]) != 3:
                    raise _bad_line(line, path)
            elif words[1:2] == [_ATTRIBUTE_COMMENT]:
                if len(words) < 5 or words[4] not in KINDS or not all(_COUNT.fullmatch(w) for w in words[5:]):
                    raise _bad_line(line, path)
                try:
                    spec = AttributeSpec.from_json({"name": words[2], "dtype": words[3], "kind": words[4],
                                                    "shape": [int(w) for w in words[5:]]})
                except ValueError:
                    raise _bad_line(line, path) from None
                declared[spec.name] = spec
            elif words[1:2] == [_EXTRA_COMMENT]:
                if len(words) < 3 or not all(_COUNT.fullmatch(w) for w in words[3:]):
                    raise _bad_line(line, path)
                declared[words[2]] = AttributeSpec(words[2], np.dtype(np.float32), tuple(int(w) for w in words[3:]))
        elif keyword == "format":
            if fmt is not None or len(words) != 3 or words[1] not in _FORMATS:
                raise _bad_line(line, path)
            fmt = _FORMATS[words[1]]
        elif keyword == "element":
            if len(words) != 3 or not _COUNT.fullmatch(words[2]):
                raise _bad_line(line, path)
            if any(element.name == words[1] for element in elements):
                raise InputError(path, f"PLY header declares element '{words[1]}' twice")
            elements.append(Element(words[1], int(words[2])))
        elif keyword == "property":
            if not elements:
                raise InputError(path, "PLY header has a property before any element")
            prop = _parse_property(words, line, path)
            if prop.name in elements[-1].properties:
                raise InputError(path, f"PLY element '{elements[-1].name}' declares "
                                       f"property '{prop.name}' twice")
            elements[-1].properties[prop.name] = prop
        else:
            raise _bad_line(line, path)
    if fmt is None:
        raise InputError(path, "PLY header has no format line")
    if not any(element.name == "vertex" for element in elements):
        raise InputError(path, "PLY file has no vertex element")
    return Header(fmt, elements, declared, geospatial, body, sensors)


def _parse_property(words: list[str], line: str, path: str) -> Property:
    if len(words) == 3 and words[1] in _TYPES:
        return Property(words[2], _TYPES[words[1]])
    if (len(words) == 5 and words[1] == "list" and words[2] in _TYPES and words[3] in _TYPES
            and _TYPES[words[2]][0] in "iu"):
        return Property(words[4], _TYPES[words[3]], _TYPES[words[2]])
    raise _bad_line(line, path)


def _bad_line(line: str, path: str) -> InputError:
    return InputError(path, f"bad PLY header line {line.strip()[:60]!r}")


# --- binary body ------------------------------------------------------------------------

def _read_binary(data: mmap.mmap, header: Header, wanted: set[str], path: str) -> dict[str, _Columns]:
    found: dict[str, _Columns] = {}
    offset = header.body_offset
    for element in header.elements:
        if wanted <= found.keys():
            break
        kept = next((name for name in _FACE_LISTS if name in element.properties), None) \
            if element.name in MESH_ELEMENTS else None
        columns, offset = _binary_element(data, offset, element, header.format, kept, path)
        if element.name in wanted:
            found[element.name] = columns
    return found


def _binary_element(data: mmap.mmap, offset: int, element: Element, order: str, kept: str | None,
                    path: str) -> tuple[_Columns, int]:
    """The element's scalar columns and its list `kept` (views into `data` where possible), and
    the offset after it. Other list properties are skipped (nothing reads them)."""
    props = list(element.properties.values())
    n = element.count
    if not props:
        return {}, offset
    smallest = sum(np.dtype(p.length_type or p.type).itemsize for p in props)  # empty lists
    _check_fits(element, n * smallest, len(data) - offset, path)
    codes = np.frombuffer(data, dtype=np.uint8)
    layout = RecordLayout.of(props, order, kept)
    lists = [p for p in props if p.is_list]
    if n and lists:
        # Guess that every record's lists are as long as the first record's (all faces
        # triangles, say): then the element is one fixed-size record array.
        lengths = _first_lengths(codes, offset, props, order, element.name, path)
    else:
        lengths = {p.name: 0 for p in lists}
    dtype = np.dtype([field for p in props for field in record_fields(p, order, lengths)])
    size = n * dtype.itemsize
    if size <= len(data) - offset:
        records = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
        if all((records[_length_field(p)] == lengths[p.name]).all() for p in lists):
            columns: _Columns = {p.name: records[p.name] for p in props if not p.is_list}
            if kept is not None:
                columns[kept] = _List(np.full(n, lengths[kept], dtype=np.int64), records[kept].reshape(-1))
            return columns, offset + size
    # Lists of varying lengths: walked record by record by compiled kernels (ply_records).
    walk = walk_records(codes, offset, n, layout)
    if walk.end < 0:
        raise _walk_error(walk.end, element.name, path)
    scalars, items = gather_records(codes, offset, n, layout, walk)
    columns = {} if scalars is None else {p.name: scalars[p.name] for p in props if not p.is_list}
    if kept is not None:
        item = np.dtype(order + element.properties[kept].type)
        columns[kept] = _List(walk.lengths.astype(np.int64), items.view(item))
    return columns, walk.end


def _first_lengths(codes: np.ndarray, offset: int, props: list[Property], order: str, element: str,
                   path: str) -> dict[str, int]:
    """The list lengths of the record at `offset`."""
    lengths = {}
    for p in props:
        if not p.is_list:
            offset += np.dtype(p.type).itemsize
            continue
        length_type = np.dtype(order + p.length_type)
        if offset + length_type.itemsize > len(codes):
            raise _truncated(element, path)
        length = int(codes[offset:offset + length_type.itemsize].view(length_type)[0])
        if length < 0:
            raise _walk_error(NEGATIVE, element, path)
        lengths[p.name] = length
        offset += length_type.itemsize + length * np.dtype(p.type).itemsize
    return lengths


def record_fields(prop: Property, order: str, lengths: dict[str, int]) -> list[tuple]:
    """The numpy structured-dtype fields of one property in a binary record (a list property:
    its length, then `lengths[name]` items)."""
    if prop.length_type is None:
        return [(prop.name, order + prop.type)]
    return [(_length_field(prop), order + prop.length_type),
            (prop.name, order + prop.type, (lengths[prop.name],))]


def _length_field(prop: Property) -> str:
    return f"{prop.name} length"  # PLY names have no spaces, so this never collides


def _walk_error(code: int, element: str, path: str) -> InputError:
    if code == NEGATIVE:
        return InputError(path, f"PLY element '{element}' has a list of negative length")
    return _truncated(element, path)


def _check_fits(element: Element, need: int, have: int, path: str) -> None:
    if need > have:
        raise InputError(path, f"PLY file is truncated: element '{element.name}' "
                               f"({element.count} records) needs at least {need} bytes, "
                               f"{max(have, 0)} remain")


def _truncated(element: str, path: str) -> InputError:
    return InputError(path, f"PLY file is truncated inside element '{element}'")


# --- ascii body -------------------------------------------------------------------------

def _read_ascii(data: mmap.mmap, header: Header, wanted: set[str], path: str) -> dict[str, _Columns]:
    values, per_line, _ = numbers_by_line(data[header.body_offset:], np.float64, path)
    counts = per_line[per_line > 0]  # one record per non-blank line
    firsts = np.cumsum(counts) - counts
    found: dict[str, _Columns] = {}
    record = 0
    for element in header.elements:
        if wanted <= found.keys():
            break
        n = element.count if element.properties else 0  # an element without properties has no lines
        if n > len(counts) - record:
            raise InputError(path, f"PLY file is truncated: element '{element.name}' has {n} "
                                   f"records but only {len(counts) - record} lines remain")
        if element.name in wanted:
            found[element.name] = _ascii_element(values, firsts[record:record + n],
                                                 counts[record:record + n], element, path)
        record += n
    return found


def _ascii_element(values: np.ndarray, firsts: np.ndarray, counts: np.ndarray,
                   element: Element, path: str) -> _Columns:
    """Columns of an element from its lines, walking all lines' properties at once."""
    position = firsts.copy()
    end = firsts + counts
    columns: _Columns = {}
    for prop in element.properties.values():
        if (position >= end).any():
            raise _wrong_count(element, path)
        if not prop.is_list:
            columns[prop.name] = values[position]
            position = position + 1
            continue
        lengths = values[position]
        position = position + 1
        if not ((lengths >= 0) & (lengths <= end - position) & (lengths == np.round(lengths))).all():
            raise _wrong_count(element, path)
        lengths = lengths.astype(np.int64)
        columns[prop.name] = _List(lengths, values[np.repeat(position, lengths) + ragged_arange(lengths)])
        position = position + lengths
    if (position != end).any():
        raise _wrong_count(element, path)
    return columns


def _wrong_count(element: Element, path: str) -> InputError:
    return InputError(path, f"PLY element '{element.name}': a line does not match its properties")


# --- building the cloud -----------------------------------------------------------------

def _cloud(header: Header, found: dict[str, _Columns], path: str) -> PointCloud:
    vertex = next(element for element in header.elements if element.name == "vertex")
    columns = found["vertex"]

    def stacked(names: tuple[str, ...], dtype: type = np.float32) -> np.ndarray | None:
        if any(name in vertex.properties and vertex.properties[name].is_list for name in names):
            raise InputError(path, f"PLY vertex properties {' '.join(names)} must not be lists")
        present = [columns.get(name) for name in names]
        arrays = [column for column in present if isinstance(column, np.ndarray)]
        return np.column_stack(arrays).astype(dtype) if len(arrays) == len(names) else None

    positions = stacked(_POSITION, np.float64)
    if positions is None:
        raise InputError(path, "PLY vertex element lacks x, y or z")
    n = len(positions)
    normals = file_normals(stacked(_NORMAL))
    colors = stacked(_COLOR)
    if colors is not None:
        scale = [color_scale(vertex.properties[name].type) for name in _COLOR]
        colors = np.clip(colors / scale, 0.0, 1.0)
    radius = stacked(("radius",))
    radii = None if radius is None else radius[:, 0]
    axes = stacked(_AXES)
    if axes is not None:
        axes = axes.reshape(n, 2, 3)
    layout = vertex_layout(header, path)
    attributes = vertex_attributes(layout, columns, n, path)

    faces = _faces(found, n, path)
    if faces is not None:
        keep, faces = referenced_vertices(faces, n)
        if len(keep) < n:
            positions = positions[keep]
            normals, colors, radii, axes = (
                None if a is None else a[keep] for a in (normals, colors, radii, axes))
            attributes = {name: value[keep] for name, value in attributes.items()}
        if normals is None:
            normals = mesh_normals(positions, faces)
    return PointCloud(positions=positions, normals=normals, colors=colors, radii=radii, axes=axes,
                      faces=faces, attributes=attributes,
                      kinds={a.spec.name: a.spec.kind for a in layout if a.stated},
                      geospatial=header.geospatial, source=path,
                      sensors=np.array(header.sensors) if header.sensors else None)


def _faces(found: dict[str, _Columns], n: int, path: str) -> np.ndarray | None:
    """The triangles of the face and tristrips elements, or None where the file has neither."""
    triangles = []
    for element in MESH_ELEMENTS:
        columns = found.get(element, {})
        lists = [column for name in _FACE_LISTS if isinstance(column := columns.get(name), _List)]
        if not lists or not len(lists[0].lengths):
            continue
        items = lists[0].items
        if element == "face":
            triangles.append(triangles_from_polygons(lists[0].lengths, items, n, path))
        else:  # each list one or more strips: a -1 after each list ends its last
            ends = np.cumsum(lists[0].lengths)
            triangles.append(triangles_from_strips(np.insert(items, ends, -1), n, path))
    triangles = [t for t in triangles if len(t)]  # strips may make none (all stitching)
    return np.concatenate(triangles) if triangles else None


def vertex_layout(header: Header, path: str) -> list[VertexAttribute]:
    """The attributes of the vertex element (module docstring), in property order."""
    vertex = next(element for element in header.elements if element.name == "vertex")
    props = vertex.properties
    layout, used = [], set()
    for spec in header.declared.values():
        size = spec.components
        # Compare with the property count first: a comment must not make us build huge name lists.
        names = None
        if size <= len(props):
            names = (spec.name,) if not spec.shape else tuple(f"{spec.name}_{i}" for i in range(size))
        if names is None or not all(name in props and not props[name].is_list for name in names):
            raise InputError(path, f"PLY header declares attribute '{spec.name}' but its vertex properties "
                                   f"are missing")
        layout.append(VertexAttribute(spec, names, True))
        used.update(names)
    rest = [name for name, prop in props.items()
            if name not in _RESERVED and name not in used and not prop.is_list]
    taken = {*header.declared, *_RESERVED}
    for name, prop in zip(canonical_names(rest, taken=taken), (props[p] for p in rest), strict=True):
        layout.append(VertexAttribute(AttributeSpec(name, np.dtype(prop.type)), (prop.name,), False))
    return layout


def vertex_attributes(layout: list[VertexAttribute], columns, n: int, path: str) -> dict[str, np.ndarray]:
    """The attributes of `layout` from the vertex columns (name -> (n,) array: decoded records,
    or the float64 numbers of an ascii body), each in its spec's dtype and shape."""
    attributes = {}
    for item in layout:
        spec = item.spec
        values = (np.column_stack([columns[name] for name in item.properties]) if spec.shape
                  else columns[item.properties[0]])
        converted = values.astype(spec.dtype)
        if spec.dtype.kind in "biu" and values.dtype != spec.dtype and not np.array_equal(converted, values):
            raise InputError(path, f"PLY attribute '{spec.name}' holds values that are not {spec.dtype}")
        attributes[spec.name] = converted.reshape(n, *spec.shape)
    return attributes


def color_scale(code: str) -> float:
    """What a colour property of PLY type `code` is divided by to lie in [0, 1]."""
    if code[0] == "f":
        return 1.0
    return 65535.0 if code[1] == "2" else 255.0
