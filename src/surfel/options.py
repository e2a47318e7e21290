"""Typed settings: `RenderOptions`, what every method honours, and `Settings`, the base of
every method's parameter dataclass (`methods/params.py`, one subclass per method).

A setting is a field of a frozen dataclass, declared once with its default and, where not
every value of its type can be honoured, the check its value must pass (`setting(default,
check)`). Constructing the dataclass checks every field's type and value, so a value that
cannot be honoured is refused in one line naming it, whoever built it: the Python API, the
command line (`request.py`, which names the flag instead) or a batch job.
`from_mapping` builds one from a mapping of names, refusing names the class does not have.
"""

from __future__ import annotations

import math
import os
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from functools import cache

from .colors import DEFAULT_COLORMAP, RETURN_WORDS, Coloring, check_colormap
from .edl import DEFAULT_RADIUS as DEFAULT_EDL_RADIUS
from .edl import DEFAULT_STRENGTH as DEFAULT_EDL_STRENGTH
from .errors import SurfelError
from .shading import DEFAULT as DEFAULT_SHADING
from .shading import EDL, MODELS, PER_PIXEL


class SettingError(SurfelError):
    """A value a setting cannot take: `name` is the field, `problem` what is wrong with it."""

    def __init__(self, name: str, problem: str):
        self.name, self.problem = name, problem
        super().__init__(f"{name}: {problem}")


# Checks: a value in, the problem (or None) out; each is given a value of the field's type.
def positive(value) -> str | None:
    return None if math.isfinite(value) and value > 0 else f"must be a positive number, got {value}"


def non_negative(value) -> str | None:
    return None if math.isfinite(value) and value >= 0 else f"must be a number >= 0, got {value}"


def open_unit_interval(value) -> str | None:
    return None if 0 < value < 1 else f"must lie strictly between 0 and 1, got {value}"


def at_least(low: int) -> Callable:
    def check(value) -> str | None:
        return None if value >= low else f"must be at least {low}, got {value}"

    return check


def between(low: int, high: int) -> Callable:
    def check(value) -> str | None:
        return None if low <= value <= high else f"must be in {low}..{high}, got {value}"

    return check


def one_of(choices) -> Callable:
    def check(value) -> str | None:
        return None if value in choices else f"must be one of {', '.join(choices)}, got {value!r}"

    return check


def increasing(value) -> str | None:
    lo, hi = value
    ok = math.isfinite(lo) and math.isfinite(hi) and lo < hi
    return None if ok else f"must be two finite numbers LO,HI with LO below HI, got {lo:g},{hi:g}"


def class_codes(value) -> str | None:
    if not value:
        return "must name at least one class"
    bad = [v for v in value if not 0 <= v <= 255]
    return f"classification codes are 0..255, got {bad[0]}" if bad else None


def return_choices(value) -> str | None:
    if not value:
        return "must name at least one return"
    for v in value:
        if v not in RETURN_WORDS and not (v.isdigit() and 1 <= int(v) <= 15):
            return f"returns are numbers 1..15, first or last, got {v!r}"
    return None


def unit_rgb(value) -> str | None:
    ok = all(math.isfinite(v) and 0 <= v <= 1 for v in value)
    return None if ok else f"must be three values in [0, 1], got {','.join(f'{v:g}' for v in value)}"


def setting(default, check: Callable | None = None):
    """A dataclass field with its default and the check its value must pass."""
    return field(default=default, metadata={"check": check})


def _coerce(name: str, value, hint):
    """`value` as the annotated type `hint` (ints widen to floats, paths to strings), or a
    SettingError naming `name`."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(hint):
            return None
        options = [h for h in typing.get_args(hint) if h is not type(None)]
        for option in options[:-1]:
            try:
                return _coerce(name, value, option)
            except SettingError:
                pass
        return _coerce(name, value, options[-1])
    if origin is typing.Literal:
        return value if value in typing.get_args(hint) else _refuse(name, value, hint)
    if origin is tuple:
        items = typing.get_args(hint)
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
            _refuse(name, value, hint)
        if len(items) == 2 and items[1] is Ellipsis:  # tuple[X, ...]: any number of X
            items = (items[0],) * len(value)
        if len(value) != len(items):
            _refuse(name, value, hint)
        return tuple(_coerce(name, v, h) for v, h in zip(value, items, strict=True))
    if hint is bool:
        return value if isinstance(value, bool) else _refuse(name, value, hint)
    if hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
        return value if ok else _refuse(name, value, hint)
    if hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return float(value) if ok else _refuse(name, value, hint)
    if hint is str:
        return os.fspath(value) if isinstance(value, (str, os.PathLike)) else _refuse(name, value, hint)
    return value if isinstance(value, hint) else _refuse(name, value, hint)


def _refuse(name: str, value, hint):
    wanted = {bool: "true or false", int: "an integer", float: "a number", str: "a path or text"}.get(hint)
    if typing.get_origin(hint) is typing.Literal:
        wanted = "one of " + ", ".join(map(str, typing.get_args(hint)))
    elif typing.get_origin(hint) is tuple:
        items = typing.get_args(hint)
        wanted = "a list of values" if items[-1] is Ellipsis else f"{len(items)} numbers"
    raise SettingError(name, f"must be {wanted or getattr(hint, '__name__', hint)}, got {value!r}")


@cache  # a class's annotations never change; resolving them costs more than a frame's bookkeeping
def _field_types(cls) -> dict:
    return typing.get_type_hints(cls)


@dataclass(frozen=True)
class Settings:
    """Base of typed settings: checks every field's type and value on construction."""

    def __post_init__(self):
        hints = _field_types(type(self))
        for f in fields(self):
            value = _coerce(f.name, getattr(self, f.name), hints[f.name])
            object.__setattr__(self, f.name, value)  # the coerced value (an int given for a float)
            check = f.metadata.get("check")
            problem = check(value) if check is not None and value is not None else None
            if problem:
                raise SettingError(f.name, problem)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    @classmethod
    def defaults(cls) -> dict:
        return {f.name: f.default for f in fields(cls) if f.default is not MISSING}

    @classmethod
    def from_mapping(cls, values: Mapping[str, object], owner: str):
        """An instance from `values`; a name the class lacks is refused, naming `owner`'s
        settings (e.g. "method 'phong'")."""
        unknown = [name for name in values if name not in cls.names()]
        if unknown:
            known = ", ".join(cls.names()) or "none"
            raise SettingError(unknown[0], f"{owner} has no setting {unknown[0]!r}; it has: {known}")
        return cls(**values)


@dataclass(frozen=True)
class RenderOptions(Settings):
    """What a render is asked for, beyond the camera and the method:

    shading      : a model of shading.MODELS, None for the data's default (`shading.default_for`:
                   edl for a geospatial cloud without normals, else phong); every method
    color        : what the albedo shows (surfel.colors): rgb, elevation or an attribute's
                   name; None for the data's default (`colors.default_color`: rgb where the
                   cloud has colours, else elevation for geospatial data, else white)
    colormap     : matplotlib's name of the colour map of continuous attributes
    color_range  : (lo, hi) the colour map spans; None for the 2nd-98th percentiles
    classes      : classification codes to draw, None for all (`colors.selection`)
    returns      : return numbers and/or "first", "last" to draw, None for all
    edl_strength, edl_radius : eye-dome lighting (`edl`): strength, radius in output pixels
    background   : RGB in [0, 1] the image is composited over; every method
    supersample  : samples per pixel side, None for the method's default; every method
    lod_error    : sequential point tree error threshold in pixels, None for full detail (a
                   lazy LodSource, which cannot be drawn whole, then uses 1 pixel); the methods
                   that draw splats (`Method.needs_radii`), refused by the others
    point_budget : most nodes a LodSource's cut may hold (its error is raised to fit); the
                   same methods, and only for such a source
    dump_passes  : folder to write the intermediate passes to as images; the methods that
                   draw with the three-pass targets, on the backends of `Method.dump_passes`
    smooth       : denoise the positions first (preprocess/smoothing.py, MLS projection; raw
                   scans); every method, for clouds loaded whole
    params       : the method's parameters (its `Method.params` dataclass), None for its
                   defaults
    """

    shading: str | None = setting(None, one_of(MODELS))
    color: str | None = setting(None, lambda value: None if value else "must not be empty")
    colormap: str = setting(DEFAULT_COLORMAP, check_colormap)
    color_range: tuple[float, float] | None = setting(None, increasing)
    classes: tuple[int, ...] | None = setting(None, class_codes)
    returns: tuple[str, ...] | None = setting(None, return_choices)
    edl_strength: float = setting(DEFAULT_EDL_STRENGTH, non_negative)
    edl_radius: float = setting(DEFAULT_EDL_RADIUS, positive)
    background: tuple[float, float, float] = setting((0.0, 0.0, 0.0), unit_rgb)
    supersample: int | None = setting(None, between(1, 8))
    lod_error: float | None = setting(None, positive)
    point_budget: int | None = setting(None, at_least(1))
    dump_passes: str | None = None
    smooth: bool = setting(False)
    params: Settings | None = None
    coloring: Coloring | None = None  # `color` resolved for the cloud drawn (by the Renderer); None: rgb

    @property
    def surface_shading(self) -> str:
        """The model methods shade each pixel with: `shading`, where edl's per-pixel part is
        none (its screen-space term is applied to the samples afterwards); unresolved, the
        default model."""
        return PER_PIXEL.get(self.shading or DEFAULT_SHADING, self.shading or DEFAULT_SHADING)

    @property
    def edl(self) -> bool:
        return self.shading == EDL


# Samples (pixels times supersampling squared) the CPU rasterizers hold at most: their
# per-sample buffers take about 160 bytes a sample (EWA's two layers of accumulators, then
# the resolved layers), some 10 GB at this size (8192 x 8192, or 2048 x 2048 at 4 x 4).
MAX_CPU_SAMPLES = 8192 * 8192


def fitting_supersample(default: int, width: int, height: int, side_limit: int | None = None) -> int:
    """A method's default samples per pixel side for a width x height image, fewer where they
    would outgrow MAX_CPU_SAMPLES or `side_limit` samples a side (a GL context's targets): a
    very large still image takes one sample rather than fail. A count the options give is
    checked instead (`check_cpu_samples`, gl.targets.check_target_size)."""
    side_limit = side_limit or math.inf
    s = default
    while s > 1 and (width * height * s * s > MAX_CPU_SAMPLES or max(width, height) * s > side_limit):
        s -= 1
    return s


def check_cpu_samples(width: int, height: int) -> None:
    """Refuse a supersampled CPU render target of width x height samples beyond
    MAX_CPU_SAMPLES, naming the options that set it."""
    if width * height > MAX_CPU_SAMPLES:
        raise SurfelError(f"--size/--supersample: rendering on the CPU needs {width}x{height} samples (the image size "
                          f"times the supersampling), more than its limit of {MAX_CPU_SAMPLES} samples; choose a "
                          "smaller --size or --supersample")


# The options a method may not use: set (not None), they must be used by the chosen method.
METHOD_DEPENDENT = ("lod_error", "point_budget", "dump_passes")
