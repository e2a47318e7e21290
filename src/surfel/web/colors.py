"""Colour modes of the page (CONVENTIONS.md, "Colour"): what each one embeds.

`rgb` shows the points' colours (white without them). `elevation` maps the coordinate along
the data's up axis, any other mode a per-point attribute: continuous attributes through a
colour map over a range (default the 2nd to 98th percentile, robust to outliers), sampled
from the `cmap` library (BSD-3-Clause; matplotlib's maps by the same names) into 256-entry
tables; categorical attributes (integer codes: classification, return number, point source
id, any integer field with few values) through a palette, classification with the ASPRS
standard class colours, never blended (web/category.glsl).
"""

from __future__ import annotations

import numpy as np

from ..errors import SurfelError

LUT_SIZE = 256
COLORMAPS = ("viridis", "turbo", "inferno", "cividis", "terrain", "gray")
DEFAULT_COLORMAP = "viridis"
ROBUST_PERCENTILES = (2.0, 98.0)
CATEGORICAL_NAMES = ("classification", "return_number", "number_of_returns", "point_source_id", "user_data",
                     "scan_direction_flag", "edge_of_flight_line", "synthetic", "key_point", "withheld", "overlap")
MAX_CATEGORIES = 64   # an integer attribute with at most this many distinct values is categorical
CATEGORY_PALETTE = "tab20"
# ASPRS LAS 1.4 standard classes (R15) in the colours LiDAR viewers (Potree, CloudCompare) use.
ASPRS_COLORS = {
    0: (0.50, 0.50, 0.50), 1: (0.70, 0.70, 0.70), 2: (0.63, 0.32, 0.18), 3: (0.60, 0.85, 0.35),
    4: (0.20, 0.70, 0.20), 5: (0.05, 0.45, 0.10), 6: (1.00, 0.66, 0.00), 7: (1.00, 0.00, 1.00),
    8: (1.00, 0.00, 0.00), 9: (0.10, 0.35, 1.00), 10: (0.55, 0.30, 0.55), 11: (0.35, 0.35, 0.35),
    12: (1.00, 1.00, 0.00), 13: (0.90, 0.90, 0.40), 14: (1.00, 0.85, 0.20), 15: (0.80, 0.25, 0.10),
    16: (1.00, 0.55, 0.80), 17: (0.55, 0.75, 0.90), 18: (0.85, 0.10, 0.40),
}
INTERNAL = ("clip_lines", "phong_alpha", "phong_beta", "lod_emin", "lod_emax", "lod_dparent", "lod_dsuffix")


def mode_name(color: str) -> str:
    """The attribute a --color value names: return-number is the attribute return_number."""
    return color.replace("-", "_")


def colormap_table(name: str) -> np.ndarray:
    """(LUT_SIZE, 3) uint8 samples of a colour map (matplotlib's names)."""
    import cmap

    try:
        lut = cmap.Colormap(name).lut(LUT_SIZE)
    except (ValueError, KeyError) as exc:
        raise SurfelError(f"--colormap: unknown colour map {name!r} ({exc})") from None
    return np.round(np.asarray(lut)[:, :3] * 255).astype(np.uint8)


def palette_table(name: str) -> np.ndarray:
    """(LUT_SIZE, 3) uint8: the colour of category code c % LUT_SIZE."""
    if name == "classification":
        import cmap

        rest = np.asarray(cmap.Colormap(CATEGORY_PALETTE).lut())[:, :3]
        table = np.array([ASPRS_COLORS.get(c, rest[c % len(rest)]) for c in range(LUT_SIZE)])
    else:
        import cmap

        colors = np.asarray(cmap.Colormap(CATEGORY_PALETTE).lut())[:, :3]
        table = colors[np.arange(LUT_SIZE) % len(colors)]
    return np.round(table * 255).astype(np.uint8)


def is_categorical(name: str, values: np.ndarray) -> bool:
    integral = bool(np.all(values == np.round(values))) and values.min() >= 0 and values.max() <= 65535
    return integral and (name in CATEGORICAL_NAMES or len(np.unique(values)) <= MAX_CATEGORIES)


def attribute_modes(cloud, up: np.ndarray, color_range: tuple[float, float] | None, initial: str) -> tuple[list, dict]:
    """The colour modes the page offers for `cloud` and each one's 16-bit point values.

    Returns (modes, values): modes is a list of {"name", "kind": "rgb" | "continuous" |
    "categorical", "range": [lo, hi] in the data's units, "quantized": [min, max] the 16 bits
    span (elevation: "offset", the local origin's elevation), "palette" (categorical)};
    `color_range` applies to the mode `initial`."""
    modes = [{"name": "rgb", "kind": "rgb"}]
    values: dict[str, np.ndarray] = {}
    elevation = _continuous("elevation", cloud.positions @ up, color_range if initial == "elevation" else None)
    elevation["offset"] = float(cloud.local_origin @ up)  # the page's positions are local
    modes.append(elevation)
    for name in sorted(cloud.attributes):
        data = cloud.attributes[name]
        if name in INTERNAL or data.ndim != 1:
            continue
        if is_categorical(name, data):
            values[name] = data.astype(np.uint16)
            modes.append({"name": name, "kind": "categorical", "palette": palette_table(name).tolist()})
            continue
        mode = _continuous(name, data, color_range if initial == name else None)
        lo, hi = mode["quantized"]
        values[name] = np.round((data - lo) / max(hi - lo, 1e-30) * 65535).astype(np.uint16)
        modes.append(mode)
    names = [m["name"] for m in modes]
    if initial not in names:
        raise SurfelError(f"--color: {cloud.source or 'the cloud'} has no attribute {initial!r}; "
                          f"choose one of {', '.join(names)}")
    return modes, values


def _continuous(name: str, data: np.ndarray, color_range) -> dict:
    data = np.asarray(data, np.float64)
    lo, hi = (np.percentile(data, ROBUST_PERCENTILES) if color_range is None else color_range)
    return {"name": name, "kind": "continuous", "range": [float(lo), float(hi)],
            "quantized": [float(data.min()), float(data.max())]}
