"""GLSL loading: one source file per program, stages and passes chosen with #define.

A `.glsl` file holds every stage, guarded by `#ifdef VERTEX_SHADER` / `GEOMETRY_SHADER` /
`FRAGMENT_SHADER`; passes of a method are further `#define`s. `#include "name.glsl"` pulls in
shared code (resolved relative to the including file, then to the package's gl folder).
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

from .context import get_context

_GL_DIR = Path(__file__).parent
_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.M)


@cache
def expand_includes(path: Path, first: tuple[Path, ...] = ()) -> str:
    """The source of `path` with its includes resolved, recursively: in the folders `first`
    (the browser page puts its own versions of shared files there), then beside the
    including file, then in the package's gl folder."""
    text = path.read_text()

    def include(match):
        name = match.group(1)
        for folder in (*first, path.parent, _GL_DIR):
            if (folder / name).exists():
                return expand_includes(folder / name, first)
        raise FileNotFoundError(f"{path.name}: cannot include {name}")

    return _INCLUDE.sub(include, text)


def _stage(source: str, stage: str, defines: dict) -> str:
    lines = ["#version 430 core", f"#define {stage}"]
    lines += [f"#define {k} {v}" if v is not True else f"#define {k}" for k, v in defines.items() if v is not False]
    return "\n".join(lines) + "\n#line 1\n" + source


_programs: dict = {}


def build_program(path: str | Path, defines: dict | None = None, *, geometry: bool = False):
    """Compile (once per context, path and defines) the program in `path`."""
    ctx = get_context()
    defines = dict(defines or {})
    key = (id(ctx), str(path), tuple(sorted(defines.items())), geometry)
    if key not in _programs:
        source = expand_includes(Path(path))
        stages = {"vertex_shader": _stage(source, "VERTEX_SHADER", defines),
                  "fragment_shader": _stage(source, "FRAGMENT_SHADER", defines)}
        if geometry:
            stages["geometry_shader"] = _stage(source, "GEOMETRY_SHADER", defines)
        _programs[key] = ctx.program(**stages)
    return _programs[key]


def set_uniforms(program, **values) -> None:
    """Set the uniforms the program actually uses (the compiler drops unused ones)."""
    import numpy as np

    for name, value in values.items():
        if name not in program:
            continue
        if isinstance(value, np.ndarray):
            if value.shape == (4, 4) or value.shape == (3, 3):
                value = tuple(np.asarray(value, np.float32).T.ravel())  # GLSL is column-major
            else:
                value = tuple(np.asarray(value, np.float32).ravel())
        program[name].value = value
