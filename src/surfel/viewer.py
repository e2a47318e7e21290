"""`surfel view`: an interactive window (GLFW, the optional `view` extra).

Frames are rendered by the same headless pipeline as `surfel render`, by the viewer's own
Renderer, and shown in the window through a textured full-screen triangle, with the status
line (method, time, splats, shading, colour mode and its range) and help drawn over them.
The keys set options wherever the method has them (`request.render_options`): the EWA
filter starts at each method's own default, as on the command line; colour mode and shading
start at the data's defaults (surfel.colors, surfel.shading). A geospatial tile opens in an
oblique view (OBLIQUE_ELEVATION degrees) framed by its extent, and keeps that distance as the
camera orbits.

While the camera moves, frames are drawn at half the window's resolution (each pixel shown
2x2), at MOVING_LOD_FACTOR times the LOD error the keys chose, and, while they take longer than
MOTION_FRAME_MS, at a coarser level of detail still (the sequential point tree's
projected-error cut, doubled per slow frame and halved per fast one); once it stops, the view
is drawn again in full, at the detail the keys chose. The notebook widget moves the same way. So a
million-point tile stays interactive on a software rasterizer without giving up its still frame.

    mouse: left drag orbits, right drag pans, wheel zooms
    1-9  : choose the method (the order of `surfel methods`)    e: EWA filter on/off
    + -  : LOD error x2 / /2 (0 = full detail)                  s: next shading model
    c    : next colour mode (rgb, elevation, attributes)        l: eye-dome lighting on/off
    b    : back-face culling on/off                             h: help on/off
    r    : reset the camera                                     q / Esc: quit
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from . import colors
from .camera import default_up, frame, view_direction
from .cloud import PointCloud
from .errors import SurfelError
from .methods import DEFAULT_METHOD, METHODS, get_method
from .rendering import Renderer
from .request import VIEW_SIZE, default, parse_values, render_options
from .shading import DEFAULT as DEFAULT_SHADING
from .shading import EDL, MODELS, default_for

OBLIQUE_ELEVATION = 35.0  # degrees: how a geospatial tile opens
MOVING_LOD_FACTOR = 4.0  # a moving frame's LOD error / the still frame's (when that is not 0)
MOTION_FRAME_MS = 150.0  # a moving frame: coarser detail until it takes no longer (7 frames a second)
MAX_MOTION_ERROR = 8.0  # pixels: coarser cuts turn a canopy into blobs
MOTION_SETTLE_S = 0.25  # the camera counts as stopped after this long without a drag or a wheel step
# the key table of the docstring, shown over the frames (found by its first line, so that a
# paragraph added above it does not take its place)
HELP = next([line.strip() for line in paragraph.splitlines() if line.strip()]
            for paragraph in __doc__.split("\n\n") if paragraph.lstrip().startswith("mouse:"))
VERTEX = """#version 330
out vec2 uv;
void main() {
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    uv = vec2(p.x, 1.0 - p.y);  // image rows go top to bottom
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}"""
FRAGMENT = """#version 330
uniform sampler2D image;
in vec2 uv;
out vec4 color;
void main() { color = vec4(texture(image, uv).rgb, 1.0); }"""


class ViewState:
    """What the keys and the mouse change; everything a frame needs to render."""

    def __init__(self, cloud, method: str, shading: str | None = None, renderer: Renderer | None = None, *,
                 color: str | None = None, colormap: str = colors.DEFAULT_COLORMAP,
                 motion_frame_ms: float = MOTION_FRAME_MS):
        self.cloud = cloud
        self.methods = [m.name for m in METHODS.values() if m.name != "mesh" or getattr(cloud, "is_mesh", False)]
        self.method = method
        self.shading = shading or default_for(cloud)
        self.lit = self.shading if self.shading != EDL else DEFAULT_SHADING  # what `l` turns EDL off to
        self.colors = colors.offered(cloud)
        # None: the data's default, decided per frame (a LodSource's cut shows whether it has colours)
        self.color = color or (colors.default_color(cloud) if isinstance(cloud, PointCloud) else None)
        if self.color is not None and self.color not in self.colors:
            self.colors.append(self.color)
        self.colormap = colormap
        self.renderer = renderer or Renderer()
        self.distance: tuple | None = None  # (size, distance) of a geospatial tile's framing
        self.ewa_filter: bool | None = None  # None: the method's own default
        self.lod_error = 0.0
        self.motion_frame_ms = motion_frame_ms
        self.moving = False
        self.motion_error = 0.0  # the extra projected error (pixels) while moving, adapted per frame
        self.backface_culling = False
        self.show_help = True
        self.reset()

    def reset(self):
        self.azimuth, self.zoom = 0.0, 1.0
        self.elevation = OBLIQUE_ELEVATION if self.cloud.geospatial else 0.0
        self.pan = np.zeros(3)

    def camera(self, size):
        c = self.cloud
        if not c.geospatial:
            return frame(c.center, c.bounding_radius, azimuth=self.azimuth, elevation=self.elevation,
                         geospatial=False, size=size, zoom=self.zoom, target=c.center + self.pan)
        if self.distance is None or self.distance[0] != tuple(size):  # the whole tile, seen obliquely
            start = frame(c.center, c.bounding_radius, azimuth=0.0, elevation=OBLIQUE_ELEVATION, geospatial=True,
                          size=size, bounds=c.bounds)
            self.distance = (tuple(size), float(np.linalg.norm(start.eye - c.center)))
        direction, _ = view_direction(None, default_up(True), self.azimuth, self.elevation)
        target = c.center + self.pan
        return frame(c.center, c.bounding_radius, eye=target + direction * self.distance[1] * self.zoom,
                     target=target, geospatial=True, size=size)

    def key(self, name: str) -> bool:
        """Apply a key; False to quit."""
        if name in ("q", "escape"):
            return False
        if name.isdigit() and 1 <= int(name) <= len(self.methods):
            self.method = self.methods[int(name) - 1]
        elif name == "e" and self.ewa_filter_on() is not None:
            self.ewa_filter = not self.ewa_filter_on()
        elif name in ("+", "="):
            self.lod_error = 1.0 if self.lod_error == 0 else self.lod_error * 2
        elif name == "-":
            self.lod_error = 0.0 if self.lod_error <= 1.0 else self.lod_error / 2
        elif name == "s":
            self.shading = MODELS[(MODELS.index(self.shading) + 1) % len(MODELS)]
        elif name == "c":
            now = self.colors.index(self.color) if self.color in self.colors else -1
            self.color = self.colors[(now + 1) % len(self.colors)]
        elif name == "l":
            if self.shading != EDL:
                self.lit = self.shading
            self.shading = self.lit if self.shading == EDL else EDL
        elif name == "b":
            self.backface_culling = not self.backface_culling
        elif name == "h":
            self.show_help = not self.show_help
        elif name == "r":
            self.reset()
        return True

    def ewa_filter_on(self) -> bool | None:
        """Whether the method filters with the EWA approximation; None if it has no such setting."""
        m = get_method(self.method)
        if not m.uses("ewa_filter"):
            return None
        return m.make_params().ewa_filter if self.ewa_filter is None else self.ewa_filter

    def frame_lod_error(self) -> float:
        """The level of detail of the next frame: the keys' choice, coarser while moving."""
        if not self.moving:
            return self.lod_error
        return max(self.lod_error * MOVING_LOD_FACTOR, self.motion_error)

    def render(self, size):
        """The next frame for a window of `size`: while moving, at half its resolution and one
        sample a pixel (a still frame takes the method's supersampling)."""
        if self.moving:
            size = (max(1, size[0] // 2), max(1, size[1] // 2))
        values = {"shading": self.shading, "color": self.color, "colormap": self.colormap,
                  "backface_culling": self.backface_culling, "ewa_filter": self.ewa_filter,
                  "lod_error": self.frame_lod_error() or None, "supersample": 1 if self.moving else None}
        options = render_options(self.method, values, strict=False)
        start = time.perf_counter()
        result = self.renderer.render(self.cloud, self.camera(size), self.method, options=options)
        ms = (time.perf_counter() - start) * 1000
        self.adapt_motion_detail(ms)
        return result, ms

    def adapt_motion_detail(self, ms: float) -> None:
        """Coarser while frames are slow, finer while fast. A slow still frame starts the next
        movement coarse, so its first dragged frame does not stall."""
        if not self.moving:
            if ms > self.motion_frame_ms and self.motion_error == 0:
                self.motion_error = 2.0
        elif ms > self.motion_frame_ms:
            self.motion_error = min(MAX_MOTION_ERROR, max(1.0, self.motion_error * 2))
        elif ms < self.motion_frame_ms / 3:
            self.motion_error = 0.0 if self.motion_error <= 1.0 else self.motion_error / 2


def color_status(stats: dict) -> str:
    """The colour mode as the status line shows it: its name, and its map and range."""
    if "color_range" in stats:
        lo, hi = stats["color_range"]
        return f"{stats['color']} {stats['colormap']} {lo:.4g}..{hi:.4g}"
    return stats.get("color", "rgb")


def annotate(rgb: np.ndarray, state: ViewState, result, ms: float) -> np.ndarray:
    """The status line (method, frame time, splats) and, if on, the help, drawn into the image."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(rgb)
    draw = ImageDraw.Draw(image)
    error = state.frame_lod_error()
    lod = f"  lod {error:g}px" if error else ""
    ewa = state.ewa_filter_on()
    ewa = "" if ewa is None else f"  ewa filter {'on' if ewa else 'off'}"
    status = (f"{state.method}@{result.stats['backend']}  {ms:.0f} ms  {result.stats['splats']} splats"
              f"  {state.shading}  {color_status(result.stats)}{lod}{ewa}")
    draw.rectangle([0, 0, image.width, 16], fill=(0, 0, 0))
    draw.text((4, 2), status, fill=(255, 255, 255))
    if state.show_help:
        lines = HELP + ["methods: " + ", ".join(f"{i + 1} {m}" for i, m in enumerate(state.methods))]
        top = image.height - 14 * len(lines) - 8
        draw.rectangle([0, top, image.width, image.height], fill=(0, 0, 0))
        for i, line in enumerate(lines):
            draw.text((4, top + 4 + 14 * i), line, fill=(220, 220, 220))
    return np.asarray(image)


def view_command(values: dict, screenshot=None) -> None:
    """`surfel view`: the options parsed as the other commands parse them, then the window."""
    parsed = parse_values(values, ("input", "demo", "method", "shading", "color", "colormap", "size"))
    if parsed.get("demo", False) == ("input" in parsed):
        raise SurfelError("give an INPUT file or --demo (not both)")
    method = default("method", parsed)
    get_method(method)
    if parsed.get("demo"):
        from .data import demo_cloud

        cloud = demo_cloud()
    else:
        from .io import load

        cloud = load(parsed["input"])
    if "color" in parsed:
        colors.resolve(cloud, parsed["color"])  # an attribute the cloud lacks: refused before the window opens
    view(cloud, method=method, shading=parsed.get("shading"), color=parsed.get("color"),
         colormap=parsed.get("colormap", colors.DEFAULT_COLORMAP), size=parsed.get("size", VIEW_SIZE),
         screenshot=screenshot)


def view(cloud, *, method: str = DEFAULT_METHOD, shading: str | None = None, color: str | None = None,
         colormap: str = colors.DEFAULT_COLORMAP, size=VIEW_SIZE, screenshot=None) -> None:
    """Open the window; with `screenshot`, draw one frame, save what the window shows, close."""
    try:
        import glfw
    except ImportError:
        raise SurfelError("the viewer needs GLFW: pip install 'surfel[view]'") from None
    import moderngl

    with warnings.catch_warnings():  # GLFW warns of a missing display: the error below says it in one line
        warnings.simplefilter("ignore", glfw.GLFWError)
        if not glfw.init():
            raise SurfelError("cannot open a window (no display?); set DISPLAY or run under Xvfb")
    state = None
    try:
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.VISIBLE, True)
        window = glfw.create_window(size[0], size[1], f"surfel: {cloud.source or 'cloud'}", None, None)
        if not window:
            raise SurfelError("cannot open an OpenGL 3.3 window on this display")
        glfw.make_context_current(window)
        ctx = moderngl.create_context()
        program = ctx.program(vertex_shader=VERTEX, fragment_shader=FRAGMENT)
        triangle = ctx.vertex_array(program, [])
        state = ViewState(cloud, method, shading, Renderer(), color=color, colormap=colormap)
        drag = {"button": None, "x": 0.0, "y": 0.0}
        dirty = [True]
        last_motion = [0.0]

        def moved():
            state.moving, last_motion[0], dirty[0] = True, time.monotonic(), True

        def on_key(_w, key, _scancode, action, _mods):
            if action != glfw.PRESS:
                return
            name = {glfw.KEY_ESCAPE: "escape", glfw.KEY_KP_ADD: "+", glfw.KEY_KP_SUBTRACT: "-"}.get(key)
            name = name or (glfw.get_key_name(key, 0) or "")
            if not state.key(name.lower()):
                glfw.set_window_should_close(window, True)
            dirty[0] = True

        def on_button(_w, button, action, _mods):
            drag["button"] = button if action == glfw.PRESS else None
            drag["x"], drag["y"] = glfw.get_cursor_pos(window)

        def on_move(_w, x, y):
            if drag["button"] is None:
                return
            dx, dy = x - drag["x"], y - drag["y"]
            drag["x"], drag["y"] = x, y
            if drag["button"] == glfw.MOUSE_BUTTON_LEFT:
                state.azimuth -= 0.4 * dx
                state.elevation = max(-89.0, min(89.0, state.elevation + 0.4 * dy))
            else:
                cam = state.camera(size)
                scale = 2 * cloud.bounding_radius * state.zoom / size[1]
                right, up = cam.world_to_eye[0, :3], cam.world_to_eye[1, :3]
                state.pan += scale * (-dx * right + dy * up)
            moved()

        def on_scroll(_w, _dx, dy):
            state.zoom *= math.pow(0.9, dy)
            moved()

        glfw.set_key_callback(window, on_key)
        glfw.set_mouse_button_callback(window, on_button)
        glfw.set_cursor_pos_callback(window, on_move)
        glfw.set_scroll_callback(window, on_scroll)
        texture = None
        while not glfw.window_should_close(window):
            if (state.moving and drag["button"] is None
                    and time.monotonic() - last_motion[0] > MOTION_SETTLE_S):
                state.moving, dirty[0] = False, True  # stopped: the still frame at full detail
            if dirty[0]:
                width, height = glfw.get_framebuffer_size(window)
                result, ms = state.render((width, height))
                glfw.make_context_current(window)  # rendering used the headless context
                rgb = np.round(np.clip(result.color, 0, 1) * 255).astype(np.uint8)
                rows = np.arange(height) * rgb.shape[0] // height  # a moving frame's pixels, shown 2x2
                rgb = annotate(rgb[rows][:, np.arange(width) * rgb.shape[1] // width], state, result, ms)
                if texture is None or texture.size != (width, height):
                    texture = ctx.texture((width, height), 3)
                texture.write(np.ascontiguousarray(rgb).tobytes())
                ctx.screen.use()
                ctx.viewport = (0, 0, width, height)
                texture.use(0)
                triangle.render(moderngl.TRIANGLES, vertices=3)
                glfw.swap_buffers(window)
                dirty[0] = False
                if screenshot is not None:
                    save_window(ctx, width, height, screenshot)
                    break
            glfw.wait_events_timeout(0.1)
    finally:
        if state is not None:
            from .gl.context import get_context

            with get_context():  # the Renderer's objects live in the headless context
                state.renderer.close()
        glfw.terminate()


def save_window(ctx, width: int, height: int, path) -> None:
    """What the window shows (its front buffer after the swap), as a PNG."""
    import io

    from PIL import Image

    from .files import write_atomically

    pixels = np.frombuffer(ctx.screen.read(viewport=(0, 0, width, height), components=3), np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels.reshape(height, width, 3)[::-1]).save(buffer, format="PNG")
    write_atomically(path, buffer.getvalue())
