"""Colour by attribute (docs/conventions.md "Colour"): what `--color`, `--colormap`,
`--color-range`, `--classes` and `--returns` mean, for every method and backend.

A colour mode names what the albedo shows: `rgb` (the points' colours, white without them),
`elevation` (the coordinate along the cloud's up axis: +Z for geospatial data, +Y otherwise),
or an attribute (`intensity`, `classification`, `return-number` for return_number, or any
attribute's own name). `resolve` turns the mode into a `Coloring` for one cloud, using the
attribute schema (surfel.attributes) for its kind:

continuous  a value v is mapped through a colour map (matplotlib's names, served by the
            `cmap` library, BSD-3-Clause) over a range [lo, hi], by default the 2nd to 98th
            percentiles of the finite values (robust to outliers):
                t = clamp((v - lo) / (hi - lo), 0, 1),   albedo = LUT[round(255 t)]
            with LUT the map sampled at LUT_SIZE points. Values are splatted and filtered like
            colour, then mapped per pixel: every method splats the encoded colour
            (t, valid, 0), valid = 1 for a finite v and 0 for NaN, and after normalization
            (weighted means t', valid') shows
                albedo = mix(NEUTRAL, LUT[round(255 t' / valid')], valid')
            (the LUT entry itself where valid' = 1), so that a pixel of finite values has
            an exact colour of the map and points whose
            value is not a number show NEUTRAL. Methods that shade each splat before
            blending map each splat instead (gl/colors.glsl `splat_albedo`).
categorical codes (classification, return numbers, point source ids, any integer field with
            few values) are never blended: each distinct code gets a palette entry (the
            ASPRS LAS 1.4 standard classes in the colours Potree gives them,
            ClassificationScheme.DEFAULT; other codes and other attributes cycle through
            matplotlib's tab20), and a pixel shows the entry of the one splat that wins
            there, the one of largest weight. The splat's palette index k rides in the
            encoded colour (k / CODE_SCALE, 0, 0); a pass with MAX blending keeps, per pixel,
                packed = level(w) * code_levels + k,
                level(w) = clamp(floor((log2 w + 64) / 128 * weight_levels), 0, weight_levels - 1)
            with code_levels the power of two above the number of codes and weight_levels =
            2^24 / code_levels, so that packed is an exact float32 integer and the heaviest
            splat wins (ties: the larger index). The CPU rasterizer keeps the same packed
            maximum. Methods with no splats (mls, mls-gpu, mesh) take the code of the sample
            nearest to the surface point (`surface_albedo`).

Filters: `--classes 2,9` keeps the points of these classification codes, `--returns` those
of these return numbers and/or `first` (return 1) and `last` (return_number ==
number_of_returns); the Renderer applies them before anything is estimated, so that a
filtered cloud gets splats sized for what is drawn (`--classes 2`: a continuous bare earth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache, cached_property

import numba
import numpy as np

from .attributes import CATEGORICAL, CONTINUOUS
from .errors import SurfelError

RGB = "rgb"
ELEVATION = "elevation"
NAMED = (RGB, "intensity", ELEVATION, "classification", "return-number")  # what --help lists
LUT_SIZE = 256
DEFAULT_COLORMAP = "viridis"
ROBUST_PERCENTILES = (2.0, 98.0)
NEUTRAL = (0.5, 0.5, 0.5)  # the albedo of a point whose value is not a number
CATEGORY_PALETTE = "tab20"
# ASPRS LAS 1.4 R15 standard classes (table 17) in Potree's colours (ClassificationScheme.DEFAULT);
# the classes Potree leaves at its default colour get distinct ones here.
ASPRS_COLORS = {
    0: (0.5, 0.5, 0.5), 1: (0.5, 0.5, 0.5), 2: (0.63, 0.32, 0.18), 3: (0.0, 1.0, 0.0), 4: (0.0, 0.8, 0.0),
    5: (0.0, 0.6, 0.0), 6: (1.0, 0.66, 0.0), 7: (1.0, 0.0, 1.0), 8: (1.0, 0.0, 0.0), 9: (0.0, 0.0, 1.0),
    10: (0.55, 0.3, 0.55), 11: (0.21, 0.27, 0.31), 12: (1.0, 1.0, 0.0), 13: (0.9, 0.9, 0.4),
    14: (1.0, 0.85, 0.2), 15: (0.8, 0.25, 0.1), 16: (1.0, 0.55, 0.8), 17: (0.55, 0.75, 0.9),
    18: (0.85, 0.1, 0.4),
}
CODE_SCALE = float(2 ** 20)  # a categorical splat's palette index k is encoded as k / CODE_SCALE
MAX_CODES = 2 ** 16
PACKED_BITS = 24  # packed (level, index) stays an exact float32 integer
LOG2_WEIGHT_SPAN = 128.0  # level(w) spans log2 w in [-64, 64)
RETURN_WORDS = ("first", "last")


def attribute_name(color: str, cloud=None) -> str:
    """The attribute a --color value names: dashes stand for underscores (`return-number`
    is return_number) unless `cloud` has an attribute spelt with the dashes."""
    if cloud is not None and color in getattr(cloud, "attributes", {}):
        return color
    return color.replace("-", "_")


@cache
def colormap_table(name: str) -> np.ndarray:
    """(LUT_SIZE, 3) float32: the colour map sampled at LUT_SIZE points, each channel rounded
    to k / 255 so that the CPU and GPU paths read identical entries."""
    import cmap

    try:
        lut = np.asarray(cmap.Colormap(name).lut(LUT_SIZE), np.float64)[:, :3]
    except (ValueError, KeyError, TypeError) as exc:
        raise SurfelError(f"--colormap: unknown colour map {name!r} ({exc})") from None
    if len(lut) != LUT_SIZE:  # a qualitative map: its own colours, spread over the range
        lut = lut[np.minimum(np.arange(LUT_SIZE) * len(lut) // LUT_SIZE, len(lut) - 1)]
    return quantized(lut)


def quantized(rgb) -> np.ndarray:
    return (np.round(np.asarray(rgb, np.float64) * 255) / 255).astype(np.float32)


def check_colormap(name: str) -> str | None:
    """The problem with a colour map's name, or None (a Settings check)."""
    try:
        colormap_table(name)
    except SurfelError as exc:
        return str(exc).split(": ", 1)[1]
    return None


def palette(attribute: str, codes: np.ndarray) -> np.ndarray:
    """(len(codes), 3) float32: classification codes in ASPRS_COLORS, anything else (and
    unlisted classes) in CATEGORY_PALETTE, by the code's rank so that neighbours differ."""
    import cmap

    cycle = np.asarray(cmap.Colormap(CATEGORY_PALETTE).lut(), np.float64)[:, :3]
    rows = []
    for rank, code in enumerate(np.asarray(codes).tolist()):
        if attribute == "classification" and code in ASPRS_COLORS:
            rows.append(ASPRS_COLORS[code])
        elif isinstance(code, float) and not math.isfinite(code):
            rows.append(NEUTRAL)
        else:
            rows.append(cycle[(int(code) if attribute == "classification" else rank) % len(cycle)])
    return quantized(np.reshape(rows, (-1, 3)))


def code_levels(count: int) -> int:
    """Codes per weight level in the packed category value: a power of two >= count."""
    return 1 << max(1, math.ceil(math.log2(max(count, 2))))


@numba.njit(cache=True, fastmath=True)
def category_pack(weight, index, levels):  # pragma: no cover - compiled
    """The packed (weight level, palette index) of the module docstring, as float32."""
    weight_levels = (1 << PACKED_BITS) // levels
    scaled = (math.log2(max(weight, 1e-30)) + LOG2_WEIGHT_SPAN / 2) / LOG2_WEIGHT_SPAN * weight_levels
    level = min(max(math.floor(scaled), 0), weight_levels - 1)
    return np.float32(level * levels + index)


_NEUTRAL = tuple(np.float32(c) for c in NEUTRAL)


@numba.njit(inline="always", fastmath=True)
def continuous_pixel(t, valid, table):  # pragma: no cover - compiled
    """`Coloring.decode` of one encoded continuous colour (t, valid) for numba kernels (gl/colors.glsl
    `continuous_albedo`): the albedo (r, g, b) from the colour map's LUT `table` (LUT_SIZE, 3)."""
    valid = min(valid, np.float32(1.0))
    if valid <= 0:
        return _NEUTRAL
    t = min(max(t / valid, np.float32(0.0)), np.float32(1.0))
    entry = table[int(math.floor(t * np.float32(LUT_SIZE - 1) + np.float32(0.5)))]
    if valid >= 1:
        return entry[0], entry[1], entry[2]
    return (_NEUTRAL[0] + (entry[0] - _NEUTRAL[0]) * valid, _NEUTRAL[1] + (entry[1] - _NEUTRAL[1]) * valid,
            _NEUTRAL[2] + (entry[2] - _NEUTRAL[2]) * valid)


def category_unpack(packed: np.ndarray, levels: int) -> np.ndarray:
    """Palette indices (int32, -1 where nothing was packed) of packed category values."""
    packed = np.asarray(packed)
    index = np.mod(np.round(packed), levels).astype(np.int32)
    return np.where(packed >= 0, index, -1).astype(np.int32)


def up_axis(cloud) -> np.ndarray:
    """The cloud's up axis: +Z for geospatial data, +Y otherwise (docs/conventions.md)."""
    return np.array([0.0, 0.0, 1.0]) if cloud.geospatial else np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True, eq=False)
class Coloring:
    """A colour mode resolved for one cloud: what every method splats as colour (`encode`)
    and how a pixel's normalized value becomes its albedo (`decode`, `table`).

    name    the mode: rgb, elevation or an attribute's name
    kind    rgb, continuous or categorical
    colormap, range   continuous modes: the map and the [lo, hi] it spans
    codes   categorical modes: the distinct codes, sorted (a pixel's palette index k shows codes[k])
    """

    name: str
    kind: str
    colormap: str | None = None
    range: tuple[float, float] | None = None
    codes: np.ndarray | None = None

    @property
    def categorical(self) -> bool:
        return self.kind == CATEGORICAL

    @property
    def continuous(self) -> bool:
        return self.kind == CONTINUOUS

    @cached_property
    def table(self) -> np.ndarray:
        """(M, 3) float32: the colour map's LUT or the palette, by index."""
        if self.continuous:
            return colormap_table(self.colormap)
        if self.categorical:
            return palette(self.name, self.codes)
        return np.ones((1, 3), np.float32)

    @property
    def code_levels(self) -> int:
        return code_levels(len(self.codes)) if self.categorical else 2

    def values(self, cloud) -> np.ndarray:
        """The per-point values the mode shows (elevation from the positions)."""
        if self.name == ELEVATION:
            return cloud.positions @ up_axis(cloud)
        return cloud.attributes[self.name]

    def encode(self, cloud) -> np.ndarray:
        """(N, 3) float32: the colour every method splats (module docstring)."""
        values = self.values(cloud)
        if self.categorical:
            index = np.searchsorted(self.codes, values)
            if values.dtype.kind == "f":  # NaN sorts last: the palette's last (neutral) entry
                index = np.where(np.isnan(values), len(self.codes) - 1, index)
            out = np.zeros((len(cloud), 3), np.float32)
            out[:, 0] = np.minimum(index, len(self.codes) - 1) / CODE_SCALE
            return out
        lo, hi = self.range
        values = np.asarray(values, np.float64)
        valid = np.isfinite(values)
        with np.errstate(invalid="ignore"):
            t = np.clip((values - lo) / (hi - lo), 0.0, 1.0)
        return np.stack([np.where(valid, t, 0.0), valid, np.zeros(len(values))], axis=1).astype(np.float32)

    def decode(self, blended: np.ndarray) -> np.ndarray:
        """Albedo (..., 3) float32 of normalized encoded colours (..., 3): gl/colors.glsl's
        `blended_albedo` on the CPU."""
        blended = np.asarray(blended, np.float32)
        if self.categorical:
            return self.table[self.indices(blended)]
        if not self.continuous:
            return blended
        valid = np.minimum(blended[..., 1], 1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.clip(blended[..., 0] / np.maximum(valid, 1e-30), 0.0, 1.0)
        mapped = self.table[np.floor(t * (LUT_SIZE - 1) + 0.5).astype(np.int64)]
        neutral = np.asarray(NEUTRAL, np.float32)
        mixed = neutral + (mapped - neutral) * np.maximum(valid, 0.0)[..., None]
        out = np.where((valid >= 1)[..., None], mapped, mixed)  # all numbers: the map's own entry
        return np.where((valid > 0)[..., None], out, neutral).astype(np.float32)

    def indices(self, encoded: np.ndarray) -> np.ndarray:
        """Palette indices (int64) of encoded categorical colours."""
        return np.clip(np.floor(encoded[..., 0] * CODE_SCALE + 0.5), 0, len(self.codes) - 1).astype(np.int64)

    def describe(self) -> dict:
        """What the stats report."""
        out: dict = {"color": self.name}
        if self.continuous:
            out.update(colormap=self.colormap, color_range=[float(self.range[0]), float(self.range[1])])
        elif self.categorical:
            out["categories"] = [v.item() if np.isfinite(v) else None for v in np.asarray(self.codes, np.float64)]
        return out


def default_color(cloud) -> str:
    """`--color` when not given: rgb where the cloud has colours, else elevation for
    geospatial data (a LiDAR tile without RGB), else rgb (white)."""
    return RGB if cloud.colors is not None or not cloud.geospatial else ELEVATION


def offered(cloud) -> list[str]:
    """The colour modes `cloud` can show, for menus and the viewer's key: rgb, elevation, the
    named attributes it has, then its other one-number-per-point scanner attributes."""
    schema = getattr(cloud, "schema", None) or {}  # a LodSource may describe none before its cut
    scalars = [name for name, spec in schema.items() if spec.shape == () and not spec.derived]
    named = [mode for mode in NAMED if mode not in (RGB, ELEVATION) and attribute_name(mode) in scalars]
    return [RGB, ELEVATION, *named, *(n for n in scalars if n not in {attribute_name(m) for m in named})]


def resolve(cloud, color: str | None, colormap: str = DEFAULT_COLORMAP,
            color_range: tuple[float, float] | None = None) -> Coloring:
    """The Coloring of mode `color` (None: `default_color`) for `cloud`; an attribute the
    cloud lacks, or one that is not one number per point, is a one-line SurfelError."""
    color = default_color(cloud) if color is None else color
    if color == RGB:
        return Coloring(RGB, RGB)
    name = attribute_name(color, cloud)
    where = cloud.source or "the cloud"
    if name == ELEVATION:
        kind = CONTINUOUS
    elif name in cloud.attributes:
        spec = cloud.schema[name]
        if spec.shape != ():
            raise SurfelError(f"--color: attribute {name!r} of {where} holds {spec.components} numbers per "
                              "point; a colour mode needs one")
        kind = spec.kind
    else:
        scalars = [n for n, s in cloud.schema.items() if s.shape == () and not s.derived]
        raise SurfelError(f"--color: {where} has no attribute {name!r}; choose rgb, elevation"
                          + (f" or one of {', '.join(scalars)}" if scalars else ""))
    coloring = Coloring(name, kind)
    values = coloring.values(cloud)
    if kind == CATEGORICAL:
        codes = np.unique(values)  # NaN, if any, sorts last
        if values.dtype.kind == "f" and np.isnan(codes).any():
            codes = np.append(codes[~np.isnan(codes)], np.nan)
        if len(codes) > MAX_CODES:
            raise SurfelError(f"--color: attribute {name!r} of {where} has {len(codes)} distinct codes; "
                              f"a categorical palette takes at most {MAX_CODES}")
        return Coloring(name, kind, codes=codes)
    if color_range is None:
        finite = np.asarray(values, np.float64)
        finite = finite[np.isfinite(finite)]
        lo, hi = (np.percentile(finite, ROBUST_PERCENTILES) if finite.size else (0.0, 1.0))
        if not hi > lo:  # one value: a range around it
            lo, hi = lo - 0.5, hi + 0.5
        color_range = (float(lo), float(hi))
    colormap_table(colormap)
    return Coloring(name, kind, colormap=colormap, range=(float(color_range[0]), float(color_range[1])))


def selection(cloud, classes: tuple[int, ...] | None, returns: tuple[str, ...] | None) -> np.ndarray | None:
    """The mask of points `--classes` and `--returns` keep (None: no filter); a filter the
    cloud has no attribute for, or one that keeps nothing, is a one-line SurfelError."""
    if classes is None and returns is None:
        return None
    where = cloud.source or "the cloud"
    keep = np.ones(len(cloud), bool)
    if classes is not None:
        if "classification" not in cloud.attributes:
            raise SurfelError(f"--classes: {where} has no classification attribute")
        keep &= np.isin(cloud.attributes["classification"], np.asarray(classes))
    if returns is not None:
        if "return_number" not in cloud.attributes:
            raise SurfelError(f"--returns: {where} has no return_number attribute")
        number = cloud.attributes["return_number"]
        chosen = np.isin(number, [int(r) for r in returns if r not in RETURN_WORDS])
        if "first" in returns:
            chosen |= number == 1
        if "last" in returns:
            if "number_of_returns" not in cloud.attributes:
                raise SurfelError(f"--returns last: {where} has no number_of_returns attribute")
            chosen |= number == cloud.attributes["number_of_returns"]
        keep &= chosen
    if not keep.any():
        asked = ", ".join(f"{flag} {','.join(map(str, value))}" for flag, value in
                          (("--classes", classes), ("--returns", returns)) if value is not None)
        raise SurfelError(f"{asked}: no point of {where} is left to draw")
    return keep


def shade_samples(shaded, normals, depth, albedo, model: str, near: float, far: float) -> np.ndarray:
    """Shaded colours (H, W, 3) with every covered sample (finite depth) shaded again from
    `albedo` (H, W, 3) under `model` (for methods whose colour modes are resolved on the CPU)."""
    from .shading import shade

    covered = np.isfinite(depth)
    out = np.array(shaded, np.float32, copy=True)
    if covered.any():
        out[covered] = shade(model, albedo[covered], normals[covered], depth[covered], near, far)
    return out


def surface_albedo(cloud, camera, depth: np.ndarray, coloring: Coloring, tree=None):
    """For methods without splats (mls, mls-gpu, mesh): (albedo (H, W, 3), palette indices
    (H, W) or None) of the surface seen at each sample of `depth` (eye distance along the
    viewing axis, inf where empty), or (None, None) where the method's own blend of the
    encoded colours stands. Elevation is that of the surface point itself (these methods
    define the surface, not splats of it); a category is that of the point nearest to it.
    `cloud` holds the encoded colours (`encode`); `tree`: a cKDTree of cloud.local_positions()."""
    if not (coloring.categorical or coloring.name == ELEVATION):
        return None, None
    h, w = depth.shape
    albedo = np.ones((h, w, 3), np.float32)
    hit = np.isfinite(depth)
    indices = np.full((h, w), -1, np.int32) if coloring.categorical else None
    if not hit.any():
        return albedo, indices
    o, d = camera.rays_at(*np.nonzero(hit))
    eye = o + d * (depth[hit] / -d[:, 2])[:, None]
    view = camera.view_matrix(cloud.local_origin)
    local = (eye - view[:3, 3]) @ view[:3, :3]  # R^T (eye - t)
    if coloring.categorical:
        from scipy.spatial import cKDTree

        tree = tree if tree is not None else cKDTree(cloud.local_positions())
        _, nearest = tree.query(local, workers=-1)
        indices[hit] = coloring.indices(cloud.colors[nearest])
        albedo[hit] = coloring.table[indices[hit]]
    else:
        elevation = (local + cloud.local_origin) @ up_axis(cloud)
        lo, hi = coloring.range
        t = np.clip((elevation - lo) / (hi - lo), 0.0, 1.0)
        albedo[hit] = coloring.decode(np.stack([t, np.ones_like(t), np.zeros_like(t)], axis=1))
    return albedo, indices


__all__ = ["Coloring", "resolve", "offered", "selection", "default_color", "colormap_table", "palette", "NAMED",
           "DEFAULT_COLORMAP", "NEUTRAL", "CODE_SCALE", "category_pack", "category_unpack", "continuous_pixel",
           "shade_samples", "surface_albedo", "up_axis"]
