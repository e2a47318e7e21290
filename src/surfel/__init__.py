"""surfel: render point clouds as continuous, hole-free, anti-aliased surfaces.

    import surfel
    cloud = surfel.load("bunny.obj")
    image = surfel.render(cloud, method="deferred", size=(512, 512))   # shows itself in notebooks
    image.color, image.alpha, image.depth, image.normals              # numpy arrays
"""

from .cloud import PointCloud
from .errors import InputError, SurfelError
from .io import load, write_ply
from .rendering import Renderer, default_camera, render

__all__ = ["PointCloud", "InputError", "SurfelError", "Renderer", "load", "write_ply", "render", "default_camera",
           "show"]
__version__ = "0.1.0"


def show(cloud: PointCloud, method: str = "deferred", size=(512, 512), **options):
    """Render with the default camera and display it: inline in a notebook, else the image viewer."""
    result = render(cloud, method=method, size=size, **options)
    try:
        from IPython import get_ipython
        from IPython.display import display

        if get_ipython() is not None:
            display(result)
            return result
    except ImportError:
        pass
    from PIL import Image

    Image.fromarray(result.rgba8(), "RGBA").show()
    return result
