"""The one place surfel creates its OpenGL context.

Headless EGL by default (Mesa's llvmpipe on machines without a GPU, the GPU driver
otherwise); `SURFEL_GL_BACKEND` overrides it (e.g. `x11` for a GLX context on a display,
or `default` for moderngl's platform default).
"""

from __future__ import annotations

import os

from ..errors import NoOpenGLError

REQUIRED_VERSION = 430
INSTALL_HINT = ("install EGL and Mesa (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri libgbm1; "
                "Fedora: dnf install mesa-libEGL mesa-dri-drivers) or use --backend cpu")

_context = None
_failure: str | None = None


def get_context():
    """The process-wide moderngl context, created on first use; NoOpenGLError if impossible."""
    global _context, _failure
    if _context is not None:
        return _context
    if _failure is not None:
        raise NoOpenGLError(_failure)
    backend = os.environ.get("SURFEL_GL_BACKEND", "egl")
    try:
        import moderngl

        kwargs = {} if backend == "default" else {"backend": backend}
        ctx = moderngl.create_context(standalone=True, require=REQUIRED_VERSION, **kwargs)
    except Exception as exc:  # moderngl raises plain Exceptions for missing libraries/drivers
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        version = f"{REQUIRED_VERSION // 100}.{REQUIRED_VERSION % 100 // 10}"
        _failure = f"no OpenGL {version} context ({backend}: {reason}); {INSTALL_HINT}"
        raise NoOpenGLError(_failure) from None
    _context = ctx
    return ctx


def gl_available() -> bool:
    try:
        get_context()
        return True
    except NoOpenGLError:
        return False


def renderer_string() -> str:
    """The GL_RENDERER string, e.g. 'llvmpipe (LLVM 15.0.6, 256 bits)'."""
    return get_context().info["GL_RENDERER"]
