"""The project's modules import each other without a circle, and every import points down the data flow.

The sources are parsed, not imported (no bpy, CuPy or Dask needed). Every import counts, at module level or
inside a function: ``from . import a``, ``from ..scene.bvh import BVH``, ``import tofcore.rng`` and
``from tofcore import limits``. A circle means a module can only be imported half-initialised (or needs a
function-local import to dodge it); the assertion names it, e.g. ``tofcore.output.writers →
tofcore.output.convergence_plot → tofcore.output.writers``.

:data:`LAYERS` is the house from the ground up (DESIGN.md "The flow", docs/architecture.md). A module may
import its own part and the parts on lower floors; parts that share a floor stand side by side and do not
import each other (the tracer does not know the sensor model, nor the sensor the tracer).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The packages of this repository (folder name = import name).
PACKAGES = ("tofcore", "batch", "addon")

#: Floors from the ground up; each floor lists its parts (a module or a package, by import name).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("tofcore.constants", "tofcore.errors", "tofcore.progress", "tofcore.units", "tofcore.native", "tofcore.console",
     "tofcore._interrupt"),
    ("tofcore.backend", "tofcore.limits"),
    # rng, the counter-based hash, stands below the tracer and the sensor: the tracer's samplers and
    # the sensor's noise (tofcore.sensor.noise) draw from it, so one seed gives the same numbers on both devices
    ("tofcore.scene", "tofcore.rng"),
    # gpu (traversal, the BVH's CUDA twin) needs only the scene: the compiled GPU tracer (above) drives it
    ("tofcore.tracer", "tofcore.sensor", "tofcore.plan", "tofcore.gpu"),
    # fused twins the tracer's and the sensor's functions; the compiled tracer reuses them and, in
    # compiled.tracer, picks itself or the NumPy reference for a trace (render imports that choice)
    ("tofcore.output", "tofcore.fused", "tofcore.compiled"),
    ("tofcore.render",),
    ("tofcore", "tofcore.cli"),   # "tofcore": the package face (tofcore/__init__.py)
    ("tofcore.__main__",),
    ("addon",),
    ("batch",),
)


def modules(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> dict[str, Path]:
    """Dotted module name → source file for every ``.py`` under the packages (``pkg/__init__.py`` → ``pkg``)."""
    found: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _targets(node: ast.AST, module: str, is_package: bool, known: set[str]) -> set[str]:
    """The project modules one import statement names (the package itself for names it defines)."""
    if isinstance(node, ast.Import):
        return {_nearest(alias.name, known) for alias in node.names} - {None}
    if not isinstance(node, ast.ImportFrom):
        return set()
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - node.level + 1]
        source = ".".join(base + ([node.module] if node.module else []))
    else:
        source = node.module or ""
    found = set()
    for alias in node.names:
        found.add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else _nearest(source, known))
    return found - {None}


def _nearest(name: str, known: set[str]) -> str | None:
    """``name`` or its closest enclosing project module (``tofcore.scene.bvh.BVH`` → ``tofcore.scene.bvh``)."""
    parts = name.split(".")
    while parts and ".".join(parts) not in known:
        parts.pop()
    return ".".join(parts) or None


def import_graph(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """Module → the project modules it imports anywhere in its source (self-imports left out)."""
    sources = modules(root, packages)
    known = set(sources)
    graph: dict[str, set[str]] = {}
    for name, path in sources.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        edges: set[str] = set()
        for node in ast.walk(tree):
            edges |= _targets(node, name, path.name == "__init__.py", known)
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


def part_of(module: str, layers=LAYERS) -> tuple[int, str]:
    """(floor, part) of a module: the longest part name that is the module or encloses it."""
    best: tuple[int, str] | None = None
    for floor, parts in enumerate(layers):
        for part in parts:
            if (module == part or module.startswith(part + ".")) and (best is None or len(part) > len(best[1])):
                best = (floor, part)
    if best is None:
        raise AssertionError(f"tests/test_import_graph.py: module {module} is on no floor of LAYERS; add it")
    return best


def wrong_arrows(graph: dict[str, set[str]], layers=LAYERS) -> list[str]:
    """Imports that run up a floor or sideways between two parts of one floor."""
    wrong = []
    for module, targets in sorted(graph.items()):
        floor, part = part_of(module, layers)
        for target in sorted(targets):
            target_floor, target_part = part_of(target, layers)
            if target_part != part and target_floor >= floor:
                way = "up" if target_floor > floor else "sideways"
                wrong.append(f"{module} (floor {floor}) → {target} (floor {target_floor}, {way})")
    return wrong


def room_floors(graph: dict[str, set[str]]) -> dict[str, int]:
    """Floor of each room, a room being a top-level folder or file of a package (``tofcore.tracer.qmc`` →
    ``tofcore.tracer``): 1 + the highest floor it imports from, 1 for a room that imports none.

    A module that stands lower than its folder (a part nested in another part of :data:`LAYERS`) lifts every
    room that imports it above the whole folder, so the house seen folder by folder grows a floor.
    """
    def room(module: str) -> str:
        return ".".join(module.split(".")[:2])

    rooms: dict[str, set[str]] = {}
    for module, targets in graph.items():
        rooms.setdefault(room(module), set()).update(room(t) for t in targets if room(t) != room(module))
    floors: dict[str, int] = {}

    def floor(name: str) -> int:
        if name not in floors:
            floors[name] = 1 + max((floor(t) for t in rooms.get(name, ())), default=0)
        return floors[name]

    for name in rooms:
        floor(name)
    return floors


def test_the_project_has_no_import_cycle():
    graph = import_graph()
    assert {"tofcore.tracer.transport", "batch.cli", "addon.operators"} <= set(graph)  # the parser found them
    assert "tofcore.scene.bvh" in graph["tofcore.scene.scene"]  # and their imports, function-local ones too
    cycle = find_cycle(graph)
    assert cycle is None, f"modules import each other in a circle: {' → '.join(cycle)}"


def test_every_import_points_down_the_flow():
    wrong = wrong_arrows(import_graph())
    assert not wrong, "imports against the layers (tests/test_import_graph.py LAYERS):\n" + "\n".join(wrong)


def test_the_folders_stand_on_the_floors_of_the_layers():
    """Folder by folder, tofcore has as many floors as :data:`LAYERS` gives it (docs/architecture.md): no
    module sits below its own folder, as ``tracer/rng.py`` once did (9 floors, the sensor above the tracer)."""
    floors = room_floors(import_graph(packages=("tofcore",)))
    layer_floors = sum(any(p == "tofcore" or p.startswith("tofcore.") for p in parts) for parts in LAYERS)
    assert floors["tofcore.sensor"] == floors["tofcore.tracer"]
    assert max(floors.values()) == layer_floors == 8, sorted(floors.items(), key=lambda item: item[1])


def test_find_cycle_names_the_circle(tmp_path):
    """The checker itself: function-local, absolute and ``from .a import f`` imports all count."""
    pkg = tmp_path / "addon"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from . import a\n", encoding="utf-8")
    (pkg / "a.py").write_text("from .b import f\n", encoding="utf-8")
    (pkg / "b.py").write_text("def f():\n    import addon.c\n", encoding="utf-8")
    (pkg / "c.py").write_text("def g():\n    from addon import a\n", encoding="utf-8")
    graph = import_graph(tmp_path, ("addon",))
    assert graph == {"addon": {"addon.a"}, "addon.a": {"addon.b"}, "addon.b": {"addon.c"}, "addon.c": {"addon.a"}}
    assert find_cycle(graph) == ["addon.a", "addon.b", "addon.c", "addon.a"]
    (pkg / "c.py").write_text("from . import b\n", encoding="utf-8")
    assert find_cycle(import_graph(tmp_path, ("addon",))) == ["addon.b", "addon.c", "addon.b"]
    (pkg / "c.py").write_text("import os\n", encoding="utf-8")
    assert find_cycle(import_graph(tmp_path, ("addon",))) is None


def test_wrong_arrows_names_upward_and_sideways_imports(tmp_path):
    """The layer check itself, on a small package: one arrow up, one sideways, one allowed."""
    pkg = tmp_path / "pkg"
    (pkg / "low").mkdir(parents=True)
    (pkg / "__init__.py").write_text("", encoding="utf-8")
    (pkg / "low" / "__init__.py").write_text("", encoding="utf-8")
    (pkg / "low" / "a.py").write_text("from ..high import h\n", encoding="utf-8")   # up
    (pkg / "left.py").write_text("from . import right\nfrom .low import a\n", encoding="utf-8")  # sideways, down
    (pkg / "right.py").write_text("", encoding="utf-8")
    (pkg / "high.py").write_text("def h():\n    from pkg.low.a import x\n", encoding="utf-8")
    layers = (("pkg.low",), ("pkg.left", "pkg.right"), ("pkg.high", "pkg"))
    assert wrong_arrows(import_graph(tmp_path, ("pkg",)), layers) == [
        "pkg.left (floor 1) → pkg.right (floor 1, sideways)",
        "pkg.low.a (floor 0) → pkg.high (floor 2, up)",
    ]
