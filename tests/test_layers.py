"""The layers of docs/architecture.md, kept by the code: read from the source with ``ast`` (the import
graph of tests/test_imports.py), nothing imported.

- a package imports only packages of lower rank (never one of its own rank: ``cell`` and ``reports``,
  ``vision`` and ``models`` know nothing of each other), so nothing below the interfaces imports the
  simulator, the CLI or the server;
- another package is imported through its ``__init__`` (``from eyetohand.core import InputError``), never
  by a module inside it nor by a ``_private`` name;
- no module over 900 lines, no function over 150.
"""

from __future__ import annotations

import ast

from test_imports import MODULES, PACKAGE, graph

#: package → rank; the top-level facade ``eyetohand`` and ``_version`` are outside the layers
RANKS = {
    "core": 0,
    "geometry": 1,
    "vision": 2,
    "models": 2,
    "solve": 3,
    "calibration": 4,
    "cell": 5,
    "positioning": 6,
    "reports": 5,
    "sim": 6,
    "cli": 8,
    "server": 7,
}
MAX_MODULE_LINES = 900
MAX_FUNCTION_LINES = 150


def layer(module: str) -> str | None:
    """The package of the layers a module belongs to (None for the facade and ``_version``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in RANKS else None


def test_every_module_is_in_a_layer():
    loose = [m for m in MODULES if layer(m) is None and m not in (PACKAGE, f"{PACKAGE}._version")]
    assert not loose, f"modules outside the layers (put each in a package of RANKS): {loose}"


def test_imports_only_go_down():
    bad = []
    for name, targets in sorted(graph().items()):
        mine = layer(name)
        if mine is None:
            continue
        for target, line in targets.items():
            theirs = layer(target)
            if theirs is None:
                if target != f"{PACKAGE}._version":
                    bad.append(f"{name} line {line} imports the facade {target}")
            elif theirs != mine and RANKS[theirs] >= RANKS[mine]:
                bad.append(
                    f"{name} ({mine}, rank {RANKS[mine]}) line {line} imports {target} "
                    f"({theirs}, rank {RANKS[theirs]})"
                )
    assert not bad, "imports that do not go down a layer:\n" + "\n".join(bad)


def _cross_package_imports(name: str):
    """(line, imported module path, imported names) of every import of another layer's package."""
    path = MODULES[name]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    mine = layer(name)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            target = node.module
            names = [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if layer(alias.name) not in (None, mine):
                    yield node.lineno, alias.name, []
            continue
        else:
            continue
        theirs = layer(target)
        if target.startswith(PACKAGE + ".") and theirs not in (None, mine):
            yield node.lineno, target, names


def test_other_packages_are_imported_through_their_init():
    bad = []
    for name in sorted(MODULES):
        if layer(name) is None:
            continue
        for line, target, names in _cross_package_imports(name):
            private = [n for n in names if n.startswith("_")]
            if target.count(".") > 1:
                bad.append(f"{name} line {line}: {target} (import from {'.'.join(target.split('.')[:2])})")
            elif private:
                bad.append(f"{name} line {line}: private {', '.join(private)} of {target}")
    assert not bad, "imports past a package's __init__:\n" + "\n".join(bad)


def _lines(node: ast.AST) -> int:
    return node.end_lineno - node.lineno + 1  # type: ignore[attr-defined]


def test_modules_and_functions_stay_small():
    bad = []
    for name, path in sorted(MODULES.items()):
        if path.suffix != ".py":
            continue
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MAX_MODULE_LINES:
            bad.append(f"{name}: {text.count(chr(10))} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _lines(node) > MAX_FUNCTION_LINES:
                bad.append(f"{name}.{node.name} line {node.lineno}: {_lines(node)} lines")
    assert not bad, "too large to read at once:\n" + "\n".join(bad)
