"""Point-cloud files read chunk by chunk, for the out-of-core build (outofcore.py).

Binary PLY is read at file offsets (one structured record per vertex, `surfel.io.ply`'s
header and layout), LAS/LAZ through laspy's chunk iterator (`surfel.io.las`'s layout); other
formats, and PLY meshes or ascii bodies, are loaded whole. A directory of such tiles reads as
one cloud. Each chunk carries positions, normals and colours where the input has them, and
every attribute the readers keep: the same fields `surfel.io.load` gives, chunk by chunk.

Attribute kinds (surfel.attributes) must be the same for every partition, so they are
decided for the whole input, not per chunk: a kind the file states (a surfel_attribute PLY
comment, a surfel LAS VLR) or a known name's kind, else by `KindVote` over every chunk of
the scan pass (an integer or bool scalar attribute with at most MAX_CATEGORIES distinct
values in the whole input is categorical).
"""

from __future__ import annotations

import math
import os
import queue
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from ..attributes import CATEGORICAL, CONTINUOUS, DERIVED, MAX_CATEGORIES, AttributeSpec, known_name, resolve_kind
from ..cloud import corners, file_normals
from ..errors import InputError, SurfelError, points_have

# points read and binned at once: a chunk's arrays (about 200 bytes a point) are memory the
# process touches for the first time, which costs more than the binning itself (with huge
# pages, before pages.py, 2M-point chunks: 4.7-4.9 s per worker binning 10M points, 3 s of it
# on the first chunk; 500k: 1.6 s)
CHUNK_POINTS = 500_000
READ_AHEAD = 1  # chunks read ahead of the one processed (read_ahead)


@dataclass
class Chunk:
    """Consecutive input points: positions (m, 3) float64, normals (m, 3) float32 or None,
    colours (m, 3) float32 in [0, 1] or None, attributes by name (m, ...)."""

    positions: np.ndarray
    normals: np.ndarray | None
    colors: np.ndarray | None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Summary:
    """What the scan pass of the out-of-core build takes from a chunk: its corners lo, hi, every
    stride-th position from its first (float64), whether its normals hold a zero placeholder
    (cloud.file_normals), its attributes, its largest colour value (LAS, before scaling; else
    0) and its point count."""

    lo: np.ndarray
    hi: np.ndarray
    sample: np.ndarray
    zero_normals: bool
    attributes: dict[str, np.ndarray]
    color_max: float
    count: int


def summarise(chunk: Chunk, stride: int, kind: str) -> Summary:
    """The Summary of a chunk read whole, of an input of `kind`."""
    lo, hi = corners(chunk.positions)
    return Summary(lo, hi, chunk.positions[::stride].copy(),
                   chunk.normals is not None and file_normals(chunk.normals) is None, chunk.attributes,
                   float(chunk.colors.max()) if chunk.colors is not None and kind == "las" else 0.0,
                   len(chunk.positions))


@numba.njit(cache=True)
def _summarise_ply(x, y, z, nx, ny, nz, has_normals, stride):  # pragma: no cover - compiled
    """(lo, hi, sample, finite, zero) of Summary from a PLY chunk's columns, in one pass: the
    positions as float64 and the normals as float32, as `StreamInput.ply_chunks` converts them;
    finite: every such value is (else the chunk is refused, as `checked` refuses it)."""
    n = len(x)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    sample = np.empty(((n + stride - 1) // stride, 3))
    finite = True
    zero = False
    for i in range(n):
        p = (np.float64(x[i]), np.float64(y[i]), np.float64(z[i]))
        for a in range(3):
            finite = finite and math.isfinite(p[a])
            lo[a] = min(lo[a], p[a])
            hi[a] = max(hi[a], p[a])
            if i % stride == 0:
                sample[i // stride, a] = p[a]
        if has_normals:
            u, v, w = np.float32(nx[i]), np.float32(ny[i]), np.float32(nz[i])
            finite = finite and math.isfinite(u) and math.isfinite(v) and math.isfinite(w)
            zero = zero or (u == 0 and v == 0 and w == 0)
    return lo, hi, sample, finite, zero


@dataclass
class StreamInput:
    """One input file, read chunk by chunk. specs: its attributes (name, dtype, shape; the
    kind only where `stated`)."""

    path: str
    kind: str  # "ply" (binary, read at offsets), "las" (laspy chunks), "whole" (io.load)
    count: int
    has_normals: bool
    has_colors: bool
    geospatial: bool
    specs: list[AttributeSpec]
    stated: set[str]
    offset: int = 0
    dtype: np.dtype | None = None
    color_scale: float = 1.0
    layout: object = None  # the io reader's layout of the fields (PLY vertex layout, LasLayout)

    def chunks(self, size: int = CHUNK_POINTS) -> Iterator[Chunk]:
        if self.kind == "ply":
            yield from self.ply_chunks(size)
        elif self.kind == "las":
            yield from self._las_chunks(size)
        else:
            from ..io import load

            cloud = load(self.path)
            for start in range(0, len(cloud), size):
                part = slice(start, start + size)
                yield Chunk(cloud.positions[part], None if cloud.normals is None else cloud.normals[part],
                            None if cloud.colors is None else cloud.colors[part],
                            {name: values[part] for name, values in cloud.attributes.items()})

    def ply_chunks(self, size: int, first: int = 0, stop: int | None = None) -> Iterator[Chunk]:
        """Chunks first..stop - 1 (all by default) of `size` points of a binary PLY (`_ply_records`)."""
        from ..io.ply import vertex_attributes

        for records in self._ply_records(size, first, stop):
            m = len(records)
            positions = np.empty((m, 3))  # converted as copied: one pass, not two
            for axis, name in enumerate("xyz"):
                positions[:, axis] = records[name]
            normals = None
            if self.has_normals:  # likewise (a column stack, then a cast, copied twice)
                normals = np.empty((m, 3), np.float32)
                for axis, name in enumerate(("nx", "ny", "nz")):
                    normals[:, axis] = records[name]
            colors = None
            if self.has_colors:
                rgb = np.column_stack([records[c] for c in ("red", "green", "blue")]).astype(np.float32)
                colors = np.clip(rgb / self.color_scale, 0.0, 1.0)
            attributes = vertex_attributes(self.layout, records, m, self.path)
            yield checked(self.path, positions, normals, colors, attributes)

    def ply_summaries(self, stride: int, size: int = CHUNK_POINTS) -> Iterator[Summary]:
        """The Summary of each chunk of `size` points of a binary PLY, its positions and normals
        summarised in one compiled pass over its records, not converted (several passes)."""
        from ..io.ply import vertex_attributes

        for index, records in enumerate(self._ply_records(size)):
            m = len(records)
            normals = [records[c] for c in ("nx", "ny", "nz")] if self.has_normals else [records["x"]] * 3
            lo, hi, sample, finite, zero = _summarise_ply(records["x"], records["y"], records["z"], *normals,
                                                          self.has_normals, stride)
            attributes = vertex_attributes(self.layout, records, m, self.path)
            if not finite or any(values.dtype.kind == "f" and not np.isfinite(values).all()
                                 for values in attributes.values()):
                next(self.ply_chunks(size, index, index + 1))  # refused there, with what is wrong
            yield Summary(lo, hi, sample, zero, attributes, 0.0, m)

    def _ply_records(self, size: int, first: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        """The raw records of chunks first..stop - 1 (all by default) of `size` points of a
        binary PLY, each read at its offset (so that processes may read parts of one file in
        parallel); a short read is refused as a truncated body."""
        # plain reads, not a memory map of the whole file: mapped pages would count as
        # resident memory until unmapped, growing with the file
        end = self.count if stop is None else min(self.count, stop * size)
        with open(self.path, "rb") as file:
            for start in range(first * size, end, size):
                m = min(size, self.count - start)
                file.seek(self.offset + start * self.dtype.itemsize)
                records = np.fromfile(file, self.dtype, count=m)
                if len(records) < m:
                    raise InputError(self.path, f"truncated PLY body (vertex {start + len(records)} of {self.count})")
                yield records

    def _las_chunks(self, size: int) -> Iterator[Chunk]:
        import laspy

        from ..io.las import COLOR_NAMES, layout_values

        try:
            with laspy.open(self.path) as reader:
                for points in reader.chunk_iterator(size):
                    positions = np.column_stack([np.asarray(points.x), np.asarray(points.y),
                                                 np.asarray(points.z)]).astype(np.float64)
                    colors = None
                    if self.has_colors:
                        rgb = np.column_stack([points[name] for name in COLOR_NAMES]).astype(np.float32)
                        colors = np.clip(rgb / self.color_scale, 0.0, 1.0)
                    normals, _, attributes = layout_values(points, self.layout)
                    yield checked(self.path, positions, normals, colors, attributes)
        except SurfelError:
            raise
        except Exception as error:  # laspy and lazrs raise many types; all mean a bad file here
            message = (str(error).splitlines() or [type(error).__name__])[0][:120]
            raise InputError(self.path, f"cannot decode LAS data: {message}") from error


def checked(path: str, positions: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None,
            attributes: dict[str, np.ndarray]) -> Chunk:
    """The chunk, if its values are what a PointCloud accepts (InputError otherwise)."""
    if not np.isfinite(positions).all():
        raise InputError(path, "points have NaN or infinite coordinates")
    if normals is not None:
        # zero vectors are placeholders (cloud.file_normals): the scan pass drops such normals
        if not np.isfinite(normals).all():  # counted only then: a reduction along rows is slow
            bad = ~np.isfinite(normals).all(axis=1)
            raise InputError(path, f"{points_have(int(bad.sum()))} NaN or infinite normals (in one chunk)")
    for name, values in attributes.items():
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            raise InputError(path, f"points have NaN or infinite {name}")
    return Chunk(positions, normals, colors, attributes)


def open_ply(path: str) -> StreamInput:
    from ..io.ply import MESH_ELEMENTS, color_scale, parse_header, record_fields, vertex_layout

    with open(path, "rb") as file:
        head = file.read(1 << 16)  # headers are small; parse only this much
    if not head:
        raise InputError(path, "file is empty")
    header = parse_header(head, path)  # reads bytes like its usual memory map
    if header.format == "ascii":
        return whole(path)
    offset = header.body_offset
    for element in header.elements:
        props = list(element.properties.values())
        if any(p.is_list for p in props):
            if element.name == "vertex":
                raise InputError(path, "PLY vertex element has list properties")
            return whole(path)  # a list element before the vertices: sizes unknown, load it
        dtype = np.dtype([f for p in props for f in record_fields(p, header.format, {})])
        if element.name == "vertex":
            break
        offset += element.count * dtype.itemsize
    else:
        raise InputError(path, "PLY has no vertex element")
    if any(e.name in MESH_ELEMENTS and e.count for e in header.elements):
        return whole(path)  # a mesh: its referenced vertices are the points
    names = set(element.properties)
    if not {"x", "y", "z"} <= names:
        raise InputError(path, "PLY vertex element lacks x, y or z")
    need = offset + element.count * dtype.itemsize
    if os.path.getsize(path) < need:
        raise InputError(path, f"truncated PLY body ({os.path.getsize(path)} bytes, header needs {need})")
    if element.count == 0:
        raise InputError(path, "no points")
    has_colors = {"red", "green", "blue"} <= names
    scale = color_scale(element.properties["red"].type) if has_colors else 1.0
    layout = vertex_layout(header, path)
    return StreamInput(path, "ply", element.count, {"nx", "ny", "nz"} <= names, has_colors, header.geospatial,
                       [item.spec for item in layout], {item.spec.name for item in layout if item.stated},
                       offset, dtype, scale, layout)


def open_las(path: str) -> StreamInput:
    import laspy

    from ..io.las import COLOR_NAMES, check_header, las_layout

    check_header(path)
    try:
        with laspy.open(path) as reader:
            count = int(reader.header.point_count)
            point_format = reader.header.point_format
            layout = las_layout(point_format, reader.header.vlrs, path)
    except SurfelError:
        raise
    except Exception as error:
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        raise InputError(path, f"cannot decode LAS data: {message}") from error
    if count == 0:
        raise InputError(path, "no points")
    return StreamInput(path, "las", count, layout.normals is not None,
                       set(COLOR_NAMES) <= set(point_format.dimension_names), layout.geospatial,
                       [spec for spec, _ in layout.attributes], set(layout.kinds), layout=layout)


def whole(path: str) -> StreamInput:
    from ..io import load

    cloud = load(path)  # small formats (ascii, meshes): load once to learn what they hold
    schema = cloud.schema
    return StreamInput(path, "whole", len(cloud), cloud.normals is not None, cloud.colors is not None,
                       cloud.geospatial, list(schema.values()), set(schema))


def open_inputs(path: str | os.PathLike) -> list[StreamInput]:
    """The input files of `path` (a file, or a directory of tiles read as one cloud)."""
    from ..io import FORMATS

    name = os.fspath(path)
    if os.path.isdir(name):
        files = sorted(str(p) for p in Path(name).iterdir()
                       if p.is_file() and p.suffix.lower().lstrip(".") in FORMATS)
        if not files:
            raise InputError(name, "directory holds no point-cloud files")
    elif os.path.isfile(name):
        files = [name]
    else:
        raise InputError(name, "no such file")
    inputs = []
    for file in files:
        ext = os.path.splitext(file)[1].lower()
        inputs.append(open_ply(file) if ext == ".ply" else open_las(file) if ext in (".las", ".laz")
                      else whole(file))
    if len({i.has_normals for i in inputs}) > 1 or len({i.has_colors for i in inputs}) > 1:
        raise InputError(name, "tiles differ in whether they have normals or colours")
    if len({tuple((s.name, s.dtype, s.shape) for s in i.specs) for i in inputs}) > 1:
        raise InputError(name, "tiles differ in their attributes (names, types or shapes)")
    return inputs


def all_chunks(inputs: list[StreamInput]) -> Iterator[Chunk]:
    for source in inputs:
        yield from source.chunks()


def read_ahead(chunks: Iterator[Chunk]) -> Iterator[Chunk]:
    """The chunks, the next one read by a background thread while the caller processes the
    last: the reads (file I/O, numpy's conversions, LAZ decoding) release the GIL, so they run
    on the other core. At most READ_AHEAD chunks wait; a read's error is raised in the caller."""
    waiting: queue.Queue = queue.Queue(maxsize=READ_AHEAD)
    stop = threading.Event()
    finished = object()

    def hand_over(item) -> bool:
        while not stop.is_set():
            try:
                waiting.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def read() -> None:
        try:
            for chunk in chunks:
                if not hand_over(chunk):
                    return
            hand_over(finished)
        except BaseException as error:  # raised again in the caller's thread
            hand_over(error)

    reader = threading.Thread(target=read, name="surfel-read-ahead", daemon=True)
    reader.start()
    try:
        while (item := waiting.get()) is not finished:
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        reader.join()


class KindVote:
    """The kinds of the inputs' attributes, decided over every chunk (module docstring):
    `add` each chunk of the scan pass, then read `kinds`."""

    def __init__(self, inputs: list[StreamInput]):
        self.specs = inputs[0].specs
        stated = set.intersection(*(source.stated for source in inputs))
        self._kinds = {spec.name: spec.kind for spec in self.specs if spec.name in stated}
        self._distinct: dict[str, np.ndarray | None] = {}
        for spec in self.specs:
            if spec.name in self._kinds:
                continue
            if spec.name in DERIVED or known_name(spec.name) is not None:
                self._kinds[spec.name] = resolve_kind(spec.name, np.zeros((0, *spec.shape), spec.dtype))
            elif spec.shape or spec.dtype.kind not in "biu":
                self._kinds[spec.name] = CONTINUOUS
            else:
                self._distinct[spec.name] = np.zeros(0, spec.dtype)

    def add(self, attributes: dict[str, np.ndarray]) -> None:
        """Count the distinct values of a chunk's attributes."""
        for name, seen in self._distinct.items():
            if seen is not None:
                seen = np.union1d(seen, np.unique(attributes[name]))
                self._distinct[name] = seen if len(seen) <= MAX_CATEGORIES else None

    @property
    def kinds(self) -> dict[str, str]:
        return {**self._kinds, **{name: CONTINUOUS if seen is None else CATEGORICAL
                                  for name, seen in self._distinct.items()}}
