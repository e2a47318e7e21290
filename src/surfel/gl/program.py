"""GLSL loading: one source file per program, stages and passes chosen with #define.

A `.glsl` file holds every stage, guarded by `#ifdef VERTEX_SHADER` / `GEOMETRY_SHADER` /
`FRAGMENT_SHADER`, or `COMPUTE_SHADER` for a compute program of the same source; passes of a
method are further `#define`s. `#include "name.glsl"` pulls in
shared code (resolved relative to the including file, then to the package's gl folder).
Programs are compiled here and kept by their owner (`rendering.Renderer.program`).

Uniforms are set by name (`set_uniforms`), strictly: a name the source does not declare, in
any variant, is an error (a misspelt uniform must fail, not be ignored); a declared uniform
that the compiler removed from this variant, because nothing in it reads the uniform, is
skipped.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .context import get_context

_GL_DIR = Path(__file__).parent
_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.M)
_COMMENT = re.compile(r"//[^\n]*|/\*.*?\*/", re.S)
# "uniform float u_a;", "uniform sampler2D u_b, u_c;", "uniform vec4 u_d[2];"
_UNIFORM = re.compile(r"\buniform\s+\w+\s+([^;{]+);")


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


def declared_uniforms(source: str) -> frozenset[str]:
    """Every uniform name the source declares, whatever #ifdef guards the declaration."""
    names = set()
    for match in _UNIFORM.finditer(_COMMENT.sub("", source)):
        names.update(part.split("[")[0].strip() for part in match.group(1).split(","))
    return frozenset(names)


def _stage(source: str, stage: str, defines: dict) -> str:
    lines = ["#version 430 core", f"#define {stage}"]
    lines += [f"#define {k} {v}" if v is not True else f"#define {k}" for k, v in defines.items() if v is not False]
    return "\n".join(lines) + "\n#line 1\n" + source


def build_program(path: str | Path, defines: dict | None = None, *, geometry: bool = False, compute: bool = False):
    """Compile the program in `path` with these #defines (`compute`: its compute shader);
    `program.extra` holds its source's declared uniform names for `set_uniforms`."""
    ctx = get_context()
    defines = dict(defines or {})
    source = expand_includes(Path(path))
    if compute:
        program = ctx.compute_shader(_stage(source, "COMPUTE_SHADER", defines))
        program.extra = {"source": Path(path).name, "uniforms": declared_uniforms(source)}
        return program
    stages = {"vertex_shader": _stage(source, "VERTEX_SHADER", defines),
              "fragment_shader": _stage(source, "FRAGMENT_SHADER", defines)}
    if geometry:
        stages["geometry_shader"] = _stage(source, "GEOMETRY_SHADER", defines)
    program = ctx.program(**stages)
    program.extra = {"source": Path(path).name, "uniforms": declared_uniforms(source)}
    return program


def set_uniforms(program, **values) -> None:
    """Set uniforms by name: a name the program's source lacks raises KeyError; one the
    compiler removed from this variant is skipped."""
    declared = program.extra["uniforms"]
    for name, value in values.items():
        if name not in declared:
            raise KeyError(f"{program.extra['source']} declares no uniform {name!r}")
        if name not in program:
            continue
        if isinstance(value, np.ndarray):
            if value.shape == (4, 4) or value.shape == (3, 3):
                value = tuple(np.asarray(value, np.float32).T.ravel())  # GLSL is column-major
            else:
                value = tuple(np.asarray(value, np.float32).ravel())
        program[name].value = value
