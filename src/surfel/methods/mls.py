"""`mls`: ray tracing the MLS point set surface (Adamson & Alexa 2003, survey section 2.3);
the implementation lives in surfel.mls (surface.py: projection operator, raytrace.py: tracer)."""

from __future__ import annotations

from ..mls.raytrace import render_mls_cpu

__all__ = ["render_mls_cpu"]
