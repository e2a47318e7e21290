"""`surfel.show` in Jupyter: any method, rendered where the kernel runs, streamed as frames.

The view is a remote frame buffer (jupyter_rfb, MIT; the optional `notebook` extra): the
kernel renders each frame with surfel.render (every method, .lod hierarchies and COPC files
read lazily as far as the view needs) and the widget sends it to the browser, JPEG while the
camera moves and a lossless PNG when it rests; the browser sends back mouse events. Left drag
orbits, right drag pans, the wheel zooms (surfel.viewer.ViewState, the desktop viewer's
camera). While the camera moves, frames are rendered at half resolution and, for large
clouds and hierarchies, at MOVING_LOD_FACTOR times the LOD error, so they come at
interactive rates; SETTLE_S after the last event a full frame replaces them. ipywidgets
controls pick the method, colour mode, colour map, shading model and LOD error; the status
line reports each frame's time and splat count.
"""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np

from .cloud import PointCloud
from .errors import SurfelError
from .methods import METHODS, get_method
from .rendering import complete
from .shading import MODELS
from .viewer import ViewState
from .web import colors

MOVING_LOD_FACTOR = 4
MOVING_DOWNSAMPLE = 2
SETTLE_S = 0.3
LARGE_CLOUD = 300_000  # above this many points, moving frames use a coarser LOD too


def _require():
    try:
        import ipywidgets
        import jupyter_rfb
    except ImportError as exc:
        raise SurfelError(f"the notebook widget needs {exc.name}: pip install 'surfel[notebook]'") from None
    return ipywidgets, jupyter_rfb


def recolor(cloud: PointCloud, mode: str, colormap: str) -> PointCloud:
    """`cloud` with its colours replaced by colour mode `mode` (web.colors' tables): the
    albedo every method then splats. Categorical codes take their palette's colours."""
    if not isinstance(cloud, PointCloud):
        raise SurfelError(f"color {mode!r}: a level-of-detail source shows its own colours (rgb)")
    up = np.array([0.0, 0.0, 1.0]) if cloud.geospatial else np.array([0.0, 1.0, 0.0])
    modes, values = colors.attribute_modes(cloud, up, None, mode)
    spec = next(m for m in modes if m["name"] == mode)
    if spec["kind"] == "rgb":
        return cloud
    if spec["kind"] == "categorical":
        table = np.asarray(spec["palette"], np.float32) / 255
        return cloud.with_(colors=table[values[mode] % colors.LUT_SIZE])
    data = cloud.positions @ up if mode == "elevation" else cloud.attributes[mode]
    lo, hi = spec["range"]
    t = np.clip((data - lo) / max(hi - lo, 1e-30), 0, 1)
    table = colors.colormap_table(colormap).astype(np.float32) / 255
    return cloud.with_(colors=table[np.round(t * (colors.LUT_SIZE - 1)).astype(np.int64)])


def make_view(cloud, *, method: str = "deferred", shading: str = "phong", size=(512, 512),
              color: str = "rgb", colormap: str = colors.DEFAULT_COLORMAP, lod_error: float | None = None):
    """The widget: controls above a SurfelFrames view (`widget.frames`) and a status line."""
    ipywidgets, jupyter_rfb = _require()

    class SurfelFrames(jupyter_rfb.RemoteFrameBuffer):
        """Frames of a ViewState, rendered on demand, moving frames coarse."""

        _event_compatibility = 2  # events as {"type": ...}

        def __init__(self):
            super().__init__(css_width=f"{size[0]}px", css_height=f"{size[1]}px", resizable=True)
            # OpenGL contexts are current in one thread: frames are rendered in the thread that
            # made the widget (the kernel's main thread), whichever thread asks for them
            self.render_thread = threading.get_ident()
            try:
                self.render_loop = asyncio.get_running_loop()
            except RuntimeError:
                self.render_loop = None
            self.size = tuple(size)
            self.moving = False
            self.drag = None
            self.settle_handle = None
            self.last_stats: dict = {}

        def handle_event(self, event):
            kind = event.get("type")
            if kind == "resize":
                ratio = event.get("ratio", 1.0)
                self.size = (max(int(event["width"] * ratio), 16), max(int(event["height"] * ratio), 16))
                return
            if kind == "pointer_down":
                self.drag = (event["x"], event["y"], event.get("button", 1))
                return
            if kind == "pointer_up":
                self.drag = None
                self.settle_later()
                return
            if kind == "pointer_move" and self.drag is not None:
                x0, y0, button = self.drag
                self.drag = (event["x"], event["y"], button)
                move(event["x"] - x0, event["y"] - y0, pan="Shift" in event.get("modifiers", ()) or button == 2)
            elif kind == "wheel":
                state.zoom *= 0.9 ** (-event["dy"] / 100)
            else:
                return
            self.moving = True
            if self.drag is None:
                self.settle_later()
            self.request_draw()

        def settle_later(self):
            if self.settle_handle is not None:
                self.settle_handle.cancel()
            try:
                self.settle_handle = asyncio.get_running_loop().call_later(SETTLE_S, self.settle)
            except RuntimeError:  # no event loop (plain Python): the caller settles
                self.settle_handle = None

        def settle(self):
            self.moving = False
            self.request_draw()

        def get_frame(self):
            if self.render_loop is None or threading.get_ident() == self.render_thread:
                return self.render_frame()
            self.render_loop.call_soon_threadsafe(self.render_and_send)
            return None

        def render_and_send(self):
            frame = self.render_frame()
            if frame is not None:
                self.send_frame(frame)

        def render_frame(self):
            scale = MOVING_DOWNSAMPLE if self.moving else 1
            frame_size = (max(self.size[0] // scale, 8), max(self.size[1] // scale, 8))
            if self.moving and coarse:
                state.lod_error = max(lod_box.value, 1.0) * MOVING_LOD_FACTOR
            else:
                state.lod_error = lod_box.value
            start = time.perf_counter()
            try:
                result, _ = state.render(frame_size)
            except SurfelError as exc:
                status.value = f"surfel: {exc}"
                return None
            ms = (time.perf_counter() - start) * 1000
            self.last_stats = {**result.stats, "frame_ms": ms, "moving": self.moving}
            status.value = (f"{ms:.0f} ms · {result.stats['splats']:,} of {result.stats['points']:,} splats · "
                            f"{frame_size[0]}x{frame_size[1]}{' (moving)' if self.moving else ''} · "
                            f"{state.method}@{result.stats['backend']}")
            return result.rgba8()[..., :3]

    is_source = not isinstance(cloud, PointCloud)
    if not is_source:
        cloud, _ = complete(cloud)
    coarse = is_source or len(cloud) > LARGE_CLOUD
    base = cloud
    state = ViewState(cloud, method, shading)
    state.methods = [m.name for m in METHODS.values()
                     if get_method(m.name).needs_radii or (m.name == "mesh" and not is_source and cloud.is_mesh)]
    if method not in state.methods:
        raise SurfelError(f"method {method!r} cannot show {'this source' if is_source else 'this cloud'}; "
                          f"choose one of {', '.join(state.methods)}")
    modes = ["rgb"] if is_source else [m["name"] for m in colors.attribute_modes(
        cloud, np.array([0.0, 0.0, 1.0]) if cloud.geospatial else np.array([0.0, 1.0, 0.0]), None, "rgb")[0]]
    if colors.mode_name(color) not in modes:
        raise SurfelError(f"color: no mode {color!r}; choose one of {', '.join(modes)}")
    recolored: dict = {}
    frames = SurfelFrames()
    status = ipywidgets.Label("")

    def move(dx, dy, pan):
        if pan:
            camera = state.camera(frames.size)
            step = 2 * cloud.bounding_radius * state.zoom / frames.size[1]
            state.pan = state.pan + step * (-dx * camera.world_to_eye[0, :3] + dy * camera.world_to_eye[1, :3])
        else:
            state.azimuth -= 0.4 * dx
            state.elevation = max(-89.0, min(89.0, state.elevation + 0.4 * dy))

    method_box = ipywidgets.Dropdown(options=state.methods, value=method, description="method")
    color_box = ipywidgets.Dropdown(options=modes, value=colors.mode_name(color), description="colour")
    map_box = ipywidgets.Dropdown(options=list(dict.fromkeys((colormap, *colors.COLORMAPS))), value=colormap,
                                  description="map")
    shading_box = ipywidgets.Dropdown(options=list(MODELS), value=shading, description="shading")
    lod_box = ipywidgets.BoundedFloatText(value=lod_error or (1.0 if is_source else 0.0), min=0.0, max=64.0,
                                          step=0.5, description="LOD px")

    def changed(_change=None):
        state.method, state.shading = method_box.value, shading_box.value
        if not is_source:
            key = (color_box.value, map_box.value)
            if key not in recolored:
                recolored[key] = recolor(base, *key)
            state.cloud = recolored[key]
        frames.request_draw()

    for box in (method_box, color_box, map_box, shading_box, lod_box):
        box.observe(changed, names="value")
        box.layout = ipywidgets.Layout(width="auto")
    changed()
    controls = ipywidgets.HBox([method_box, color_box, map_box, shading_box, lod_box],
                               layout=ipywidgets.Layout(flex_flow="row wrap"))
    widget = ipywidgets.VBox([controls, frames, status])
    widget.frames = frames
    widget.state = state
    return widget


def widget_frontend() -> bool:
    """True inside a Jupyter kernel with the widget libraries installed."""
    try:
        from IPython import get_ipython
    except ImportError:
        return False
    shell = get_ipython()
    if shell is None or type(shell).__name__ != "ZMQInteractiveShell":
        return False
    try:
        _require()
    except SurfelError:
        return False
    return True
