"""`surfel export-html`: one self-contained HTML file that splats the cloud in the browser.

The page (page.html, viewer.js) runs methods/splatting.glsl itself in WebGL2 (GLSL ES 3.00):
the exporter resolves its includes with the page's splat_attributes.glsl first, which
decodes the quantized columns of pack.py under the attribute names the desktop shaders use.
So the page's `phong` and `deferred` are Botsch et al. 2004 and 2005 exactly as `surfel render`
draws them: visibility, attribute accumulation, the category pass of categorical colour modes
and normalization, the EWA screen-space filter approximation, splats curved by their normal
fields, coverage from edge_distance() and surrounded(), point sprites on a guard band or
quads. The cloud is completed for the method the page opens with. Colour modes are surfel.colors'
(gl/colors.glsl decodes them in the same passes, with the same tables); eye-dome lighting
is gl/edl.glsl, the twin of surfel.edl, in the page's last pass (display.glsl), which also
box-filters supersamples without mixing categories; before it, pinholes.glsl fills the
samples through which the surface shows what lies behind it, as surfel.pinholes does. The
camera, options and colour mode it opens with are the exporter's (the same request rows as
`surfel render`); everything travels inside the file (gzip-compressed, base64), nothing is
fetched.
"""

from __future__ import annotations

import base64
import gzip
import html
import json
import re
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import colors
from ..camera import Camera, frame
from ..cloud import PointCloud
from ..errors import SurfelError
from ..files import write_atomically
from ..gl.program import expand_includes
from ..methods import DEFAULT_METHOD, get_method
from ..methods.splatting import DEFAULT_SUPERSAMPLES, DeferredParams
from ..options import RenderOptions
from ..request import (
    PAGE_COMMAND,
    PAGE_MAX_SUPERSAMPLE,
    CameraSpec,
    Outputs,
    RenderRequest,
    method_and_backend,
    options_from,
    parse_values,
)
from .pack import pack_cloud

HERE = Path(__file__).parent
SPLATTING = HERE.parent / "methods" / "splatting.glsl"
GL = HERE.parent / "gl"
METHODS = ("phong", "deferred", "gaussian")   # the methods of splatting.glsl the page offers
PAGE_COLORMAPS = ("viridis", "turbo", "inferno", "cividis", "terrain", "gray")  # its menu
DEFAULT_POINT_BUDGET = 300_000       # above it the page draws a sequential point tree
DEFAULT_LOD_ERROR = 1.0              # pixels, for a page with a point tree and no --lod-error
SOURCE_MAX_POINTS = 3_000_000        # what a page takes from a hierarchy larger than memory
SOURCE_CUT_ERROR = 0.25              # pixels of the page's size, across the whole hierarchy
VALUE_STEPS = 65534                  # a continuous attribute's 16-bit steps; 65535: not a number
_COMMENT = re.compile(r"//[^\n]*|/\*.*?\*/", re.S)


def shader_sources() -> dict[str, str]:
    """The page's programs, includes resolved and comments dropped (GLSL ES wants ASCII; the
    comments live in the .glsl files)."""
    sources = {"splat": expand_includes(SPLATTING, (HERE,)), "display": expand_includes(HERE / "display.glsl", (GL,)),
               "pinholes": expand_includes(HERE / "pinholes.glsl", ())}
    return {name: "\n".join(line.rstrip() for line in _COMMENT.sub("", text).splitlines() if line.strip())
            for name, text in sources.items()}


def source_cut(source, size) -> tuple[PointCloud, dict]:
    """What the page takes from a LodSource: its uniform cut of at most SOURCE_MAX_POINTS nodes."""
    view = frame(source.center, source.bounding_radius, view="top", geospatial=source.geospatial,
                 size=size, ortho_height=2 * source.bounding_radius)
    return source.select(view, SOURCE_CUT_ERROR, SOURCE_MAX_POINTS)


def check_page_method(method: str) -> None:
    if method not in METHODS:
        offered = f"{', '.join(METHODS[:-1])} or {METHODS[-1]}"
        raise SurfelError(f"--method: the page draws {offered}, not {method!r}")


def cloud_for_page(cloud: PointCloud, method: str, point_budget: int, lod_error: float | None, renderer,
                   cut: bool = False) -> tuple[PointCloud, dict]:
    """What the page draws: the cloud completed for `method` as surfel render would complete
    it (normals, radii, axes; the normal fields that light phong's splats and curve phong's and
    deferred's, except deferred's on a source's `cut`, whose splats surfel render draws flat), as a
    sequential point tree when it holds more than `point_budget` points or a LOD error is asked
    for. Returns (cloud, report)."""
    from ..lod import as_sequential, is_sequential

    report: dict = {}
    m = get_method(method)
    cloud, estimated = renderer.complete(cloud, needs_radii=m.needs_radii, elliptical=m.fits_ellipses(cloud),
                                         normal_field=m.normal_field and (m.fields_per_cut or not cut))
    if estimated:
        report["estimated"] = estimated
    if is_sequential(cloud) or len(cloud) > point_budget or lod_error is not None:  # a loaded tree: its cut
        cloud = as_sequential(cloud)
        report["point_tree"] = len(cloud)
    return cloud, report


def camera_json(camera: Camera, origin: np.ndarray, center: np.ndarray) -> dict:
    """The camera relative to the page's local origin: eye, a target on the viewing axis
    (level with the cloud's centre, the orbit's pivot), the camera's own up and intrinsics."""
    eye = camera.eye - origin
    forward = camera.forward
    distance = max(float(np.dot(center - origin - eye, forward)), 1e-9)
    return {"eye": eye.tolist(), "target": (eye + forward * distance).tolist(),
            "up": camera.world_to_eye[1, :3].tolist(), "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
            "cy": camera.cy, "width": camera.width, "height": camera.height, "ortho_height": camera.ortho_height}


def table_rows(table: np.ndarray) -> list:
    """A colour table as 8-bit rows for the page (its entries are already multiples of 1/255)."""
    return np.round(np.asarray(table) * 255).astype(int).tolist()


def color_modes(cloud: PointCloud, options: RenderOptions) -> tuple[list, dict]:
    """The colour modes the page offers for `cloud` (colors.offered) and each one's 16-bit
    point values. A mode is {"name", "kind", and: "range" [lo, hi] in the data's units and
    "quantized" [min, max] the 16 bits span (continuous attributes; elevation: "offset", the
    local origin's elevation, since the page's positions are local), "palette" and
    "code_levels" (categorical)}; the options' colour mode opens with their range."""
    modes, values = [], {}
    up = colors.up_axis(cloud)
    names = colors.offered(cloud)
    if options.coloring.name not in (colors.attribute_name(name, cloud) for name in names):
        names.append(options.coloring.name)
    for name in names:
        chosen = colors.attribute_name(name, cloud) == options.coloring.name
        coloring = options.coloring if chosen else colors.resolve(cloud, name, options.colormap)
        mode: dict = {"name": name, "kind": coloring.kind}
        if coloring.categorical:
            values[name] = coloring.indices(coloring.encode(cloud)).astype(np.uint16)
            mode.update(palette=table_rows(coloring.table), code_levels=coloring.code_levels)
        elif coloring.continuous:
            mode["range"] = list(coloring.range)
            if name == colors.ELEVATION:
                mode["offset"] = float(cloud.local_origin @ up)
            else:
                data = np.asarray(coloring.values(cloud), np.float64)
                finite = np.isfinite(data)
                lo, hi = (float(data[finite].min()), float(data[finite].max())) if finite.any() else (0.0, 1.0)
                steps = np.round((np.where(finite, data, lo) - lo) / max(hi - lo, 1e-30) * VALUE_STEPS)
                values[name] = np.where(finite, steps, VALUE_STEPS + 1).astype(np.uint16)
                mode["quantized"] = [lo, hi]
        modes.append(mode)
    return modes, values


def export_html(cloud, camera: Camera, output, *, method: str = DEFAULT_METHOD, options: RenderOptions | None = None,
                renderer=None, title: str | None = None) -> dict:
    """Write the page of `cloud` (a PointCloud or a LodSource) seen by `camera` to `output`.

    `method`: phong, deferred or gaussian; `options`: surfel render's, with the method's parameters
    (colour mode, colour map and range, --classes/--returns, shading (edl included),
    supersampling, LOD error; point_budget: above it the page draws a sequential point
    tree); `renderer`: the rendering.Renderer that estimates what the cloud lacks. Returns a
    report (points, bytes)."""
    from ..lod.source import is_source
    from ..rendering import Renderer

    options = options or RenderOptions()
    renderer = renderer or Renderer()
    title = title or f"surfel: {getattr(cloud, 'source', None) or getattr(cloud, 'path', None) or 'point cloud'}"
    check_page_method(method)
    if (options.supersample or 1) > PAGE_MAX_SUPERSAMPLE:
        raise SurfelError(f"--supersample: the page takes at most {PAGE_MAX_SUPERSAMPLE}, got {options.supersample}")
    m = get_method(method)
    m.check_options(options)
    params = options.params if options.params is not None else m.make_params()
    cut = None
    if is_source(cloud):
        cloud, cut = source_cut(cloud, camera.size)
    cloud, options = renderer.appearance(cloud, options)  # --classes, --returns, the data's defaults
    page_cloud, report = cloud_for_page(cloud, method, options.point_budget or DEFAULT_POINT_BUDGET,
                                        options.lod_error, renderer, cut=cut is not None)
    if cut is not None:
        report["source_cut"] = cut
    page_options = replace(options, coloring=colors.resolve(page_cloud, options.coloring.name, options.colormap,
                                                            options.coloring.range))
    modes, values = color_modes(page_cloud, page_options)
    layout, blob = pack_cloud(page_cloud, values)
    origin = page_cloud.local_origin
    initial = next(m for m in modes if colors.attribute_name(m["name"], page_cloud) == page_options.coloring.name)
    settings = {"method": method, "ewa_filter": bool(params.ewa_filter),
                "ewa_given": options.params is not None and params.ewa_filter != m.make_params().ewa_filter,
                # each method's own default, which the page takes on switching (unless given)
                "ewa_defaults": {name: get_method(name).make_params().ewa_filter for name in METHODS},
                # deferred's normals (splatting.DeferredParams), also on switching to it
                "phong_normals": bool(getattr(params, "phong_normals", DeferredParams.phong_normals)),
                "shading": options.shading, "background": list(options.background),
                "supersample": options.supersample or DEFAULT_SUPERSAMPLES[method],
                "supersample_given": options.supersample is not None,
                # each method's own still-frame sampling, which the page takes on switching (unless given)
                "supersample_defaults": {name: DEFAULT_SUPERSAMPLES[name] for name in METHODS},
                "radius_scale": params.radius_scale,
                "depth_offset": params.depth_offset, "lowpass_radius": params.lowpass_radius,
                "backface_culling": bool(params.backface_culling),
                "lod_error": options.lod_error if options.lod_error is not None else
                (DEFAULT_LOD_ERROR if "lod" in layout["columns"] else 0),
                "color": initial["name"], "colormap": options.colormap, "range": initial.get("range", [0, 1]),
                "edl_strength": options.edl_strength, "edl_radius": options.edl_radius}
    maps = dict.fromkeys((options.colormap, *PAGE_COLORMAPS))
    meta = {"camera": camera_json(camera, origin, page_cloud.center), "settings": settings, "modes": modes,
            "colormaps": {name: table_rows(colors.colormap_table(name)) for name in maps},
            "up": colors.up_axis(page_cloud).tolist(), "data": layout, "neutral": list(colors.NEUTRAL),
            "code_scale": colors.CODE_SCALE, "value_steps": VALUE_STEPS,
            "sphere": {"center": (page_cloud.center - origin).tolist(), "radius": page_cloud.bounding_radius}}
    parts = {"TITLE": html.escape(title),
             "META": _script_json(meta), "SHADERS": _script_json(shader_sources()),
             "DATA": base64.b64encode(gzip.compress(blob, 6, mtime=0)).decode("ascii"),
             "SCRIPT": (HERE / "viewer.js").read_text()}
    page = re.sub(r"\{\{(\w+)\}\}", lambda match: parts[match.group(1)], (HERE / "page.html").read_text())
    write_atomically(output, page.encode("utf-8"))
    return {"output": str(output), "points": len(page_cloud), "bytes": len(page), "data_bytes": len(blob),
            "shading": options.shading, **page_options.coloring.describe(), **report}


def page_request(values: Mapping[str, object]) -> RenderRequest:
    """The request `surfel export-html` makes with these option values (request.PAGE_COMMAND):
    its page is `outputs.png`; the options' point_budget is the size above which the page
    draws a sequential point tree. Checked before anything is loaded, like `surfel render`'s."""
    parsed = parse_values(values, PAGE_COMMAND)
    if parsed.get("demo", False) == ("input" in parsed):
        raise SurfelError("give an input file or --demo (not both)")
    method, _ = method_and_backend(parsed)
    check_page_method(method)
    options = options_from(parsed, method)
    if (options.supersample or 1) > PAGE_MAX_SUPERSAMPLE:
        raise SurfelError(f"--supersample: the page takes at most {PAGE_MAX_SUPERSAMPLE}, got {options.supersample}")
    return RenderRequest(parsed.get("input"), parsed.get("demo", False), method, None,
                         CameraSpec.from_parsed(parsed), options, Outputs(png=parsed["output"]))


def _script_json(value) -> str:
    """JSON safe inside a <script> element."""
    return json.dumps(value, separators=(",", ":")).replace("</", "<\\/")
