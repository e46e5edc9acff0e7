"""The package's import graph: no cycles, the CLI imported by nobody, library modules print nothing.

Read from the source with ``ast`` (nothing is imported): every ``import`` and ``from … import`` of a
module, at module level or inside a function, relative ones resolved against the module's package.
Imports under ``if TYPE_CHECKING:`` are left out: they never run, so they cannot form a cycle.
An edge goes to the module named; ``from pkg import name`` goes to ``pkg.name`` when that is a module
of the package, else to ``pkg`` itself. Importing a submodule runs its packages' ``__init__`` too, but
that is not counted as an edge of the importer (every module would then depend on ``eyetohand``).
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "eyetohand"
CLI = f"{PACKAGE}.cli"
# layers allowed to talk to the terminal: the commands, and the server (uvicorn's startup lines)
MAY_PRINT = (CLI, f"{PACKAGE}.server")


def _module_files() -> dict[str, Path]:
    """Every module of the package → its source; a compiled module (``_rows.c``) by its stub ``.pyi``,
    a leaf: it imports nothing at run time."""
    out = {}
    stubs = [p for p in (SRC / PACKAGE).rglob("*.pyi") if not p.with_suffix(".py").exists()]
    for path in sorted([*(SRC / PACKAGE).rglob("*.py"), *stubs]):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _module_files()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _runtime_nodes(tree: ast.AST):
    """Every node, skipping the bodies of ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                stack.extend(child.orelse)
                continue
            stack.append(child)


def _resolve(importer: str, level: int, module: str | None) -> str:
    base = importer.split(".")
    if not _is_package(importer):
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def _owned(name: str) -> str | None:
    """``name`` or its longest prefix that is a module of the package; None outside it."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in MODULES:
            return candidate
        parts.pop()
    return None


def imports_of(name: str) -> dict[str, int]:
    """Modules of the package that ``name`` imports at run time → line of the first such import."""
    tree = ast.parse(MODULES[name].read_text(encoding="utf-8"), str(MODULES[name]))
    found: dict[str, int] = {}

    def add(target: str | None, line: int) -> None:
        if target is not None and target != name:
            found[target] = min(found.get(target, line), line)

    for node in _runtime_nodes(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(_owned(alias.name), node.lineno)
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(name, node.level, node.module) if node.level else (node.module or "")
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                add(sub if sub in MODULES else _owned(base), node.lineno)
    return found


@functools.cache
def graph() -> dict[str, dict[str, int]]:
    """Each module's imports (module → line), read once when a test asks (not at collection: every
    pytest worker imports this file, and test_layers/test_conveyor_modules import it)."""
    return {name: imports_of(name) for name in MODULES}


def find_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Cycles (a → … → a) of each strongly connected component with more than one module: the
    shortest one through each of its modules, without repeats."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def strongconnect(v: str) -> None:  # Tarjan; the graph is a few dozen nodes
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)

    cycles = []
    for comp in components:  # the shortest way back to each module, inside its component
        members = set(comp)
        seen: set[frozenset[str]] = set()
        for start in comp:
            cycle = _shortest_cycle(graph, start, members)
            key = frozenset(zip(cycle, cycle[1:], strict=False))
            if key not in seen:
                seen.add(key)
                cycles.append(cycle)
    return cycles


def _shortest_cycle(graph: dict[str, dict[str, int]], start: str, members: set[str]) -> list[str]:
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph[v]):
            if w == start:
                return paths[v] + [start]
            if w in members and w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    raise AssertionError(f"{start} is in a strongly connected component but on no cycle")


def _describe(cycle: list[str]) -> str:
    steps = [f"{a} (line {graph()[a][b]})" for a, b in zip(cycle, cycle[1:], strict=False)]
    return " -> ".join(steps + [cycle[-1]])


def test_the_graph_is_read():
    """The parser sees the package: known imports are found (a broken resolver would find none)."""
    assert f"{PACKAGE}.core.errors" in graph()[f"{PACKAGE}.core.pairs"]
    assert f"{PACKAGE}.core" in graph()[f"{PACKAGE}.reports.report"]
    assert f"{PACKAGE}.core" in graph()[f"{PACKAGE}.sim.cell"]
    assert f"{PACKAGE}.models._rows" in graph()[f"{PACKAGE}.models.base"]  # the compiled module, by its stub
    assert CLI in MODULES


def test_find_cycles_reports_a_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3, "d": 4}, "d": {}}
    assert find_cycles(graph) == [["a", "b", "c", "a"]]
    two = find_cycles({"a": {"b": 1, "c": 1}, "b": {"a": 2}, "c": {"a": 3}})
    assert sorted(two) == [["a", "b", "a"], ["c", "a", "c"]]
    assert find_cycles({"a": {"b": 1}, "b": {}}) == []


def test_no_import_cycle():
    cycles = find_cycles(graph())
    on_cycles = sorted({m for c in cycles for m in c})
    assert not cycles, (
        "import cycles:\n"
        + "\n".join(_describe(c) for c in cycles)
        + "\nmodules on a cycle: "
        + ", ".join(on_cycles)
    )


def test_only_the_cli_imports_the_cli():
    bad = [
        f"{name} line {graph()[name][t]} imports {t}"
        for name in sorted(graph())
        if not (name == CLI or name.startswith(CLI + "."))
        for t in graph()[name]
        if t == CLI or t.startswith(CLI + ".")
    ]
    assert not bad, "library modules importing the CLI:\n" + "\n".join(bad)


def _terminal_uses(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
            found.append(f"line {node.lineno}: print(")
        elif (
            isinstance(node, ast.Attribute)
            and node.attr in ("stdout", "stderr")
            and isinstance(node.value, ast.Name)
            and node.value.id == "sys"
        ):
            found.append(f"line {node.lineno}: sys.{node.attr}")
        elif isinstance(node, ast.ImportFrom) and node.module == "sys":
            found += [
                f"line {node.lineno}: from sys import {a.name}"
                for a in node.names
                if a.name in ("stdout", "stderr")
            ]
    return found


def test_library_modules_print_nothing():
    bad = [
        f"{name} {use}"
        for name, path in sorted(MODULES.items())
        if not any(name == p or name.startswith(p + ".") for p in MAY_PRINT)
        for use in _terminal_uses(path)
    ]
    assert not bad, "library modules writing to the terminal (use a callback):\n" + "\n".join(bad)
