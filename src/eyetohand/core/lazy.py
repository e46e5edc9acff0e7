"""A package's public names imported on first use (PEP 562), so importing a package costs only the
modules a caller touches: ``eyetohand apply`` needs the calibration file, not the fit, compare,
verify or export modules beside it in :mod:`eyetohand.calibration`.

A package ``__init__`` imports its names under ``if TYPE_CHECKING:`` (what mypy and readers see)
and, for the run time, hands the same names to :func:`lazy_exports`::

    if TYPE_CHECKING:
        from eyetohand.calibration.file import Calibration, Mapped
    else:
        __getattr__, __dir__ = lazy_exports(__name__, {"file": ("Calibration", "Mapped")})

A name that is also a submodule's name (``calibration.compare``, the function in ``compare.py``)
needs one more step: the import system binds a submodule on its package when it first loads it
(``import eyetohand.calibration.compare`` anywhere), which would hide the function behind the module.
The package's module type then keeps the exported name instead (:class:`_LazyPackage`), as an eager
``from .compare import compare`` in the ``__init__`` did. tests/test_startup_path.py checks each
package's names against its ``if TYPE_CHECKING:`` imports and ``__all__``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from importlib import import_module
from types import ModuleType


def lazy_exports(
    package: str, exports: dict[str, tuple[str, ...]]
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``: each name of ``exports[module]`` is looked up in
    ``package.module`` when first asked for, and every name of that module is then bound on the
    package (later look-ups are plain attribute reads)."""
    where = {name: module for module, names in exports.items() for name in names}

    class _LazyPackage(ModuleType):
        def __setattr__(self, name: str, value: object) -> None:
            if (
                name in where and isinstance(value, ModuleType) and value.__name__ == f"{package}.{name}"
            ):  # a submodule loading, named as an export: keep the export
                value = getattr(import_module(f"{package}.{where[name]}"), name)
            super().__setattr__(name, value)

    module = sys.modules[package]
    module.__class__ = _LazyPackage
    for name, value in list(vars(module).items()):  # loaded already, by an eager import above the call
        module.__setattr__(name, value)

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        source = import_module(f"{package}.{module}")
        namespace = vars(sys.modules[package])
        for other in exports[module]:
            namespace[other] = getattr(source, other)
        return namespace[name]

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *where})

    return __getattr__, __dir__
