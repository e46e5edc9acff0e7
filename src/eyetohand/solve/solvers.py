"""Solvers refine a model's flat parameter vector against a robot-space objective.

A registry, name → :class:`Solver`: ``linear`` keeps the model's closed-form estimate; ``lm`` is
Levenberg–Marquardt (MINPACK, as SciPy's ``least_squares`` runs it: :mod:`eyetohand.geometry.lm`) on the
residuals of equation (16); ``hybrid-pso`` and ``pso`` are the paper's hybrid particle swarm (section
IV) and its plain ablation, from :mod:`eyetohand.solve.optimize`. Each solver declares the objectives it can
minimise and its options, which are validated before any work starts. Solvers know nothing about
cameras: they see ``model.batch_image_to_robot``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from eyetohand.core import DegenerateError, FitInfo, InputError
from eyetohand.geometry import batch_jacobian, levenberg_marquardt
from eyetohand.models import Model
from eyetohand.solve.objectives import OBJECTIVES, SMOOTH_OBJECTIVES, Objective, get_objective, huber_delta_mm

# the swarm (eyetohand.solve.optimize) loads when a swarm runs or is sized, not for every import of the
# registry: `eyetohand apply` needs OPTIMIZERS' names only

PSO_SPREAD_MM = 1.0
HUBER_ROUNDS = 5


@dataclass(frozen=True)
class Problem:
    """What a solver minimises: the model, its training pairs, the objective and the Huber threshold."""

    model: Model
    uv_px: np.ndarray
    xyz_mm: np.ndarray
    objective: Objective
    delta_mm: float

    def residuals(self, batch: np.ndarray) -> np.ndarray:
        """(P, N, 3) residuals of (P, D) parameter rows."""
        return self.model.batch_image_to_robot(batch, self.uv_px, self.xyz_mm[:, 2]) - self.xyz_mm[None]

    def fitness(self, batch: np.ndarray) -> np.ndarray:
        return self.objective.values(self.residuals(batch), self.delta_mm)

    def extra(self) -> dict[str, float]:
        """What a fit records beside its fitness: a robust objective's threshold."""
        return {"huber_delta_mm": self.delta_mm} if self.objective.robust else {}


@dataclass(frozen=True)
class Solver:
    """A refinement method: ``run(problem, solver=, seed=, callback=, **options) -> (model, FitInfo)``
    (``solver``: this one), with the facts its callers act on (they ask the solver, never compare its
    name)."""

    name: str
    run: Callable[..., tuple[Model, FitInfo]]
    objectives: tuple[str, ...]
    options: tuple[str, ...] = ()
    summary: str = ""
    cv_solvers: tuple[Solver, ...] = ()
    """Cheaper solvers for cross-validation refits, the first that minimises the objective (none:
    itself)."""
    is_swarm: bool = False
    """A particle swarm: calls ``callback(iteration, best, x)`` after every iteration (progress, cancel)
    and evaluates a swarm of candidates per iteration (:meth:`candidates`, :func:`check_swarm_size`)."""
    hybrid: bool = False
    """The swarm crosses over and mutates (the paper's hybrid), else the plain PSO."""
    is_least_squares: bool = False
    """The least-squares refiner (Levenberg–Marquardt): its leave-one-out can start from the full fit."""
    is_linear: bool = False
    """The closed-form linear solve: the model's own estimate, no refinement."""

    @property
    def memory_factor(self) -> float:
        """Candidate positions one iteration evaluates per particle, hence memory per particle and pair:
        the hybrid's candidate buffer (optimize._init) holds the moved particle, its two crossover
        children (with its personal and with the global best) and ``MUTATION_RATE`` of a mutant:
        1 + 2 + 0.1 = 3.1; the plain swarm only the moved particle (1); 0 for solvers without a swarm."""
        if not self.is_swarm:
            return 0.0
        from eyetohand.solve.optimize import MUTATION_RATE

        return 1 + 2 + MUTATION_RATE if self.hybrid else 1.0

    def candidates(self, n_particles: int) -> int:
        """Positions one iteration of this swarm evaluates (the optimiser's own count)."""
        from eyetohand.solve.optimize import candidates_per_iteration

        return candidates_per_iteration(n_particles, crossover=self.hybrid, mutation=self.hybrid)

    def minimises(self, objective: Objective) -> bool:
        """Whether this solver can minimise ``objective``."""
        return objective.name in self.objectives

    def for_cross_validation(self, objective: Objective) -> Solver:
        """The solver whose refits score held-out pairs: the swarms' are too slow to repeat n times,
        so they use ``lm`` (smooth objectives) or ``linear``."""
        return next((s for s in self.cv_solvers if s.minimises(objective)), self)


# ---------------------------------------------------------------- the solvers


def _linear(problem: Problem, **_):  # (solver, seed, callback: unused)
    f = float(problem.fitness(problem.model.params[None])[0])
    return problem.model, FitInfo(
        optimizer="linear",
        objective=problem.objective.name,
        fitness=f,
        history=(f,),
        nfev=1,
        nit=0,
        seconds=0.0,
        seed=None,
        message="closed form",
        extra=problem.extra(),
    )


def _lm(problem: Problem, **_):
    from scipy.optimize import least_squares

    model, objective, delta = problem.model, problem.objective, problem.delta_mm
    t0 = time.perf_counter()
    free = model.free_params()  # a gauge freedom's parameters stay at the start's values
    held = len(free) < model.params.size

    def full(Q):
        if not held:
            return Q
        P = np.tile(model.params, (len(Q), 1))
        P[:, free] = Q
        return P

    def fun_batch(Q):
        return problem.residuals(full(Q)).reshape(len(Q), -1)

    def fun(q):
        return fun_batch(q[None])[0]

    def jac(q):  # all finite-difference steps in one batched call
        return batch_jacobian(fun_batch, q)

    extra: dict[str, float] = {}
    start = model.params[free]
    if objective.least_squares:  # least_squares(method="lm", x_scale="jac")'s own routine and iterates
        sol = levenberg_marquardt(fun, start, jac)
    else:
        # the starting fit's errors are inflated by the very pairs Huber should discount, so the
        # threshold is re-estimated from the robust fit's own errors until it settles
        x = start
        for _round in range(HUBER_ROUNDS):
            sol = least_squares(fun, x, jac=jac, method="trf", loss="huber", f_scale=delta, x_scale="jac")
            x = sol.x
            new = huber_delta_mm(np.linalg.norm(fun(x).reshape(-1, 3), axis=1))
            if abs(new - delta) <= 0.01 * delta:
                break
            delta = new
        extra["huber_delta_mm"] = delta
    best = model.with_params(full(np.asarray(sol.x, float)[None])[0])
    f = float(objective.values(fun(sol.x).reshape(1, -1, 3), delta)[0])
    return best, FitInfo(
        optimizer="lm",
        objective=objective.name,
        fitness=f,
        history=(f,),
        nfev=int(sol.nfev),
        nit=int(sol.nfev),
        seconds=time.perf_counter() - t0,
        seed=None,
        message=str(sol.message),
        extra=extra,
    )


def _swarm(
    problem: Problem,
    *,
    solver: Solver,
    seed=None,
    callback=None,
    n_particles: int = 200,
    iterations: int = 150,
):
    """The particle swarm ``solver`` (hybrid or plain, :attr:`Solver.hybrid`) on ``problem``."""
    model = problem.model
    check_swarm_size(solver, n_particles, len(problem.uv_px))
    t0 = time.perf_counter()
    # each element alone moves the mapped points by 1/sqrt(D) mm RMS, the swarm ~1 mm (docs/pso.md)
    sigma = param_scale(
        model, problem.uv_px, problem.xyz_mm[:, 2], step_mm=PSO_SPREAD_MM / np.sqrt(model.n_params)
    )
    from eyetohand.solve.optimize import hybrid_pso, pso

    fn = hybrid_pso if solver.hybrid else pso
    res = fn(
        problem.fitness,
        model.params,
        sigma,
        n_particles=n_particles,
        iterations=iterations,
        seed=seed,
        callback=callback,
    )
    return model.with_params(res.x), FitInfo(
        optimizer=solver.name,
        objective=problem.objective.name,
        fitness=float(res.fun),
        history=tuple(float(v) for v in res.history),
        nfev=int(res.nfev),
        nit=int(res.nit),
        seconds=time.perf_counter() - t0,
        seed=int(seed) if isinstance(seed, (int, np.integer)) else None,
        message=str(res.message),
        extra=problem.extra(),
    )


_LINEAR = Solver(
    "linear",
    _linear,
    OBJECTIVES,
    summary="the model's closed-form (normalised linear) estimate",
    is_linear=True,
)
_LM = Solver(
    "lm",
    _lm,
    SMOOTH_OBJECTIVES,
    summary="Levenberg–Marquardt on the robot-space residuals",
    is_least_squares=True,
)
SOLVERS: dict[str, Solver] = {
    s.name: s
    for s in (
        _LINEAR,
        _LM,
        Solver(
            "hybrid-pso",
            _swarm,
            OBJECTIVES,
            ("n_particles", "iterations"),
            "the paper's hybrid particle swarm (PSO + crossover + mutation)",
            cv_solvers=(_LM, _LINEAR),
            is_swarm=True,
            hybrid=True,
        ),
        Solver(
            "pso",
            _swarm,
            OBJECTIVES,
            ("n_particles", "iterations"),
            "plain particle swarm (the ablation)",
            cv_solvers=(_LM, _LINEAR),
            is_swarm=True,
        ),
    )
}
OPTIMIZERS = tuple(SOLVERS)
ALL_OPTIONS = tuple(sorted({o for s in SOLVERS.values() for o in s.options}))


def get_solver(name: str | Solver) -> Solver:
    """The solver called ``name`` (a :class:`Solver` is its own); an unknown name lists the choices."""
    if isinstance(name, Solver):
        return name
    try:
        return SOLVERS[name]
    except (KeyError, TypeError):
        raise InputError(f"unknown optimizer {name!r}; choose one of: {', '.join(OPTIMIZERS)}") from None


SEED_MAX = 2**32 - 1
"""Largest seed: what every interface carries (the HTTP API, the service's database) and the
calibration file records."""


def check_seed(seed):
    """The seed rule of every fit: None (fresh entropy), a :class:`numpy.random.Generator`, or a whole
    number from 0 to :data:`SEED_MAX`; anything else is an :class:`InputError` naming field 'seed'."""
    if seed is None or isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= SEED_MAX:
        raise InputError(f"must be a whole number from 0 to {SEED_MAX}, got {seed!r}", field="seed")
    return int(seed)


SWARM_MAX_ITERATIONS = 1_000_000
"""Most iterations a swarm may be asked for (the paper's is 150; each keeps its best in the history)."""

SWARM_MAX_BYTES = 4 * 2**30
"""Most memory a swarm's evaluation may take: one iteration evaluates every candidate on every pair
at once, ~``4 × candidates × pairs × 3 × 8`` bytes of arrays."""


def check_swarm_size(kind: str | Solver, n_particles: int, n_pairs: int) -> None:
    """Refuses (:class:`InputError`) a swarm (the solver called ``kind``) whose one iteration would need
    more than :data:`SWARM_MAX_BYTES` — with how many particles would fit — instead of a MemoryError."""
    solver = get_solver(kind)
    per_row = 4 * n_pairs * 3 * 8
    rows = solver.candidates(n_particles)
    need = rows * per_row
    if need <= SWARM_MAX_BYTES:
        return
    # the rows that fit over the rows per particle, then down to the exact count (its rounding)
    most = int(SWARM_MAX_BYTES // per_row / solver.memory_factor)
    while most >= 2 and solver.candidates(most) * per_row > SWARM_MAX_BYTES:
        most -= 1
    advice = f"at most {most} particles fit" if most >= 2 else "no swarm fits: use optimizer lm"
    raise InputError(
        f"solver option 'n_particles' = {n_particles} is too many for {n_pairs} pairs: each iteration "
        f"evaluates {rows} candidates on every pair at once (~{need / 2**30:.3g} GiB of arrays, more than "
        f"the {SWARM_MAX_BYTES / 2**30:g} GiB a fit may take); {advice}"
    )


def _swarm_rows(kind: str, n: int) -> int:
    """Positions one iteration of the ``kind`` swarm evaluates (the optimiser's own count)."""
    return get_solver(kind).candidates(n)


def check_optimizer(
    name: str | Solver, objective: str | Objective = "l2", options: dict | None = None
) -> Solver:
    """The solver called ``name``, checked against the objective and the options before any work."""
    return check_fit(name, objective, options)[0]


def check_fit(
    optimizer: str | Solver, objective: str | Objective = "l2", options: dict | None = None
) -> tuple[Solver, Objective]:
    """The solver and the objective named, checked against each other and the solver options before
    any work: what a fit request resolves once."""
    solver = get_solver(optimizer)
    obj = get_objective(objective)
    if not solver.minimises(obj):
        able = [s.name for s in SOLVERS.values() if s.minimises(obj) and not s.is_linear]
        raise InputError(
            f"optimizer '{solver.name}' needs a smooth objective ({', '.join(solver.objectives)}); "
            f"'{obj.name}' works with {' or '.join(able)}"
        )
    check_solver_options(options or {})
    return solver, obj


def check_solver_options(options: dict) -> None:
    """The solver options given (``n_particles``, ``iterations``): known, positive whole numbers, a
    swarm of two or more, at most :data:`SWARM_MAX_ITERATIONS` iterations."""
    for key, value in options.items():
        if key not in ALL_OPTIONS:
            raise InputError(f"unknown solver option {key!r}; valid options: {', '.join(ALL_OPTIONS)}")
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"solver option '{key}' must be a positive whole number, got {value!r}")
    if options and options.get("n_particles", 2) < 2:
        raise InputError("solver option 'n_particles' must be at least 2")
    if options and options.get("iterations", 1) > SWARM_MAX_ITERATIONS:
        most, got = SWARM_MAX_ITERATIONS, options["iterations"]
        raise InputError(f"solver option 'iterations' must be at most {most}, got {got!r}")


def refine(
    model,
    uv_px: np.ndarray,
    xyz_mm: np.ndarray,
    *,
    optimizer: str | Solver = "linear",
    objective: str | Objective = "l2",
    seed=None,
    callback=None,
    **options,
):
    """Refine ``model`` on the pairs; returns ``(model, FitInfo)``. Options another solver takes
    (``n_particles``, ``iterations`` for the swarms) are accepted and unused by ``linear``/``lm``.
    ``optimizer`` and ``objective``: names, or the objects a fit request resolved."""
    solver, obj = check_fit(optimizer, objective, options)
    uv = np.asarray(uv_px, float)
    xyz = np.asarray(xyz_mm, float)
    with np.errstate(all="ignore"):
        start = model.batch_image_to_robot(model.params[None], uv, xyz[:, 2])[0] - xyz
    lost = ~np.isfinite(start).all(axis=1)
    if lost.any():
        raise DegenerateError(
            f"model '{model.name}': its starting estimate maps {int(lost.sum())} of {len(uv)} pairs to no "
            "finite point (beyond its lens's fold or its horizon): the pairs do not determine it"
        )
    problem = Problem(model, uv, xyz, obj, huber_delta_mm(np.linalg.norm(start, axis=1)))
    own = {k: v for k, v in options.items() if k in solver.options}
    return solver.run(problem, solver=solver, seed=seed, callback=callback, **own)


def param_scale(model, uv_px, z_mm, step_mm: float = 1.0) -> np.ndarray:
    """Per-parameter change that moves the mapped training points by about ``step_mm`` (RMS).

    Computed from a finite-difference Jacobian at the current parameters; used as the PSO's initial
    spread so that every element of a badly scaled vector (like the paper's B, whose elements range
    over 6 orders of magnitude) is explored on the same footing in mm.
    """
    p = model.params
    uv, z = np.asarray(uv_px, float), np.asarray(z_mm, float)
    J = batch_jacobian(
        lambda P: model.batch_image_to_robot(P, uv, z).reshape(len(P), -1),
        p,
        step=1e-6 * np.maximum(np.abs(p), 1e-3),
    )  # (N*3, D) mm per unit
    sens = np.sqrt((J**2).sum(axis=0) / len(uv))  # RMS over points of the 3-D displacement
    return step_mm / np.maximum(sens, 1e-12)
