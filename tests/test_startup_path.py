"""What ``eyetohand apply CAL --uv U V`` loads (issue 29: its start ≤ 1.5× ``python -c "import numpy"``,
measured by benchmarks/bench_paths.py): the packages' public names are imported on first use
(``eyetohand.core.lazy``), the CLI registers only the named command's module, and NumPy's median and
percentile (which import ``numpy.ma``) are replaced by bit-identical ones on the file's proof path."""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import PAPER, src_env

SRC = Path(__file__).resolve().parents[1] / "src"


def _lazy_packages() -> dict[str, Path]:
    out = {}
    for init in sorted((SRC / "eyetohand").rglob("__init__.py")):
        if "lazy_exports(" in init.read_text(encoding="utf-8"):
            parts = init.parent.relative_to(SRC).parts
            out[".".join(parts)] = init
    return out


LAZY = _lazy_packages()


def _python(code: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", code]
    return subprocess.run(cmd, env=src_env(), capture_output=True, text=True, timeout=120)


def test_the_layered_packages_export_lazily():
    for name in ("eyetohand", "eyetohand.calibration", "eyetohand.solve", "eyetohand.cell", "eyetohand.sim"):
        assert name in LAZY


def _type_checking_names(init: Path) -> dict[str, str]:
    """name → module of the ``if TYPE_CHECKING:`` imports of an ``__init__``."""
    tree = ast.parse(init.read_text(encoding="utf-8"))
    out = {}
    for node in tree.body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom) and imp.module
                out.update({a.name: imp.module for a in imp.names})
    return out


@pytest.mark.parametrize("package", sorted(LAZY))
def test_lazy_names_are_the_type_checked_ones_and_resolve(package):
    """Each package's lazy names are exactly its ``if TYPE_CHECKING:`` imports (what mypy checks),
    every name of ``__all__`` resolves, and to the very object of the module it names."""
    typed = _type_checking_names(LAZY[package])
    code = f"""
import importlib, json, sys
pkg = importlib.import_module({package!r})
typed = {typed!r}
out = {{"dir": sorted(set(typed) - set(dir(pkg))), "wrong": [], "all": list(pkg.__all__)}}
for name, module in typed.items():
    if getattr(pkg, name) is not getattr(importlib.import_module(module), name):
        out["wrong"].append(name)
print(json.dumps(out))
"""
    r = _python(code)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["dir"] == [] and got["wrong"] == []
    pkg = importlib.import_module(package)
    for name in got["all"]:
        assert getattr(pkg, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        pkg.no_such_name  # noqa: B018


def test_a_submodule_loaded_first_does_not_hide_the_function_of_its_name():
    """``compare`` is both ``calibration/compare.py`` and its function: loading the module first (by
    its path, as a test or a plugin may) must leave the package's ``compare`` the function."""
    code = """
import types
import eyetohand.calibration.compare, eyetohand.calibration.verify, eyetohand.solve.evaluate
import eyetohand.sim.simulate, eyetohand.vision.render
from eyetohand.calibration import compare, verify
from eyetohand.solve import evaluate
from eyetohand.sim import simulate
from eyetohand.vision import render
for f in (compare, verify, evaluate, simulate, render):
    assert callable(f) and not isinstance(f, types.ModuleType), f
print("ok")
"""
    r = _python(code)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_the_commands_table_names_each_commands_module():
    from eyetohand.cli import _COMMANDS, COMMAND_MODULES, _build

    for module in COMMAND_MODULES:
        parser = _build((module,))
        sub = next(a for a in parser._actions if a.dest == "command")
        assert set(sub.choices) == {c for c, m in _COMMANDS.items() if m == module}, module
    assert set(_COMMANDS.values()) == set(COMMAND_MODULES)


def test_apply_loads_only_what_it_needs(tmp_path):
    """``eyetohand apply`` in a fresh process: the file, its model and its proof; none of the fit,
    the swarm, the other commands' packages, ``numpy.ma``, the CSV reader, ``tempfile`` nor OpenSSL's
    hashes and ``hmac``."""
    from eyetohand import calibrate, load_pairs

    cal = tmp_path / "cal.json"
    calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm").save(cal)
    code = f"""
import sys
from eyetohand.cli import main
sys.argv = ["eyetohand", "apply", {str(cal)!r}, "--uv", "700", "750"]
assert main() == 0
print(" ".join(sorted(sys.modules)), file=sys.stderr)
"""
    r = _python(code)
    assert r.returncode == 0, r.stderr
    loaded = set(r.stderr.split())
    assert len(r.stdout.split()) == 3
    for module in (
        "numpy.ma",
        "scipy",
        "cv2",
        "eyetohand.calibration.fit",
        "eyetohand.solve.optimize",
        "eyetohand.cell",
        "eyetohand.sim",
        "eyetohand.reports",
        "eyetohand.vision",
        "eyetohand.server",
        # issue 29's second pass: the CSV reader, tempfile and OpenSSL's hashes load on first use
        "eyetohand.core.csvtext",
        "csv",
        "tempfile",
        "hashlib",
        "_hashlib",
        "hmac",
    ):
        assert module not in loaded, module
    assert "eyetohand.calibration.file" in loaded  # the run did load and prove the file


@pytest.mark.parametrize("n", [*range(1, 40), 999, 1000])
def test_median_and_percentile_are_numpys_bit_for_bit(n):
    from eyetohand.solve.evaluate import _median, _percentile

    rng = np.random.default_rng(n)
    for scale in (1e-6, 1.0, 1e6):
        x = np.abs(rng.standard_normal(n)) * scale
        assert _median(x) == float(np.median(x))
        for q in (0.0, 5.0, 37.3, 50.0, 95.0, 99.0, 100.0):
            assert _percentile(x, q) == float(np.percentile(x, q))
    x[0] = np.nan
    assert np.isnan(_percentile(x, 95.0))
