"""The package's layers, read from its import statements (every one, those inside functions too):
technique modules are leaves, the ops below them never import upward, and no modules import each other
in a circle."""

import ast
import pathlib

import pytest

import gpupro

ROOT = pathlib.Path(gpupro.__file__).parent
TECHNIQUES = "gpupro.techniques"
REGISTRY_LOADERS = {"gpupro", "gpupro.technique"}
"""The package (which registers every technique on import) and the registry (``get``/``registered``
import the techniques package): the two modules allowed to import :mod:`gpupro.techniques`."""


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _imports(module: str) -> set[str]:
    """The gpupro modules ``module`` imports anywhere in its source: ``from a.b import c`` counts as ``a.b.c``
    when that is a module, else as ``a.b``."""
    found = set()
    package = module if MODULES[module].name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(MODULES[module].read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            found |= {f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names}
    return {name for name in found if name in MODULES and name != module}


GRAPH = {module: _imports(module) for module in MODULES}


def _is_technique(module: str) -> bool:
    return module.startswith(TECHNIQUES + ".") and MODULES[module].name != "__init__.py"


def test_the_graph_sees_the_packages_imports():
    assert "gpupro.shading.deferred" in GRAPH["gpupro.techniques.lights.deferred"]
    assert TECHNIQUES in GRAPH["gpupro.technique"]
    assert sum(map(_is_technique, MODULES)) >= 20


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _is_technique(m)))
def test_a_technique_module_imports_no_other_technique_module(module):
    others = sorted(m for m in GRAPH[module] if m.startswith(TECHNIQUES))
    assert not others, f"{module} imports {others}: move what they share into an ops package (gpupro/raster, " \
                       "gpupro/shading, gpupro/media, ...), or build a twin from the registered specification"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if not m.startswith(TECHNIQUES) and m not in REGISTRY_LOADERS))
def test_nothing_below_the_techniques_imports_them(module):
    upward = sorted(m for m in GRAPH[module] if m == TECHNIQUES or m.startswith(TECHNIQUES + "."))
    assert not upward, f"{module} imports {upward}: ops and infrastructure must not depend on a technique"


def _cycle():
    """One import cycle of the package outside the registry's loading, or None (depth-first search)."""
    graph = {m: {d for d in deps if not (m in REGISTRY_LOADERS and d.startswith(TECHNIQUES))} for m, deps in GRAPH.items()}
    colour, stack = {}, []

    def visit(module):
        colour[module] = "grey"
        stack.append(module)
        for dep in sorted(graph[module]):
            if colour.get(dep) == "grey":
                return stack[stack.index(dep):] + [dep]
            if dep not in colour and (found := visit(dep)):
                return found
        colour[module] = "black"
        stack.pop()
        return None

    for module in sorted(graph):
        if module not in colour and (found := visit(module)):
            return found
    return None


def test_no_import_circles():
    cycle = _cycle()
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_the_cycle_search_finds_a_planted_cycle(monkeypatch):
    monkeypatch.setitem(GRAPH, "gpupro.numerics", GRAPH["gpupro.numerics"] | {"gpupro.shading.brdfs"})
    assert _cycle() is not None
