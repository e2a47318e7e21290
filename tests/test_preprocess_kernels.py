"""The preprocessing kernels keep numba's on-disk cache sound.

numba caches a compiled kernel under its own source file's timestamp only: a kernel that called
a numba function, or read a constant, of another module would keep running a stale compiled copy
after that module changed. So every kernel reads only globals its own module defines (besides
modules such as math, numpy and numba, and builtins).
"""

from __future__ import annotations

import ast
import dis
import importlib
import inspect
import pkgutil
import types

import numba.core.dispatcher

import surfel.preprocess as package


def own_names(module: types.ModuleType) -> set[str]:
    """The top-level names the module's source defines itself (not the ones it imports)."""
    names = set()
    for node in ast.parse(inspect.getsource(module)).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names |= {target.id for target in node.targets if isinstance(target, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    return names


def globals_read(code: types.CodeType) -> set[str]:
    names = {i.argval for i in dis.get_instructions(code) if i.opname in ("LOAD_GLOBAL", "LOAD_NAME")}
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= globals_read(const)
    return names


def test_kernels_read_only_their_own_module():
    kernels = 0
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        own = own_names(module)
        for name, value in vars(module).items():
            if not isinstance(value, numba.core.dispatcher.Dispatcher) or value.py_func.__module__ != module.__name__:
                continue
            kernels += 1
            for used in globals_read(value.py_func.__code__):
                target = value.py_func.__globals__.get(used)
                if target is None or isinstance(target, types.ModuleType):
                    continue  # a builtin, or an attribute of math, numpy, numba
                assert used in own, f"{module.__name__}.{name} reads {used!r}, which another module defines"
    assert kernels >= 15
