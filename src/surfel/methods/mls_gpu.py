"""`mls-gpu`: GPU ray casting of the MLS point set surface (Tejada et al. 2006, survey section
2.3.2); the implementation lives in surfel.mls (gpu.py: the passes, gpu.glsl: their shaders)."""

from __future__ import annotations

from ..mls.gpu import render_mls_gl

__all__ = ["render_mls_gl"]
