"""Render options shared by every method (CLI flags map onto these one to one)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RenderOptions:
    """shading        : a model of shading.MODELS
    background     : RGB in [0, 1] the image is composited over
    supersample    : samples per pixel side (None: the method's default)
    radius_scale   : multiplies every splat radius
    depth_offset   : visibility offset z_t as a fraction of the splat radius (None: method default)
    backface_culling: drop splats whose normal faces away from the camera
    ewa_filter     : Botsch et al. 2005 screen-space filter approximation (splat methods)
    lowpass_radius : radius in pixels of the screen-space low-pass filter
    lod_error      : sequential point tree error threshold in pixels (None: full detail; for a
                     lazy LodSource, which cannot be drawn whole, None means 1 pixel)
    point_budget   : most nodes a LodSource's cut may hold (its eps is raised to fit), or None
    dump_passes    : folder to write the intermediate passes to as images
    params         : method-specific settings, documented by each method
    """

    shading: str = "phong"
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    supersample: int | None = None
    radius_scale: float = 1.0
    depth_offset: float | None = None
    backface_culling: bool = False
    ewa_filter: bool | None = None
    lowpass_radius: float = 1.0
    lod_error: float | None = None
    point_budget: int | None = None
    dump_passes: str | None = None
    params: dict = field(default_factory=dict)
