"""`surfel export-html`: one self-contained HTML file that splats the cloud in the browser.

The page (page.html, viewer.js) runs methods/splatting.glsl itself in WebGL2 (GLSL ES 3.00):
the exporter resolves its includes with the page's splat_attributes.glsl first, which
decodes the quantized columns of pack.py under the attribute names the desktop shaders use.
So the page's `deferred` is Botsch et al. 2005 exactly as `surfel render --method deferred`
draws it: visibility, attribute accumulation and normalization passes, the EWA screen-space
filter approximation, coverage from edge_distance() and surrounded(), point sprites on a
guard band or quads. The camera, options and colour mode it opens with are the exporter's;
everything travels inside the file (gzip-compressed, base64), nothing is fetched.
"""

from __future__ import annotations

import base64
import gzip
import html
import json
import re
from pathlib import Path

import numpy as np

from ..camera import Camera, default_up, frame
from ..cloud import PointCloud
from ..errors import SurfelError
from ..files import write_atomically
from ..gl.program import expand_includes
from ..methods import get_method
from ..options import RenderOptions
from ..rendering import complete
from ..shading import MODELS
from . import colors
from .pack import pack_cloud

HERE = Path(__file__).parent
SPLATTING = HERE.parent / "methods" / "splatting.glsl"
METHODS = ("deferred", "gaussian")   # the methods of splatting.glsl the page offers
SHADINGS = (*MODELS, "edl")
DEFAULT_POINT_BUDGET = 300_000       # above it the page draws a sequential point tree
DEFAULT_LOD_ERROR = 1.0              # pixels, for a page with a point tree and no --lod-error
SOURCE_MAX_POINTS = 3_000_000        # what a page takes from a hierarchy larger than memory
SOURCE_CUT_ERROR = 0.25              # pixels of the page's size, across the whole hierarchy
EDL_STRENGTH = 1.0                   # Potree's defaults
EDL_RADIUS = 1.4
_COMMENT = re.compile(r"//[^\n]*|/\*.*?\*/", re.S)


def shader_sources() -> dict[str, str]:
    """The page's three programs, includes resolved and comments dropped (GLSL ES wants
    ASCII; the comments live in the .glsl files)."""
    first = (HERE,)
    sources = {"splat": expand_includes(SPLATTING, first),
               "category": expand_includes(HERE / "category.glsl", (HERE, SPLATTING.parent)),
               "display": expand_includes(HERE / "display.glsl", first)}
    return {name: "\n".join(line.rstrip() for line in _COMMENT.sub("", text).splitlines() if line.strip())
            for name, text in sources.items()}


def cloud_for_page(cloud, camera: Camera, point_budget: int, lod_error: float | None) -> tuple[PointCloud, dict]:
    """What the page draws: the completed cloud (normals, radii, axes estimated as surfel
    render would), as a sequential point tree when it holds more than `point_budget` points
    or a LOD error is asked for; from a LodSource, its uniform cut of at most
    SOURCE_MAX_POINTS nodes first. Returns (cloud, report)."""
    from ..lod import as_sequential, is_sequential
    from ..lod.source import is_source

    report: dict = {}
    if is_source(cloud):
        view = frame(cloud.center, cloud.bounding_radius, view="top", geospatial=cloud.geospatial,
                     size=camera.size, ortho_height=2 * cloud.bounding_radius)
        cloud, selection = cloud.select(view, SOURCE_CUT_ERROR, SOURCE_MAX_POINTS)
        report["source_cut"] = selection
    method = get_method("deferred")
    cloud, estimated = complete(cloud, need_radii=method.needs_radii, elliptical=method.elliptical,
                                normal_field=method.normal_field)
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


def export_html(cloud, camera: Camera, output, *, method: str = "deferred", options: RenderOptions | None = None,
                color: str | None = None, colormap: str = colors.DEFAULT_COLORMAP,
                color_range: tuple[float, float] | None = None, edl_strength: float = EDL_STRENGTH,
                edl_radius: float = EDL_RADIUS, point_budget: int = DEFAULT_POINT_BUDGET, up=None,
                title: str | None = None) -> dict:
    """Write the page of `cloud` (a PointCloud or a LodSource) seen by `camera` to `output`.

    `method`: deferred or gaussian; `options`: surfel render's (shading may also be "edl");
    `color`: rgb, elevation or an attribute's name (default: rgb); `up`: the elevation and
    orbit axis (default +Z for geospatial data, else +Y). Returns a report (points, bytes)."""
    options = options or RenderOptions()
    title = title or f"surfel: {getattr(cloud, 'source', None) or getattr(cloud, 'path', None) or 'point cloud'}"
    if method not in METHODS:
        raise SurfelError(f"--method: the page draws {' or '.join(METHODS)}, not {method!r}")
    if options.shading not in SHADINGS:
        raise SurfelError(f"--shading: unknown model {options.shading!r}; choose one of {', '.join(SHADINGS)}")
    if options.lod_error is not None and not options.lod_error > 0:
        raise SurfelError(f"--lod-error must be positive, got {options.lod_error}")
    if color_range is not None and not color_range[0] < color_range[1]:
        raise SurfelError(f"--color-range: LO must be below HI, got {color_range[0]:g},{color_range[1]:g}")
    if colormap not in colors.COLORMAPS:
        colors.colormap_table(colormap)  # a bad name fails here, with the reason
    page_cloud, report = cloud_for_page(cloud, camera, point_budget, options.lod_error)
    up = default_up(page_cloud.geospatial) if up is None else np.asarray(up, np.float64) / np.linalg.norm(up)
    initial = colors.mode_name(color or "rgb")
    modes, values = colors.attribute_modes(page_cloud, up, color_range, initial)
    layout, blob = pack_cloud(page_cloud, values)
    origin = page_cloud.local_origin
    ewa = options.ewa_filter if options.ewa_filter is not None else method == "deferred"
    depth_offset = 1.0 if options.depth_offset is None else options.depth_offset
    initial_mode = next(m for m in modes if m["name"] == initial)
    settings = {"method": method, "ewa_filter": bool(ewa), "ewa_given": options.ewa_filter is not None,
                "shading": options.shading, "background": list(options.background),
                "supersample": options.supersample or 1, "radius_scale": options.radius_scale,
                "depth_offset": depth_offset, "lowpass_radius": options.lowpass_radius,
                "backface_culling": bool(options.backface_culling),
                "lod_error": options.lod_error if options.lod_error is not None else
                (DEFAULT_LOD_ERROR if "lod" in layout["columns"] else 0),
                "color": initial, "colormap": colormap, "range": initial_mode.get("range", [0, 1]),
                "edl_strength": edl_strength, "edl_radius": edl_radius}
    maps = dict.fromkeys((colormap, *colors.COLORMAPS))
    meta = {"camera": camera_json(camera, origin, page_cloud.center), "settings": settings, "modes": modes,
            "colormaps": {name: colors.colormap_table(name).tolist() for name in maps},
            "up": up.tolist(), "data": layout,
            "sphere": {"center": (page_cloud.center - origin).tolist(),
                       "radius": page_cloud.bounding_radius}}
    parts = {"TITLE": html.escape(title),
             "META": _script_json(meta), "SHADERS": _script_json(shader_sources()),
             "DATA": base64.b64encode(gzip.compress(blob, 6, mtime=0)).decode("ascii"),
             "SCRIPT": (HERE / "viewer.js").read_text()}
    page = re.sub(r"\{\{(\w+)\}\}", lambda m: parts[m.group(1)], (HERE / "page.html").read_text())
    write_atomically(output, page.encode("utf-8"))
    return {"output": str(output), "points": len(page_cloud), "bytes": len(page), "data_bytes": len(blob), **report}


def _script_json(value) -> str:
    """JSON safe inside a <script> element."""
    return json.dumps(value, separators=(",", ":")).replace("</", "<\\/")
