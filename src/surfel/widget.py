"""`surfel.show` in Jupyter: any method, rendered where the kernel runs, streamed as frames.

The view is a remote frame buffer (jupyter_rfb, MIT; the optional `notebook` extra): the
kernel renders each frame with surfel.render (every method, .lod hierarchies and COPC files
read lazily as far as the view needs) and the widget sends it to the browser, JPEG while the
camera moves and a lossless PNG when it rests; the browser sends back mouse events. Left drag
orbits, right drag pans, the wheel zooms (surfel.viewer.ViewState, the desktop viewer's
camera). While the camera moves, frames are rendered as the desktop viewer renders them
(ViewState: half resolution, a coarser LOD, coarser still while frames are slow), so they
come at interactive rates; SETTLE_S after the last event a full frame replaces them. ipywidgets
controls pick the method, colour mode (surfel.colors: every method colours by attribute
itself, categories never blended), colour map, shading model (eye-dome lighting included)
and LOD error; the status line reports each frame's time, splat count, colour mode and range.
The view state (camera, keys' settings, Renderer) is the desktop viewer's (viewer.ViewState).
"""

from __future__ import annotations

import asyncio
import threading

from . import colors
from .cloud import PointCloud
from .errors import SurfelError
from .methods import DEFAULT_METHOD, METHODS
from .shading import MODELS
from .viewer import ViewState, color_status

SETTLE_S = 0.3
WIDGET_COLORMAPS = ("viridis", "turbo", "inferno", "cividis", "terrain", "gray")  # the map menu


def _require():
    try:
        import ipywidgets
        import jupyter_rfb
    except ImportError as exc:
        raise SurfelError(f"the notebook widget needs {exc.name}: pip install 'surfel[notebook]'") from None
    return ipywidgets, jupyter_rfb


def make_view(cloud, *, method: str = DEFAULT_METHOD, shading: str | None = None, size=(512, 512),
              color: str | None = None, colormap: str = colors.DEFAULT_COLORMAP, lod_error: float | None = None):
    """The widget: controls above a SurfelFrames view (`widget.frames`) and a status line.
    shading and color None: the data's defaults (as `surfel render`)."""
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
            state.moving, state.lod_error = self.moving, lod_box.value
            try:
                result, ms = state.render(self.size)
            except SurfelError as exc:
                status.value = f"surfel: {exc}"
                return None
            frame_size = (result.color.shape[1], result.color.shape[0])
            self.last_stats = {**result.stats, "frame_ms": ms, "moving": self.moving}
            status.value = (f"{ms:.0f} ms · {result.stats['splats']:,} of {result.stats['points']:,} splats · "
                            f"{frame_size[0]}x{frame_size[1]}{' (moving)' if self.moving else ''} · "
                            f"{state.method}@{result.stats['backend']} · {result.stats['shading']} · "
                            f"{color_status(result.stats)}")
            return result.rgba8()[..., :3]

    is_source = not isinstance(cloud, PointCloud)
    if color is not None and not is_source:
        colors.resolve(cloud, color)  # an attribute the cloud lacks fails before the widget is built
    state = ViewState(cloud, method, shading, color=color, colormap=colormap)
    state.methods = [m.name for m in METHODS.values()
                     if m.needs_radii or (m.name == "mesh" and not is_source and cloud.is_mesh)]
    if method not in state.methods:
        raise SurfelError(f"method {method!r} cannot show {'this source' if is_source else 'this cloud'}; "
                          f"choose one of {', '.join(state.methods)}")
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
    color_box = ipywidgets.Dropdown(options=[("data default", None)] + [(m, m) for m in state.colors],
                                    value=state.color, description="colour")
    map_box = ipywidgets.Dropdown(options=list(dict.fromkeys((colormap, *WIDGET_COLORMAPS))), value=colormap,
                                  description="map")
    shading_box = ipywidgets.Dropdown(options=list(MODELS), value=state.shading, description="shading")
    lod_box = ipywidgets.BoundedFloatText(value=lod_error or (1.0 if is_source else 0.0), min=0.0, max=64.0,
                                          step=0.5, description="LOD px")

    def changed(_change=None):
        state.method, state.shading = method_box.value, shading_box.value
        state.color, state.colormap = color_box.value, map_box.value
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
