"""The parameters the splat methods share, declared once; each method's own dataclass
extends one of these (`Method.params` in the registry names it).

    RadiusParams  points: the splat radius r_k = radius_scale x the radius of the cloud
    SplatParams   gaussian, deferred, phong, object-space, ewa: the blended splats of a
                  visibility pass, whose threshold is z_t = depth_offset x r_k (Botsch &
                  Kobbelt 2003; Zwicker et al. 2001; capped where another surface lies
                  closer, preprocess/thickness.py), a screen-space low-pass of
                  lowpass_radius pixels, and back-face culling
"""

from __future__ import annotations

from dataclasses import dataclass

from ..options import Settings, non_negative, positive, setting


@dataclass(frozen=True)
class RadiusParams(Settings):
    radius_scale: float = setting(1.0, positive)  # multiplies every splat radius


@dataclass(frozen=True)
class SplatParams(RadiusParams):
    depth_offset: float = setting(1.0, non_negative)  # z_t as a fraction of the splat radius
    backface_culling: bool = False  # drop splats whose normal faces away from the camera
    lowpass_radius: float = setting(1.0, positive)  # screen-space low-pass radius in output pixels
