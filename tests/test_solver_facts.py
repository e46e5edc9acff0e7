"""The facts callers act on live in the registries: a solver says whether it is a swarm, its memory per
particle, whether it is the least-squares refiner or the linear solve; a model whether it corrects a lens.
Nothing outside the registry compares a solver's name."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from eyetohand.models import MODELS, PlanarMatrixModel
from eyetohand.solve import OPTIMIZERS, get_solver
from eyetohand.solve.optimize import MUTATION_RATE, candidates_per_iteration

SRC = Path(__file__).resolve().parents[1] / "src" / "eyetohand"


def test_each_solver_says_what_it_is():
    facts = {
        name: (s.is_swarm, s.hybrid, s.is_least_squares, s.is_linear)
        for name in OPTIMIZERS
        for s in [get_solver(name)]
    }
    assert facts == {
        "linear": (False, False, False, True),
        "lm": (False, False, True, False),
        "hybrid-pso": (True, True, False, False),
        "pso": (True, False, False, False),
    }


@pytest.mark.parametrize("name", ["hybrid-pso", "pso"])
def test_a_swarms_memory_factor_is_its_candidates_per_particle(name):
    solver = get_solver(name)
    expected = 1 + 2 + MUTATION_RATE if solver.hybrid else 1.0  # moved, two children, a share of a mutant
    assert solver.memory_factor == expected
    assert get_solver("hybrid-pso").memory_factor == 3.1  # the number the memory check divided by
    for n in (2, 10, 200, 10_001):
        assert solver.candidates(n) == candidates_per_iteration(
            n, crossover=solver.hybrid, mutation=solver.hybrid
        )
        assert abs(solver.candidates(n) - solver.memory_factor * n) <= 1  # mutants: max(1, round(0.1 n))


def test_solvers_without_a_swarm_take_no_swarm_memory():
    assert get_solver("lm").memory_factor == 0.0
    assert get_solver("linear").memory_factor == 0.0


def test_the_lens_fact_agrees_with_the_models_that_undistort():
    for cls in MODELS.values():
        if issubclass(cls, PlanarMatrixModel):
            assert cls.corrects_lens == (cls._ideal_px is not PlanarMatrixModel._ideal_px), cls.name
    assert MODELS["homography-radial"].corrects_lens
    assert MODELS["camera"].corrects_lens
    assert not MODELS["homography"].corrects_lens and not MODELS["paper"].corrects_lens


def _name_comparisons(path: Path):
    """Comparisons of a string literal that names a solver (``== "lm"``, ``in ("pso", ...)``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if not isinstance(node, ast.Compare):
            continue
        for part in [node.left, *node.comparators]:
            literals = part.elts if isinstance(part, ast.Tuple | ast.List | ast.Set) else [part]
            for lit in literals:
                if isinstance(lit, ast.Constant) and lit.value in OPTIMIZERS:
                    yield node.lineno, lit.value


def test_no_caller_compares_solver_names():
    registry = SRC / "solve" / "solvers.py"
    bad = [
        f"{path.relative_to(SRC)} line {line}: {value!r}"
        for path in sorted(SRC.rglob("*.py"))
        if path != registry
        for line, value in _name_comparisons(path)
    ]
    assert not bad, "ask get_solver(name) for the fact instead:\n" + "\n".join(bad)
