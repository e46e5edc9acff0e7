"""Objects, not names (issue 36): a model, solver and objective are resolved once, where a request is
made (``FitRequest.from_names``), and the fit takes the resolved values as they are.

- no module outside the registries compares a value with a model's, a solver's or an objective's
  name (read from the source with ``ast``, as tests/test_layers.py reads the imports);
- a request made from names holds the model class (or AUTO), the Solver and the Objective;
- fitting a request looks none of them up again (the registries are watched during the fit).
"""

from __future__ import annotations

import ast

import numpy as np
import pytest
from test_imports import MODULES

import eyetohand.calibration.request as request_module
import eyetohand.models as models_module
import eyetohand.solve.objectives as objectives_module
import eyetohand.solve.solvers as solvers_module
from eyetohand.calibration import AUTO, FitRequest, calibrate, calibrate_request
from eyetohand.core import InputError
from eyetohand.models import MODELS
from eyetohand.solve import OBJECTIVES, OPTIMIZERS, Objective, Solver, get_objective, get_solver

#: the registries: where a name becomes its object (and the models' own modules, which name their kin)
REGISTRIES = ("eyetohand.solve.objectives", "eyetohand.solve.solvers", "eyetohand.calibration.request")
NAMES = {"auto", *MODELS, *OBJECTIVES, *OPTIMIZERS}


def _in_registry(module: str) -> bool:
    return module in REGISTRIES or module == "eyetohand.models" or module.startswith("eyetohand.models.")


def _named(node: ast.AST) -> list[str]:
    """The registry names a comparison's operand spells out (a string, or a tuple/list/set of them)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in NAMES:
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [n for e in node.elts for n in _named(e)]
    return []


def name_tests(tree: ast.AST) -> list[tuple[int, str]]:
    """``(line, name)`` of every ``==``, ``!=``, ``in`` or ``not in`` against a registry name, and of
    every dict keyed by one (a lookup table by name)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            if any(isinstance(op, (ast.Eq, ast.NotEq, ast.In, ast.NotIn)) for op in node.ops):
                found += [(node.lineno, n) for o in operands for n in _named(o)]
        elif isinstance(node, ast.Dict):
            keys = [n for k in node.keys if k is not None for n in _named(k)]
            if len(keys) >= 2:  # a table over names, e.g. {"l2": ..., "huber": ...}[objective]
                found += [(node.lineno, n) for n in keys]
    return found


def test_the_name_finder_finds_what_it_should():
    src = 'a = x == "auto"\nb = y in ("l2", "huber")\nc = {"l2": 1, "linf": 2}[o]\nd = z == "other"\n'
    assert name_tests(ast.parse(src)) == [(1, "auto"), (2, "l2"), (2, "huber"), (3, "l2"), (3, "linf")]


#: the packages that carry fits' names (below them "auto" and "lm" mean other things: a detector's
#: polarity, geometry's module lm)
FIT_PACKAGES = ("calibration", "solve", "cell", "reports", "sim", "server", "cli")
#: modules exempted from the scan (none: every name test outside the registries was removed)
ELSEWHERE: set[str] = set()
#: strings that spell a registry name and mean something else: the export's matrix kinds
NOT_NAMES = {("eyetohand.calibration.export", "homography"), ("eyetohand.calibration.export", "affine")}


def test_no_module_outside_the_registries_tests_a_name():
    bad = []
    for module, path in sorted(MODULES.items()):
        package = module.split(".")[1] if "." in module else ""
        if package not in FIT_PACKAGES or _in_registry(module) or module in ELSEWHERE:
            continue
        for line, name in name_tests(ast.parse(path.read_text(encoding="utf-8"))):
            if (module, name) in NOT_NAMES:
                continue
            bad.append(f"{module} line {line}: tests the name {name!r} (ask the resolved object)")
    assert not bad, "\n".join(bad)


def test_a_request_from_names_holds_the_resolved_objects():
    r = FitRequest.from_names("homography", "hybrid-pso", "huber", n_particles=20)
    assert r.model is MODELS["homography"]
    assert isinstance(r.solver, Solver) and r.solver is get_solver("hybrid-pso") and r.solver.is_swarm
    assert isinstance(r.objective, Objective) and r.objective.robust and r.objective.fitness_unit == "mm²"
    assert r.names == ("homography", "hybrid-pso", "huber")
    auto = FitRequest.from_names()
    assert auto.model is AUTO and auto.solver.is_least_squares and auto.objective.least_squares
    assert get_objective("l2").fitness_unit == "mm" and get_objective("linf").fitness_unit == "mm"


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ({"model": "nope"}, "unknown model 'nope'; choose one of: auto, affine, paper, homography"),
        ({"optimizer": "sgd"}, "unknown optimizer 'sgd'; choose one of: linear, lm, hybrid-pso, pso"),
        ({"objective": "l3"}, "unknown objective 'l3'; choose one of: l2, linf, huber"),
    ],
)
def test_a_bad_name_is_refused_listing_the_choices(options, words):
    with pytest.raises(InputError) as info:
        FitRequest.from_names(**options)
    assert str(info.value).startswith(words)


def test_a_request_holds_values_not_names():
    with pytest.raises(TypeError, match="from_names"):
        FitRequest("homography")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="from_names"):
        FitRequest(MODELS["homography"], "lm")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="needs a smooth objective"):  # the values are checked too
        FitRequest(MODELS["homography"], get_solver("lm"), get_objective("linf"))


class _Watched(dict):
    """A registry that counts the names looked up in it."""

    def __init__(self, *args):
        super().__init__(*args)
        self.asked: list[str] = []

    def __getitem__(self, key):
        self.asked.append(key)
        return super().__getitem__(key)

    def get(self, key, default=None):
        self.asked.append(key)
        return super().get(key, default)


def _nine_plus_two():
    """Pairs at three tool angles ("9 + 2": the fit estimates the tool offset first) and check pairs."""
    from eyetohand.sim.cell import Cell
    from eyetohand.sim.simulate import simulate

    cell = Cell.default().with_values(robot={"tcp_offset_mm": [0.35, -0.2]})
    sim = simulate(cell, "grid:3x3", (150.0,), n_check=10, angles_deg=(0.0, 90.0, 180.0), seed=4)
    return sim.pairs, sim.check


@pytest.mark.parametrize(
    ("model", "optimizer", "objective", "turns"),
    [
        ("homography", "lm", "l2", False),
        ("auto", "lm", "l2", False),
        ("auto", "lm", "l2", True),
        ("affine", "lm", "huber", True),
        ("paper", "hybrid-pso", "l2", False),  # leave-one-out by lm: the swarm's cheaper solver
        ("auto", "pso", "linf", False),  # by linear: lm cannot minimise linf
    ],
)
def test_fitting_a_request_looks_no_name_up(paper_pairs, monkeypatch, model, optimizer, objective, turns):
    train, check = _nine_plus_two() if turns else paper_pairs
    swarm = {"n_particles": 12, "iterations": 5} if optimizer.endswith("pso") else {}
    request = FitRequest.from_names(model, optimizer, objective, seed=0, **swarm)
    watched = {
        "models": _Watched(models_module.MODELS),
        "solvers": _Watched(solvers_module.SOLVERS),
        "objectives": _Watched(objectives_module.REGISTRY),
        "choices": _Watched(request_module._CHOICES),
    }
    monkeypatch.setattr(models_module, "MODELS", watched["models"])
    monkeypatch.setattr(solvers_module, "SOLVERS", watched["solvers"])
    monkeypatch.setattr(objectives_module, "REGISTRY", watched["objectives"])
    monkeypatch.setattr(request_module, "_CHOICES", watched["choices"])
    cal = calibrate_request(request, train, check=check)
    assert {k: w.asked for k, w in watched.items()} == {k: [] for k in watched}
    monkeypatch.undo()
    want = calibrate(train, model, optimizer, objective, check=check, seed=0, **swarm)  # by names
    assert np.array_equal(cal.model.params, want.model.params) and cal.loo == want.loo
    assert (cal.fit.optimizer, cal.fit.objective) == (optimizer, objective)  # the file stores names


@pytest.mark.parametrize("name", OBJECTIVES)
def test_an_objectives_facts_agree_with_its_values(name):
    """The facts the fit acts on say what the objective computes: the least-squares one is the
    2-norm (its held-out score the RMS), the robust one a sum of Huber losses (scored per pair), the
    others the largest error; the smooth ones are those lm minimises."""
    obj = get_objective(name)
    r = np.random.default_rng(3).normal(0.0, 2.0, (4, 15, 3))
    point = np.linalg.norm(r, axis=-1)  # (4, 15) point errors
    delta = 1.5
    huber = np.where(point <= delta, 0.5 * point**2, delta * (point - 0.5 * delta)).sum(axis=-1)
    want = np.sqrt((point**2).sum(axis=-1)) if obj.least_squares else huber if obj.robust else point.max(-1)
    np.testing.assert_allclose(obj.values(r, delta), want, rtol=1e-12)
    score = obj.held_out_score(r[0], delta)
    per_pair = np.sqrt(np.mean(point[0] ** 2)) if obj.least_squares else want[0] / (15 if obj.robust else 1)
    assert score == pytest.approx(per_pair, rel=1e-12)
    assert obj.smooth == get_solver("lm").minimises(obj)
    assert obj.fitness_unit == ("mm²" if obj.robust else "mm")
    assert not np.isfinite(obj.values(np.full((1, 3, 3), np.nan))).any()
