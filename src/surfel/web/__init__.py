"""The cloud in a web browser: `export_html` writes one self-contained page that splats it
with WebGL2 (surfel's own splatting shaders, export.py); surfel.widget streams any method
from a notebook's kernel instead."""

from .export import export_html

__all__ = ["export_html"]
