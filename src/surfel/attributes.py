"""The attribute schema: what each per-point array of a `PointCloud` holds.

Every array of a cloud other than its geometry (positions, normals, colours, radii, axes,
faces) is an attribute, keyed by name. One `AttributeSpec` describes each:

    name    the key in `PointCloud.attributes`
    dtype   kept as read: uint16 intensity, uint8 classification, float64 GPS time ...
    shape   the per-point shape: () for a scalar, (3,) for a vector, (2, 3) for clip lines
    kind    "categorical" (codes: a class, a return number, a flag; never averaged or
            blended) or "continuous" (a measurement: averaged, filtered like colour)

A `Schema` is the ordered name -> spec mapping of a cloud (`cloud.schema`); its JSON form
(`Schema.to_json`) is how file formats store it (the LOD files, the out-of-core manifest,
the COPC writer's VLR).

Kinds. A reader that knows may state a kind (`PointCloud(kinds={...})`); otherwise
`resolve_kind` decides, in this order:

1. surfel's own estimates (`DERIVED`) are continuous;
2. the LAS standard dimensions (ASPRS LAS 1.4 R15, tables 7 and 15; `KNOWN_KINDS`) have their
   known kind: classification, return and class flags, point source id, user data, scanner
   channel are categorical; intensity, GPS time, scan angle, NIR are continuous. Names are
   compared in a compact form (lower case, letters and digits only), so ``Classification``,
   ``ReturnNumber`` and CloudCompare's ``scalar_Intensity`` are known too;
3. any other integer or boolean scalar attribute with at most MAX_CATEGORIES distinct values
   is categorical; everything else is continuous.

Derived arrays. Attributes estimated by surfel rather than measured by a scanner have reserved
names (`DERIVED`): the Phong normal-field slopes ``phong_alpha``, ``phong_beta`` (Botsch et al.
2004) that shade a splat, and ``curve_alpha``, ``curve_beta`` that shape it (a face's, flat up
to its rim: surfel.preprocess.normal_field), the sharp-feature ``clip_lines``
(surfel.preprocess), ``screen_facing`` (1 for the points on no surface, drawn as round splats
facing the camera: surfel.preprocess.structure), the ``thickness`` of a splat's layer, which
caps z_t (surfel.preprocess.thickness), and the sequential point tree's ``lod_emin``,
``lod_emax``, ``lod_dparent``, ``lod_dsuffix`` (Dachsbacher et al. 2003). They go through the
same schema (`AttributeSpec.derived` is true for them), are always float32 and continuous, and
describe the splats they were estimated for: a level-of-detail path keeps the leaves' clip lines
(inner nodes cut nothing), computes its own lod_* and drops the slopes and thicknesses (inner
nodes are new disks; Phong splatting fits them again), makes an inner node screen-facing when
most of its children's area is, while scanner attributes are aggregated (lod/build.py).
`Schema.scanner` lists the scanner fields, so that users see them apart from surfel's estimates.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

CATEGORICAL = "categorical"
CONTINUOUS = "continuous"
KINDS = (CATEGORICAL, CONTINUOUS)
# An integer attribute with more distinct values than this is a measurement, not a code
# (LAS classes stop at 255 but real files use a few dozen at most).
MAX_CATEGORIES = 64

KNOWN_KINDS = {
    "classification": CATEGORICAL, "return_number": CATEGORICAL, "number_of_returns": CATEGORICAL,
    "point_source_id": CATEGORICAL, "user_data": CATEGORICAL, "scanner_channel": CATEGORICAL,
    "scan_direction_flag": CATEGORICAL, "edge_of_flight_line": CATEGORICAL, "synthetic": CATEGORICAL,
    "key_point": CATEGORICAL, "withheld": CATEGORICAL, "overlap": CATEGORICAL,
    "intensity": CONTINUOUS, "gps_time": CONTINUOUS, "scan_angle": CONTINUOUS, "nir": CONTINUOUS,
}
# Other spellings of known names, in compact form: LAS 1.0-1.3's whole-degree scan angle.
_ALIASES = {"scananglerank": "scan_angle"}
# The normal field's slopes, in the order preprocessing fits them: the shading's, then the surface's.
FIELD_SLOPES = ("phong_alpha", "phong_beta", "curve_alpha", "curve_beta")
DERIVED = frozenset({*FIELD_SLOPES, "clip_lines", "screen_facing", "thickness", "lod_emin",
                     "lod_emax", "lod_dparent", "lod_dsuffix"})
DERIVED_DTYPE = np.dtype(np.float32)
# Each derived array's per-point shape (scalars but the clip lines: two lines a u + b v <= c,
# as surfel.preprocess estimates them); a file holding another is refused, since every
# renderer indexes them so.
DERIVED_SHAPES = {name: () for name in DERIVED} | {"clip_lines": (2, 3)}
# The derived arrays that are lengths in world units (the others are relative to a splat's
# axes); the largest float32 among them stands for infinity (the root's parent error).
DERIVED_LENGTHS = frozenset({"thickness", "lod_emin", "lod_emax", "lod_dparent", "lod_dsuffix"})
INFINITE_LENGTH = float(np.finfo(np.float32).max)
# The geometry fields of a PointCloud: never attribute names.
GEOMETRY = frozenset({"positions", "normals", "colors", "radii", "axes", "faces"})
_NUMERIC = "biuf"


def _compact(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


_KNOWN_COMPACT = {**{_compact(name): name for name in KNOWN_KINDS}, **_ALIASES}


def known_name(name: str) -> str | None:
    """The LAS standard name that `name` spells (``Intensity``, ``scalar_Classification``,
    ``GpsTime`` ...), or None."""
    compact = _compact(name)
    if name.lower().startswith("scalar_"):  # CloudCompare's prefix for its scalar fields
        compact = _compact(name[len("scalar_"):])
    return _KNOWN_COMPACT.get(compact)


def canonical_names(names: Iterable[str], taken: Iterable[str] = ()) -> list[str]:
    """Sensible attribute names for the fields a file calls `names`, in order.

    A known name takes its standard spelling (``Intensity`` -> ``intensity``), whitespace
    becomes ``_``; a name that would then collide with another, or with `taken`, stays as
    the file spells it.
    """
    names = list(names)
    taken = set(taken) | set(names)
    out = []
    for name in names:
        better = known_name(name) or re.sub(r"\s+", "_", name.strip())
        if better != name and (better in taken or not better):
            better = name
        taken.add(better)
        out.append(better)
    return out


def resolve_kind(name: str, values: np.ndarray) -> str:
    """The kind of attribute `name` holding `values` when no reader stated it (module docstring)."""
    if name in DERIVED:
        return CONTINUOUS
    known = known_name(name)
    if known is not None:
        return KNOWN_KINDS[known]
    if values.ndim == 1 and values.dtype.kind in "biu" and _few_values(values):
        return CATEGORICAL
    return CONTINUOUS


def _few_values(values: np.ndarray) -> bool:
    if not len(values):
        return True
    lo, hi = values.min(), values.max()
    if int(hi) - int(lo) < MAX_CATEGORIES:  # fewer codes than that fit in the range
        return True
    return len(np.unique(values)) <= MAX_CATEGORIES


@dataclass(frozen=True)
class AttributeSpec:
    """One attribute: name, numpy dtype, per-point shape and kind (module docstring)."""

    name: str
    dtype: np.dtype
    shape: tuple[int, ...] = ()
    kind: str = CONTINUOUS

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"attribute names are non-empty strings, not {self.name!r}")
        dtype = np.dtype(self.dtype)
        if dtype.kind not in _NUMERIC or dtype.fields is not None or dtype.subdtype is not None:
            raise ValueError(f"attribute {self.name!r}: {dtype} is not a numeric type")
        if self.kind not in KINDS:
            raise ValueError(f"attribute {self.name!r}: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        shape = tuple(int(size) for size in self.shape)
        if any(size < 0 for size in shape):
            raise ValueError(f"attribute {self.name!r}: negative size in shape {shape}")
        object.__setattr__(self, "dtype", dtype.newbyteorder("="))
        object.__setattr__(self, "shape", shape)

    @property
    def derived(self) -> bool:
        """Estimated by surfel (a reserved name), not read from the data."""
        return self.name in DERIVED

    @property
    def components(self) -> int:
        """Numbers per point (the product of the shape)."""
        return int(np.prod(self.shape, dtype=np.int64))

    def to_json(self) -> dict:
        return {"name": self.name, "dtype": self.dtype.name, "shape": list(self.shape), "kind": self.kind}

    @classmethod
    def from_json(cls, data: object) -> AttributeSpec:
        """The spec `to_json` wrote; ValueError for anything else."""
        if not isinstance(data, dict) or not {"name", "dtype", "shape", "kind"} <= data.keys():
            raise ValueError("an attribute entry needs name, dtype, shape and kind")
        shape, dtype = data["shape"], data["dtype"]
        if not isinstance(shape, list) or not all(isinstance(size, int) for size in shape):
            raise ValueError(f"attribute {data['name']!r}: shape {shape!r} is not a list of integers")
        if not isinstance(dtype, str) or not re.fullmatch(r"(bool|u?int(8|16|32|64)|float(16|32|64))", dtype):
            raise ValueError(f"attribute {data['name']!r}: {dtype!r} is not a numeric type")
        return cls(data["name"], np.dtype(dtype), tuple(shape), data["kind"])


class Schema(Mapping):
    """The attributes of a cloud, in order: name -> AttributeSpec."""

    def __init__(self, specs: Iterable[AttributeSpec] = ()):
        self._specs: dict[str, AttributeSpec] = {}
        for spec in specs:
            if spec.name in self._specs:
                raise ValueError(f"attribute {spec.name!r} appears twice in a schema")
            self._specs[spec.name] = spec

    @classmethod
    def of(cls, attributes: Mapping[str, np.ndarray], kinds: Mapping[str, str] | None = None) -> Schema:
        """The schema of per-point `attributes` (N, ...) arrays; `kinds` as stated by a reader,
        the others resolved (`resolve_kind`)."""
        kinds = kinds or {}
        return cls(AttributeSpec(name, values.dtype, values.shape[1:],
                                 CONTINUOUS if name in DERIVED else kinds.get(name) or resolve_kind(name, values))
                   for name, values in attributes.items())

    def __getitem__(self, name: str) -> AttributeSpec:
        return self._specs[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._specs)

    def __len__(self) -> int:
        return len(self._specs)

    def __repr__(self) -> str:
        return f"Schema({list(self._specs.values())!r})"

    @property
    def kinds(self) -> dict[str, str]:
        return {name: spec.kind for name, spec in self._specs.items()}

    def scanner(self) -> list[AttributeSpec]:
        """The attributes read from the data, without surfel's derived arrays."""
        return [spec for spec in self._specs.values() if not spec.derived]

    def to_list(self) -> list[dict]:
        """The JSON-ready form: one `AttributeSpec.to_json` dict per attribute, in order."""
        return [spec.to_json() for spec in self._specs.values()]

    def to_json(self) -> str:
        return json.dumps(self.to_list())

    @classmethod
    def from_json(cls, text: str | list) -> Schema:
        """The schema `to_json` wrote (as text or already parsed); ValueError for anything else."""
        data = json.loads(text) if isinstance(text, str) else text
        if not isinstance(data, list):
            raise ValueError("an attribute schema is a JSON list")
        return cls(AttributeSpec.from_json(entry) for entry in data)


def summarize(attributes: Mapping[str, np.ndarray], schema: Schema, max_values: int = 12) -> dict[str, dict]:
    """What `surfel info` shows of each attribute: dtype, shape, kind, whether derived, and
    min and max of the finite values and the count of the others (continuous) or the most
    frequent values with their counts (categorical, at most `max_values` of them; `more`
    counts the others)."""
    out = {}
    for name, spec in schema.items():
        values = attributes[name]
        entry: dict = {"dtype": spec.dtype.name, "shape": list(spec.shape), "kind": spec.kind}
        if spec.derived:
            entry["derived"] = True
        if spec.kind == CATEGORICAL:
            codes, counts = np.unique(values, return_counts=True)
            top = np.argsort(-counts, kind="stable")[:max_values]
            entry["values"] = {str(codes[i].item()): int(counts[i]) for i in top}
            if len(codes) > max_values:
                entry["more"] = int(len(codes) - max_values)
        elif values.size:
            finite = values[np.isfinite(values)] if values.dtype.kind == "f" else values
            if finite.size:
                entry["min"], entry["max"] = finite.min().item(), finite.max().item()
            if finite.size < values.size:
                entry["not_finite"] = int(values.size - finite.size)
        out[name] = entry
    return out


def summary_lines(summary: Mapping[str, dict]) -> list[str]:
    """One line per attribute of a `summarize` result, for people: name, dtype[shape], kind,
    range or values, in aligned columns."""
    rows = []
    for name, entry in summary.items():
        dtype = entry["dtype"] + ("" if not entry["shape"] else "[" + ",".join(map(str, entry["shape"])) + "]")
        kind = entry["kind"] + (" (derived)" if entry.get("derived") else "")
        if "values" in entry:
            what = ", ".join(f"{code}: {count}" for code, count in entry["values"].items())
            what += f", ... {entry['more']} more" if entry.get("more") else ""
        else:
            what = f"{entry['min']:.10g} .. {entry['max']:.10g}" if "min" in entry else "no finite value"
            what += f", {entry['not_finite']} not finite" if entry.get("not_finite") else ""
        rows.append((name, dtype, kind, what))
    widths = [max((len(row[column]) for row in rows), default=0) for column in range(3)]
    return [f"{name:{widths[0]}s}  {dtype:{widths[1]}s}  {kind:{widths[2]}s}  {what}"
            for name, dtype, kind, what in rows]
