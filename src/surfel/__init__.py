"""surfel: render point clouds as continuous, hole-free, anti-aliased surfaces."""

from .cloud import PointCloud
from .errors import InputError, SurfelError

__all__ = ["PointCloud", "InputError", "SurfelError"]
__version__ = "0.1.0"
