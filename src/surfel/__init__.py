"""surfel: render point clouds as continuous, hole-free, anti-aliased surfaces.

    import surfel
    cloud = surfel.load("bunny.obj")
    image = surfel.render(cloud, method="phong", size=(512, 512))   # shows itself in notebooks
    image.color, image.alpha, image.depth, image.normals              # numpy arrays
    tile = surfel.render(surfel.load("tile.laz"), color="classification", classes=(2, 6))
"""

from . import adapters  # surfel.adapters: Open3D, trimesh, PyVista and numpy, each imported when used
from .cloud import PointCloud
from .errors import InputError, SurfelError
from .io import load, write_ply
from .methods import DEFAULT_METHOD
from .rendering import Renderer, default_camera, render

__all__ = ["PointCloud", "InputError", "SurfelError", "Renderer", "load", "write_ply", "render", "default_camera",
           "show", "adapters"]
__version__ = "0.1.0"


def show(cloud, method: str = DEFAULT_METHOD, size=(512, 512), *, interactive: bool | None = None, **options):
    """Show `cloud` (a PointCloud, or a .lod hierarchy / COPC source from surfel.lod.open_source).

    In a Jupyter kernel with the notebook extra (pip install 'surfel[notebook]'), or with
    interactive=True: an interactive view rendered by the kernel and streamed to the
    browser, with controls for method, colour mode, shading and LOD error (surfel.widget;
    options shading, color, colormap, lod_error). Elsewhere: one frame from the default
    camera (options: those of `render`, color="classification" for instance), displayed
    inline in a notebook, else in the image viewer; returned as a RenderResult.
    """
    import os
    import sys
    import warnings

    from .widget import make_view, widget_frontend

    if interactive is None:
        interactive = widget_frontend()
    if interactive:
        return make_view(cloud, method=method, size=size, **options)
    result = render(cloud, method=method, size=size, **options)
    try:
        from IPython import get_ipython
        from IPython.display import display

        if get_ipython() is not None:
            display(result)
            return result
    except ImportError:
        pass
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        # PIL's viewer would run xdg-open, which fails noisily on a headless machine
        warnings.warn("surfel.show: no display to show the image on; the result is returned "
                      "(result.save('image.png') writes it)", stacklevel=2)
        return result
    from PIL import Image

    Image.fromarray(result.rgba8(), "RGBA").show()
    return result
