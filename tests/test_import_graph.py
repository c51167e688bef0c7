"""No import cycle among the code packages: the import graph of ``flows``, ``tasks``, ``storage`` and
``ms3d_model`` is built statically (``ast``, every import at any depth, so an import inside a function that
dodges a cycle counts too) and must be acyclic. A self-test feeds the checker a two-module cycle."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("flows", "tasks", "storage", "ms3d_model")


def module_sources(root: Path = ROOT) -> dict[str, tuple[str, bool]]:
    """Module name -> (source, is a package ``__init__``) for every file of :data:`PACKAGES`."""
    out = {}
    for pkg in PACKAGES:
        for p in sorted((root / pkg).rglob("*.py")):
            parts = p.relative_to(root).with_suffix("").parts
            init = parts[-1] == "__init__"
            out[".".join(parts[:-1] if init else parts)] = (p.read_text(), init)
    return out


def import_graph(sources: dict[str, tuple[str, bool]]) -> dict[str, set[str]]:
    """Module -> the modules of ``sources`` it imports (``from a.b import c``: ``a.b.c`` when that is a module,
    else ``a.b``; relative imports resolved)."""
    graph: dict[str, set[str]] = {m: set() for m in sources}
    for name, (src, init) in sources.items():
        package = name if init else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(src)):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    parts = parts[:len(parts) - (node.level - 1)]
                    base = ".".join(parts + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in sources else base for a in node.names]
            for t in targets:
                while t and t not in sources:
                    t = t.rpartition(".")[0]
                if t and t != name:
                    graph[name].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle():
    graph = import_graph(module_sources())
    assert len(graph) > 100 and sum(map(len, graph.values())) > 200  # the graph was found
    found = cycles(graph)
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_checker_finds_a_cycle_hidden_in_a_function():
    sources = {"storage": ("", True), "storage.a": ("from storage.b import f\n", False),
               "storage.b": ("def f():\n    from . import a\n", False),
               "storage.c": ("from storage import a\n", False)}
    graph = import_graph(sources)
    assert graph["storage.b"] == {"storage.a"} and graph["storage.c"] == {"storage.a"}
    assert cycles(graph) == [["storage.a", "storage.b"]]
    assert cycles({"x": {"y"}, "y": set()}) == []
