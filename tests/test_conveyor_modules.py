"""The conveyor's fit and its report do not import each other, not even for type checking (issue 36):
the values both use (Prepared, Layout, JointFit) live apart, in cell/conveyor/terms.py."""

from __future__ import annotations

import ast

from test_imports import MODULES


def _imported(module: str) -> set[str]:
    """Every module ``module`` imports, whether or not under ``if TYPE_CHECKING:``."""
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_the_fit_and_the_report_do_not_import_each_other():
    fit, report = "eyetohand.cell.conveyor.fit", "eyetohand.cell.conveyor.report"
    assert report in _imported(fit)  # the fit builds the report
    assert fit not in _imported(report)
    assert "eyetohand.cell.conveyor.terms" in _imported(report)
