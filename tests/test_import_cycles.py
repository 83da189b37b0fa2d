"""No import cycles in nrhdr_core. Every import of an nrhdr_core module (module level or inside
a function: a function-level import only hides a cycle) is read from the source's AST; the graph must be
acyclic."""
from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "nrhdr_core"


def _imports(path: Path, modules: set[str]) -> set[str]:
    """nrhdr_core modules that `path` imports anywhere in its body."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level == 1 or base == "nrhdr_core" or base.startswith("nrhdr_core."):
                base = base.removeprefix("nrhdr_core").lstrip(".") if node.level == 0 else base
                if base:                                   # from .x import y / from nrhdr_core.x import y
                    out.add(base.split(".")[0])
                else:                                      # from . import x, y
                    out.update(a.name for a in node.names)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("nrhdr_core."):
                    out.add(a.name.split(".")[1])
    return (out & modules) - {path.stem}


def import_graph() -> dict[str, set[str]]:
    files = {p.stem: p for p in PKG.glob("*.py") if p.stem != "__init__"}
    return {name: _imports(p, set(files)) for name, p in files.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle as a path [a, b, ..., a], or None (depth-first search with colours)."""
    colour = dict.fromkeys(graph, 0)
    stack: list[str] = []

    def visit(n):
        colour[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if colour[m] == 1:
                return stack[stack.index(m):] + [m]
            if colour[m] == 0:
                c = visit(m)
                if c:
                    return c
        stack.pop()
        colour[n] = 2
        return None

    for n in sorted(graph):
        if colour[n] == 0:
            c = visit(n)
            if c:
                return c
    return None


def test_the_cycle_finder_finds_cycles():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_the_graph_sees_function_level_imports(tmp_path):
    (tmp_path / "x.py").write_text("def f():\n    from .y import g\n    from . import z\n    import nrhdr_core.w\n")
    assert _imports(tmp_path / "x.py", {"x", "y", "z", "w"}) == {"y", "z", "w"}


def test_nrhdr_core_has_no_import_cycle():
    graph = import_graph()
    assert "crosstalk" in graph and "profile" in graph
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle in nrhdr_core: " + " -> ".join(cycle)
