"""The architecture as tests: dependencies point one way, no private name crosses a module, small modules.

Read from the source with :mod:`ast` (function-level imports included, since they make cycles too).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("engine_model", "flows")
#: Modules allowed beyond ~600 lines, with the reason.
LONG_MODULES = {
    "engine_model/cycle/engine.py": "numba kernel: the converged-cycle driver's sections share its local state",
}
MAX_LINES = 600
MAX_ROOT_MODULES = 12


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = f
    return out


MODULES = _modules()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base[: len(base) - node.level + (1 if _is_package(module) else 0)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(name: str, path: Path):
    """(edges to project modules, private names imported, module aliases) of one file."""
    tree = ast.parse(path.read_text())
    edges, private, aliases = set(), [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in PACKAGES:
                    edges.add(a.name)
                    aliases[a.asname or a.name.split(".")[0]] = a.name
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(name, node) if name else (node.module or "")
            if target.split(".")[0] not in PACKAGES:
                continue
            for a in node.names:
                full = f"{target}.{a.name}"
                if full in MODULES:
                    edges.add(full)
                    aliases[a.asname or a.name] = full
                else:
                    edges.add(target)
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        private.append(f"{target}.{a.name}")
    attrs = [f"{aliases[n.value.id]}.{n.attr}" for n in ast.walk(tree)
             if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id in aliases
             and n.attr.startswith("_") and not n.attr.startswith("__")]
    return edges, private + attrs


def _graph() -> dict[str, set[str]]:
    return {name: {e for e in _imports(name, path)[0] if e in MODULES and e != name}
            for name, path in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    graph = _graph()
    # a package's __init__ re-exports its modules; a module importing its own package's __init__ is the cycle
    assert _cycles(graph) == []


def test_no_private_name_crosses_a_module():
    bad = {}
    files = dict(MODULES)
    files.update({".".join(f.relative_to(ROOT).with_suffix("").parts): f
                  for d in ("tests", "benchmarks") for f in (ROOT / d).rglob("*.py")})
    for name, path in files.items():
        mod = name if name in MODULES else ""
        _edges, private = _imports(mod, path)
        if private:
            bad[str(path.relative_to(ROOT))] = private
    assert bad == {}


def test_dependencies_point_down():
    """flows -> engine_model -> kernels: the library never imports the orchestration or Prefect/Dask."""
    for name, path in MODULES.items():
        if not name.startswith("engine_model"):
            continue
        edges, _ = _imports(name, path)
        assert not [e for e in edges if e.startswith("flows")], name
        text = path.read_text()
        for lib in ("prefect", "distributed", "dask"):
            assert f"import {lib}" not in text and f"from {lib}" not in text, (name, lib)
    for name, path in MODULES.items():
        if name.startswith("engine_model.cycle."):
            edges, _ = _imports(name, path)
            outside = [e for e in edges if not (e.startswith("engine_model.cycle") or e == "engine_model.thermo")]
            assert outside == [], (name, outside)
            assert "import pandas" not in path.read_text(), name


def test_root_holds_few_modules_and_modules_stay_small():
    root = [p for p in (ROOT / "engine_model").glob("*.py")]
    assert len(root) <= MAX_ROOT_MODULES, sorted(p.name for p in root)
    long = {str(p.relative_to(ROOT)): n for p in MODULES.values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert set(long) <= set(LONG_MODULES), long


# Names of notes that live outside the repository (spelt in pieces so that this file does not name them).
OUTSIDE_NOTES = ["DESIGN" + ".md", "shared/" + "STACK", "STACK" + "-NOTES"]


@pytest.mark.parametrize("pattern", OUTSIDE_NOTES)
def test_nothing_points_outside_the_repository(pattern):
    hits = []
    files = [ROOT / n for n in ("README.md", "Makefile", "pyproject.toml")]
    files += [p for d in ("engine_model", "flows", "tests", "benchmarks", "docs", ".ci") for p in (ROOT / d).rglob("*")]
    for f in files:
        if f.is_file() and f.suffix in (".py", ".md", ".toml", ".txt", ".cfg", ""):
            if pattern in f.read_text(errors="ignore"):
                hits.append(str(f.relative_to(ROOT)))
    assert hits == []
