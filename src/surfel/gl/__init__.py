"""Shared OpenGL machinery: the headless context, GLSL loading, framebuffers and readback."""

from .context import get_context, renderer_string
from .program import build_program
from .targets import GBuffer, read_texture

__all__ = ["get_context", "renderer_string", "build_program", "GBuffer", "read_texture"]
