"""The package's shape (docs/architecture.md): one-way layers, no import cycles (imports inside
functions count), no private names imported across packages, no module over 600 lines."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "surfel"
MAX_LINES = 600

# Lowest first; a module may import from its own layer and those below it.
LAYERS = [
    ("core", ["errors", "files", "attributes", "cloud", "camera", "data", "parsers", "threads", "pages",
              "compile_events"]),
    ("io", ["io"]),
    ("preprocess", ["preprocess"]),
    ("lod", ["lod"]),
    ("appearance", ["shading", "colors", "edl", "pinholes", "options", "result"]),
    ("gl", ["gl"]),
    ("methods", ["methods", "mls"]),
    ("rendering", ["rendering", "compile_ahead", "compile_ahead_worker", "metrics"]),
    ("request", ["request"]),
    ("interfaces", ["cli", "compile_notice", "batch", "viewer", "turntable", "bench", "web", "widget", "adapters",
                    "scan", ""]),
]


def modules() -> dict[str, Path]:
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(["surfel", *parts])] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]):
    """(imported module, imported names) of every import statement in the module, nested ones too."""
    is_package = path.name == "__init__.py"
    package = name.split(".") if is_package else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                yield (sub, ()) if sub in known else (target, (alias.name,))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, ()


def layer_of(module: str) -> int:
    top = module.split(".")[1] if module.count(".") else ""
    for index, (_, members) in enumerate(LAYERS):
        if top in members:
            return index
    raise AssertionError(f"{module} is in no layer of docs/architecture.md (add it to LAYERS)")


def graph() -> dict[str, set[str]]:
    known = modules()
    edges = {name: set() for name in known}
    for name, path in known.items():
        for target, _ in imports(name, path, known):
            if target in known and target != name:
                edges[name].add(target)
    return edges


def test_layers_depend_one_way():
    wrong = []
    for name, targets in graph().items():
        for target in targets:
            if name.startswith(target + "."):  # a module importing its own package's __init__
                continue
            if layer_of(target) > layer_of(name):
                wrong.append(f"{name} ({LAYERS[layer_of(name)][0]}) imports {target} ({LAYERS[layer_of(target)][0]})")
    assert not wrong, "\n".join(sorted(wrong))


def test_no_import_cycles():
    edges = graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(edges[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(path[path.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    assert not cycles, "\n".join(cycles)


def test_no_private_names_across_packages():
    known = modules()
    wrong = []
    for name, path in known.items():
        for target, names in imports(name, path, known):
            if not target.startswith("surfel"):
                continue
            own = name.split(".")[:2]
            for imported in names:
                if imported.startswith("_") and target.split(".")[:2] != own:
                    wrong.append(f"{name} imports {target}.{imported}")
    assert not wrong, "\n".join(wrong)


def test_no_module_over_600_lines():
    long = {name: len(path.read_text().splitlines()) for name, path in modules().items()}
    assert not {n: c for n, c in long.items() if c > MAX_LINES}
