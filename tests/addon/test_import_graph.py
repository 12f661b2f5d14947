"""The add-on's modules import each other without a circle (no bpy needed: the sources are parsed).

Every intra-package import counts, at module level or inside a function:
``from . import a``, ``from .a import f``, and the absolute forms ``import addon.a`` /
``from addon import a`` / ``from addon.a import f``.
A circle means a module can only be imported half-initialised (or needs a function-local
import to dodge it); the assertion names the circle, e.g. ``operators → properties → operators``.
"""

from __future__ import annotations

import ast
from pathlib import Path

#: The add-on package folder.
ADDON_DIR = Path(__file__).resolve().parents[2] / "addon"
#: The package's name for absolute imports.
PACKAGE = "addon"


def add_on_modules(folder: Path = ADDON_DIR) -> dict[str, Path]:
    """Module name (``__init__`` for the package itself) → source file, for every ``.py`` in ``folder``."""
    return {path.stem: path for path in sorted(folder.glob("*.py"))}


def _targets(node: ast.AST, modules: set[str]) -> set[str]:
    """The add-on modules one import statement names (the package ``__init__`` for ``from . import f``)."""
    found: set[str] = set()
    if isinstance(node, ast.Import):
        for alias in node.names:
            parts = alias.name.split(".")
            if parts[0] == PACKAGE:
                found.add(parts[1] if len(parts) > 1 else "__init__")
    elif isinstance(node, ast.ImportFrom):
        if node.level == 1 or (node.level == 0 and node.module and node.module.split(".")[0] == PACKAGE):
            parts = (node.module or "").split(".")
            if node.level == 0:
                parts = parts[1:]
            if parts and parts[0]:
                found.add(parts[0])  # from .a import f / from addon.a import f
            else:  # from . import a, f / from addon import a, f: modules, or names of __init__
                for alias in node.names:
                    found.add(alias.name if alias.name in modules else "__init__")
    return found & modules


def import_graph(folder: Path = ADDON_DIR) -> dict[str, set[str]]:
    """Module → the add-on modules it imports anywhere in its source (self-imports left out)."""
    sources = add_on_modules(folder)
    names = set(sources)
    graph: dict[str, set[str]] = {}
    for name, path in sources.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        edges: set[str] = set()
        for node in ast.walk(tree):
            edges |= _targets(node, names)
        graph[name] = edges - {name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle as ``[a, b, …, a]``, or None (depth-first search, white/grey/black colouring)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for succ in sorted(graph.get(node, ())):
            if state.get(succ) == 1:
                return path[path.index(succ):] + [succ]
            if succ not in state:
                cycle = visit(succ)
                if cycle:
                    return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state:
            cycle = visit(start)
            if cycle:
                return cycle
    return None


def test_the_add_on_has_no_import_cycle():
    graph = import_graph()
    assert {"__init__", "operators", "properties", "panels"} <= set(graph)  # the parser found the package
    assert "operators" in graph["__init__"] and "properties" in graph["__init__"]  # and its imports
    cycle = find_cycle(graph)
    assert cycle is None, f"the add-on's modules import each other in a circle: {' → '.join(cycle)}"


def test_find_cycle_names_the_circle(tmp_path):
    """The checker itself: function-local, absolute and ``from .a import f`` imports all count."""
    (tmp_path / "__init__.py").write_text("from . import a\n", encoding="utf-8")
    (tmp_path / "a.py").write_text("from .b import f\n", encoding="utf-8")
    (tmp_path / "b.py").write_text("def f():\n    import addon.c\n", encoding="utf-8")
    (tmp_path / "c.py").write_text("def g():\n    from addon import a\n", encoding="utf-8")
    graph = import_graph(tmp_path)
    assert graph == {"__init__": {"a"}, "a": {"b"}, "b": {"c"}, "c": {"a"}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    (tmp_path / "c.py").write_text("from . import b\n", encoding="utf-8")
    assert find_cycle(import_graph(tmp_path)) == ["b", "c", "b"]
    (tmp_path / "c.py").write_text("import os\n", encoding="utf-8")
    assert find_cycle(import_graph(tmp_path)) is None
