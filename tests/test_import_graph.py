"""No import circles inside ``src/physgm``: the import graph, read with ``ast``, has no cycle.

Every ``import`` statement counts, wherever it stands: at module level, inside a function, or
under ``if TYPE_CHECKING:``. A function-level import still makes the two modules need each
other (it is usually how a circle is hidden), and a type-only import is still a dependency a
reader and a type checker follow. Two modules that need each other are missing a third
concept, or pass a private name across a boundary; the fix is to move the shared piece, not
to defer the import.

An edge goes to the module that is named: ``from physgm.a import b`` points at ``physgm.a.b``
when that is a module, else at ``physgm.a`` (its ``__init__``). The parent packages that
Python runs on the way (``physgm/__init__.py`` for every import) are not edges; otherwise
every package that re-exports its modules would sit in a circle with each of them.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "physgm"


def module_files(package_dir: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package ``__init__``) for every .py under ``package_dir``."""
    modules = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        modules[".".join(parts)] = (path, is_package)
    return modules


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Module -> the modules of the same package that it imports (see the module docstring)."""
    modules = module_files(package_dir)
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, is_package) in modules.items():
        package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                graph[name].update(alias.name for alias in node.names if alias.name in modules)
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: "." is this package, ".." its parent
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    if f"{target}.{alias.name}" in modules:
                        graph[name].add(f"{target}.{alias.name}")
                    elif target in modules:
                        graph[name].add(target)
        graph[name].discard(name)
    return graph


def find_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One closed path (first module repeated at the end) per strongly connected component."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan; the package has ~100 modules, recursion is fine
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_closed_path(graph, set(c)) for c in components]


def _closed_path(graph: dict[str, set[str]], component: set[str]) -> list[str]:
    """A shortest cycle through the component's first module, by breadth-first search."""
    start = min(component)
    parent: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & component):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(parent[path[-1]])
                    return [start, *reversed(path[:-1]), start]
                if w not in parent:
                    parent[w] = v
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"component {sorted(component)} has no cycle through {start}")


def test_src_has_no_import_circles():
    graph = import_graph(SRC)
    assert len(graph) > 50 and sum(map(len, graph.values())) > 100, "the walk found too few modules"
    circles = find_circles(graph)
    assert not circles, (
        "import circles in src/physgm (move the shared piece to a third module):\n"
        + "\n".join("  " + " -> ".join(c) for c in circles)
    )


def test_finder_names_every_kind_of_import(tmp_path):
    """The walker sees function-level, TYPE_CHECKING and relative imports, and names the circle."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from pkg.a import A\n")
    (pkg / "a.py").write_text("from pkg.sub import b\nA = 1\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..c import C\n    return C\n")
    (pkg / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.a import A\nC = 2\n"
    )
    (pkg / "d.py").write_text("import pkg.c\n")  # imports into the circle, is not part of it
    graph = import_graph(pkg)
    assert graph["pkg.sub.b"] == {"pkg.c"}
    assert graph["pkg.d"] == {"pkg.c"}
    assert find_circles(graph) == [["pkg.a", "pkg.sub.b", "pkg.c", "pkg.a"]]

    (pkg / "c.py").write_text("C = 2\n")  # the circle opens
    assert find_circles(import_graph(pkg)) == []


def test_no_module_shadows_a_top_level_name():
    """``pipeline/render.py`` beside ``physgm/render/`` made a reader guess which one was meant."""
    top = {p.stem for p in SRC.glob("*.py")} | {p.name for p in SRC.iterdir() if (p / "__init__.py").exists()}
    top -= {"__init__", "__main__"}
    deeper = [p for p in SRC.glob("*/**/*.py") if p.stem in top]
    assert len(top) > 10, f"found too few top-level names: {sorted(top)}"
    assert not deeper, "modules named like a top-level physgm package or module (rename them): " + ", ".join(
        str(p.relative_to(SRC)) for p in deeper
    )
