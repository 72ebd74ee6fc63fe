"""The layers of docs/architecture.md, checked on the source: arrows point one way.

core (science, numpy/scipy) <- core.io (file formats) <- app (jobs) <- cli | qgis_plugin |
pdal_filters (faces). The faces never import each other, app never imports a face, core never
imports app or a face, core's science never imports core.io, and no module imports itself
back through a cycle (module-level and function-level imports alike).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP_DIRS = {"tests", "benchmarks", "scripts", ".venv", ".venv-np2", "build", "demo_output"}


def _modules():
    out = {}
    for path in ROOT.rglob("*.py"):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in SKIP_DIRS or rel.parts[0].startswith("."):
            continue
        parts = list(rel.with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(["slipmap", *parts])] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path):
    """Modules of slipmap that ``name`` imports (absolute names)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("slipmap"):
                    found.add(a.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("slipmap"):
                continue
            for a in node.names:
                sub = f"{mod}.{a.name}"
                found.add(sub if sub in MODULES else mod)
    return {m for m in found if m in MODULES and m != name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _layer(name: str) -> str:
    parts = name.split(".")
    if len(parts) == 1:
        return "root"
    if parts[1] == "core":
        return "core.io" if len(parts) > 2 and parts[2] == "io" else "core"
    return parts[1]


ALLOWED = {
    "core": {"core"},
    "core.io": {"core", "core.io"},
    "styles": {"styles"},
    "app": {"core", "core.io", "app", "styles", "_version"},
    "cli": {"core", "core.io", "app", "cli", "styles", "_version"},
    "qgis_plugin": {"core", "core.io", "app", "qgis_plugin", "styles", "_version"},
    "pdal_filters": {"core", "core.io", "app", "pdal_filters", "styles", "_version"},
}


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layers_point_one_way(layer):
    bad = []
    for name, deps in GRAPH.items():
        if _layer(name) != layer:
            continue
        for d in deps:
            if _layer(d) not in ALLOWED[layer]:
                bad.append(f"{name} -> {d}")
    assert not bad, "imports against the layers:\n" + "\n".join(sorted(bad))


def test_core_science_does_not_read_files_or_plot():
    """Science modules of core import neither core.io nor matplotlib."""
    bad = []
    for name, path in MODULES.items():
        if _layer(name) != "core":
            continue
        text = path.read_text(encoding="utf-8")
        if "matplotlib" in text and "import matplotlib" in text:
            bad.append(f"{name} imports matplotlib")
        bad += [f"{name} -> {d}" for d in GRAPH[name] if _layer(d) == "core.io"]
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    """No cycle among slipmap's modules (Tarjan's strongly connected components)."""
    index, low, stack, on, cycles = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in GRAPH.get(v, ()):
            # a package's __init__ importing its own submodules is not a cycle users see
            if w.startswith(v + "."):
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"
