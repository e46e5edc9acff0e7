"""Hybrid particle swarm optimisation (PSO with genetic crossover and mutation).

This implements section IV of the reference paper ("Algorithm of Hand-Eye Calibration for
Industrial Robot"): a global-best particle swarm (equations 14 and 15) whose particles are, after
every move, crossed over a random segment with their personal best and with the global best, and
then mutated by normally distributed random particles. Crossover and mutation are *elitist*: a
new individual replaces the particle only when its fitness is strictly lower.

Why a mutation around the global best with a log-uniform step: on the paper's calibration problem
(a narrow, partly flat valley in the 12 elements of B) the swarm collapses onto a point of the
valley floor and stalls there; mutants at all scales around the best keep making progress along
the valley (docs/pso.md has the measurements that led to this choice).

Everything is vectorised over the swarm: ``fitness`` receives an ``(n, D)`` array of candidate
positions and returns ``(n,)`` fitness values. Random numbers are drawn in bulk from a
:class:`numpy.random.Generator`, so the same seed gives a bit-identical result. The swarm, its
candidates and the random numbers live in buffers allocated once per run and updated in place
(no per-iteration allocation of swarm-sized arrays); the operations and their order are those of
the straightforward formulas, so results are the same, bit for bit. Four steps of an iteration
(the move, the crossover children, the elitist choice, the bests) run compiled where the install
built ``eyetohand.solve._swarm`` (:func:`swarm_kernel`), one pass each instead of several NumPy calls:
the same draws and the same numbers, a third less time on a cheap fitness (docs/pso.md).

Units: positions, ``x0``, ``sigma``, ``bounds`` and velocities are in the units of the
optimisation parameters (for the paper's calibration matrix ``B``: pixels/mm for ``b11``..``b23``,
pixels for ``b14`` and ``b24``, 1/mm for ``b31``..``b33``, dimensionless for ``b34``); fitness
values are in the units of ``fitness`` (the paper's equation 16: mm).

Iteration ``k`` (``k = 1 .. iterations``), with ``n = n_particles``:

1. velocity and position update (eqs 14, 15), ``r1, r2 ~ U[0, 1)`` drawn per particle and
   dimension;
2. crossover of each moved particle with its personal best: two positions are drawn uniformly
   from ``0 .. D-1`` per particle and the segment between them (inclusive) is copied from the
   personal best into a copy of the particle;
3. separately, crossover of each moved particle with the global best, the same way with a new
   random segment;
4. mutation: ``max(1, round(mutation_rate * n))`` particles, drawn at random without replacement,
   each get a mutant ``g + s * z`` with ``g`` the global best, ``z ~ N(0, I)`` and a step scale
   ``s = sigma * 10 ** (-u)``, ``u ~ U(0, mutation_decades)`` drawn per mutant (log-uniform: the
   mutants probe every scale from the initial spread ``sigma`` down to
   ``sigma * 10 ** -mutation_decades``, with no adaptation state);
   the moved swarm, both crossover children and the mutants are evaluated in ONE call of
   ``fitness`` (``3 n + n_mut`` rows); then, elitist, each particle becomes the best of
   (moved particle, child with personal best, child with global best) -- ties keep the particle
   -- and a mutant replaces its particle only if it is strictly better;
5. personal and global bests are updated; the global best fitness is appended to ``history``;
   ``callback`` is called; stop criteria are checked.

The initial swarm (iteration 0, not counted in ``nit``) is ``x0 + sigma * z``, ``z ~ N(0, I)``
(the paper: mean = the elements of ``B``, variance sqrt(2), i.e. ``sigma = 2 ** 0.25``; because
the elements of ``B`` differ by orders of magnitude, ``sigma`` may be a per-element vector), with
zero initial velocity; it costs ``n`` evaluations. So
``nfev = n + nit * (n + 2 n [crossover] + max(1, round(mutation_rate * n)) [mutation])``
(``nfev_per_iteration`` in the result); plain :func:`pso` costs ``n + nit * n``.

There is no velocity clamping and no restart: with the paper's ``w``, ``c1``, ``c2`` (close to
Clerc's constriction values) the swarm is stable without clamping. Fitness values that are NaN
are treated as ``+inf`` (never accepted as a best).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np

_SWARM: ModuleType | None
try:  # the optional compiled swarm steps (setup.py); see swarm_kernel
    from eyetohand.solve import _swarm as _SWARM
except ImportError:
    _SWARM = None

__all__ = ["OptimizeResult", "hybrid_pso", "pso"]

Fitness = Callable[[np.ndarray], np.ndarray]
Callback = Callable[[int, float, np.ndarray], object]

STATUS_MAX_ITERATIONS = 0
STATUS_STALLED = 1
STATUS_CALLBACK = 2

# crossover segment masks come from a (D*D, D) lookup table up to this dimension
_MASK_TABLE_MAX_DIM = 64


@dataclass(frozen=True)
class OptimizeResult:
    """Outcome of :func:`hybrid_pso` / :func:`pso`.

    Attributes:
        x: best position found, shape ``(D,)`` (parameter units).
        fun: fitness at ``x`` (fitness units).
        history: best fitness after each iteration, shape ``(nit,)``; non-increasing.
        nfev: number of fitness evaluations (candidate positions evaluated, summed over batches).
        nit: number of iterations run (the initial swarm evaluation is not an iteration).
        success: True when the run ended with a finite best fitness.
        message: why the run stopped.
        status: 0 iteration limit, 1 stalled, 2 stopped by the callback.
        seed: the ``seed`` argument as given (an int, None or a Generator).
        n_particles: swarm size used.
        nfev_per_iteration: evaluations per iteration (swarm + crossover + mutation candidates).
    """

    x: np.ndarray
    fun: float
    history: np.ndarray
    nfev: int
    nit: int
    success: bool
    message: str
    status: int
    seed: object = field(default=None, repr=False)
    n_particles: int = 0
    nfev_per_iteration: int = 0


def swarm_kernel() -> ModuleType | None:
    """``eyetohand.solve._swarm``, four steps of an iteration compiled (src/eyetohand/solve/_swarm.c, built at
    install): the move, the crossover children, the elitist choice and the bests, each one pass
    instead of several NumPy calls. None where it could not be built: :func:`hybrid_pso` then runs
    them in NumPy, with the same random draws and the same numbers (positions and bests bit for
    bit), slower on a cheap fitness."""
    return _SWARM


def _int_option(name: str, value: object, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def _float_option(name: str, value: object, minimum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    value = float(value)
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


def _per_dimension(name: str, value: object, dim: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or an array of numbers, got {value!r}") from None
    if arr.ndim == 0:
        return np.full(dim, float(arr))
    if arr.shape != (dim,):
        raise ValueError(f"{name} must be a scalar or have shape ({dim},) to match x0, got shape {arr.shape}")
    return arr.copy()


def _make_rng(seed: object) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None or (isinstance(seed, numbers.Integral) and not isinstance(seed, bool)):
        if seed is not None and seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed}")
        return np.random.default_rng(None if seed is None else int(seed))
    raise ValueError(f"seed must be an int, None or a numpy.random.Generator, got {type(seed).__name__}")


MUTATION_RATE = 0.1  # hybrid_pso's default share of particles given a mutant each iteration


def candidates_per_iteration(
    n_particles: int, *, crossover: bool = True, mutation: bool = True, mutation_rate: float = MUTATION_RATE
) -> int:
    """Positions one iteration evaluates: the moved swarm, both crossover children of each particle
    and ``max(1, round(mutation_rate * n))`` mutants (``pso``: the swarm alone)."""
    n = n_particles
    return n + (2 * n if crossover else 0) + (max(1, round(mutation_rate * n)) if mutation else 0)


def hybrid_pso(
    fitness: Fitness,
    x0: np.ndarray,
    sigma: float | np.ndarray,
    *,
    n_particles: int = 200,
    iterations: int = 150,
    w: float = 0.7153,
    c1: float = 1.4801,
    c2: float = 1.4801,
    crossover: bool = True,
    mutation: bool = True,
    mutation_rate: float = MUTATION_RATE,
    mutation_decades: float = 6.0,
    seed: int | np.random.Generator | None = None,
    callback: Callback | None = None,
    stall_iterations: int | None = None,
    stall_tol: float = 0.0,
    bounds: tuple[float | np.ndarray, float | np.ndarray] | None = None,
) -> OptimizeResult:
    """Minimise ``fitness`` with the paper's hybrid particle swarm optimiser.

    See the module docstring for the exact iteration; defaults are the paper's settings
    (200 particles, 150 iterations, ``w = 0.7153``, ``c1 = c2 = 1.4801``).

    Args:
        fitness: vectorised objective: ``(m, D)`` positions -> ``(m,)`` values (lower is better).
            ``m`` is ``n_particles`` for the initial swarm, then ``nfev_per_iteration`` (the
            moved swarm, both crossover children and the mutants, in that order) once per
            iteration. The positions are a read-only view of a buffer the optimiser reuses:
            copy them to keep them past the call. NaN values are treated as ``+inf``.
        x0: centre of the initial swarm, shape ``(D,)`` (parameter units).
        sigma: standard deviation of the initial swarm around ``x0``: a positive scalar or a
            ``(D,)`` vector in parameter units; also the largest mutation step. For badly scaled
            parameters use a vector: for calibration, ``sigma_j = (1 mm / sqrt(D)) / s_j`` with
            ``s_j`` the RMS over the calibration points of the mapped-point displacement per unit
            of parameter ``j`` (mm/unit), so the initial swarm moves the mapped points by ~1 mm
            RMS (``docs/pso.md``).
        n_particles: swarm size, >= 2.
        iterations: maximum number of iterations, >= 1.
        w: inertia weight of equation 14.
        c1: cognitive acceleration factor (towards the personal best), >= 0.
        c2: social acceleration factor (towards the global best), >= 0.
        crossover: enable the two segment crossovers (personal best, global best).
        mutation: enable the normal-distribution mutation.
        mutation_rate: fraction of particles given a mutation candidate each iteration, in
            ``(0, 1]``; at least one particle is mutated when ``mutation`` is on.
        mutation_decades: mutation step scales are log-uniform in
            ``[sigma * 10 ** -mutation_decades, sigma]``, >= 0.
        seed: int, None (fresh entropy) or a :class:`numpy.random.Generator` (used and advanced).
        callback: ``callback(iteration, best_fun, best_x)`` after each iteration (``iteration``
            counts from 1, ``best_fun`` in fitness units, ``best_x`` a copy); a truthy return value
            (e.g. True) stops the run.
        stall_iterations: if given, stop once the best fitness has not improved by more than
            ``stall_tol`` for this many consecutive iterations. Off by default.
        stall_tol: improvement threshold for the stall test (fitness units), >= 0.
        bounds: optional ``(lower, upper)``, each a scalar or ``(D,)``; positions and candidates
            are clipped into the box (velocities are not changed).

    Returns:
        An :class:`OptimizeResult`.

    Raises:
        ValueError: an option is invalid, or ``fitness`` returns a wrong shape.
    """
    if not callable(fitness):
        raise ValueError(f"fitness must be callable, got {type(fitness).__name__}")
    opts = _Settings.checked(
        x0,
        sigma,
        n_particles=n_particles,
        iterations=iterations,
        w=w,
        c1=c1,
        c2=c2,
        crossover=crossover,
        mutation=mutation,
        mutation_rate=mutation_rate,
        mutation_decades=mutation_decades,
        stall_iterations=stall_iterations,
        stall_tol=stall_tol,
        callback=callback,
        bounds=bounds,
    )
    swarm = _init(fitness, opts, _make_rng(seed))

    history: list[float] = []
    status, message = STATUS_MAX_ITERATIONS, f"maximum number of iterations ({opts.iterations}) reached"
    stall_count = 0
    for k in range(1, opts.iterations + 1):
        previous = swarm.gbest_f
        _step(swarm)
        history.append(swarm.gbest_f)
        if callback is not None and callback(k, swarm.gbest_f, swarm.gbest_x.copy()):
            status, message = STATUS_CALLBACK, f"stopped by callback after iteration {k}"
            break
        if opts.stall_iterations is not None:
            gain = previous - swarm.gbest_f if swarm.gbest_f < previous else 0.0
            stall_count = 0 if gain > opts.stall_tol else stall_count + 1
            if stall_count >= opts.stall_iterations:
                status = STATUS_STALLED
                message = (
                    f"best fitness improved by no more than {opts.stall_tol:g} for "
                    f"{opts.stall_iterations} iterations (stopped after iteration {k})"
                )
                break

    return OptimizeResult(
        x=swarm.gbest_x,
        fun=swarm.gbest_f,
        history=np.asarray(history, dtype=float),
        nfev=swarm.nfev,
        nit=len(history),
        success=bool(np.isfinite(swarm.gbest_f)),
        message=message,
        status=status,
        seed=seed,
        n_particles=opts.n,
        nfev_per_iteration=swarm.n_rows,
    )


@dataclass(frozen=True)
class _Settings:
    """:func:`hybrid_pso`'s options, checked (units as there)."""

    x0: np.ndarray
    sigma: np.ndarray  # (D,)
    n: int
    iterations: int
    w: float
    c1: float
    c2: float
    crossover: bool
    mutation: bool
    mutation_rate: float
    mutation_decades: float
    stall_iterations: int | None
    stall_tol: float
    lower: np.ndarray | None  # (D,) or None: no bounds
    upper: np.ndarray | None

    @classmethod
    def checked(cls, x0: object, sigma: object, *, bounds: Any, **kw: Any) -> _Settings:
        """The options, or the ValueError that names the first bad one."""
        try:
            x0_v = np.asarray(x0, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"x0 must be a 1-D array of numbers, got {x0!r}") from None
        if x0_v.ndim != 1 or x0_v.size == 0:
            raise ValueError(f"x0 must be a non-empty 1-D array, got shape {x0_v.shape}")
        if not np.all(np.isfinite(x0_v)):
            raise ValueError("x0 must be finite")
        dim = x0_v.size
        sigma_v = _per_dimension("sigma", sigma, dim)
        if not np.all(np.isfinite(sigma_v)) or np.any(sigma_v <= 0):
            raise ValueError(f"sigma must be finite and > 0, got {np.asarray(sigma)!r}")
        n = _int_option("n_particles", kw["n_particles"], 2)
        iterations = _int_option("iterations", kw["iterations"], 1)
        w = _float_option("w", kw["w"])
        c1 = _float_option("c1", kw["c1"], 0.0)
        c2 = _float_option("c2", kw["c2"], 0.0)
        mutation_rate = _float_option("mutation_rate", kw["mutation_rate"])
        if kw["mutation"] and not 0.0 < mutation_rate <= 1.0:
            raise ValueError(f"mutation_rate must be in (0, 1], got {mutation_rate}")
        mutation_decades = _float_option("mutation_decades", kw["mutation_decades"], 0.0)
        stall_iterations = kw["stall_iterations"]
        if stall_iterations is not None:
            stall_iterations = _int_option("stall_iterations", stall_iterations, 1)
        stall_tol = _float_option("stall_tol", kw["stall_tol"], 0.0)
        callback = kw["callback"]
        if callback is not None and not callable(callback):
            raise ValueError(f"callback must be callable or None, got {type(callback).__name__}")
        lower = upper = None
        if bounds is not None:
            if len(bounds) != 2:
                raise ValueError(f"bounds must be (lower, upper), got {len(bounds)} items")
            lower = _per_dimension("bounds[0]", bounds[0], dim)
            upper = _per_dimension("bounds[1]", bounds[1], dim)
            if np.any(np.isnan(lower)) or np.any(np.isnan(upper)) or np.any(lower > upper):
                raise ValueError("bounds must satisfy lower <= upper in every dimension")
        return cls(
            x0=x0_v,
            sigma=sigma_v,
            n=n,
            iterations=iterations,
            w=w,
            c1=c1,
            c2=c2,
            crossover=bool(kw["crossover"]),
            mutation=bool(kw["mutation"]),
            mutation_rate=mutation_rate,
            mutation_decades=mutation_decades,
            stall_iterations=stall_iterations,
            stall_tol=stall_tol,
            lower=lower,
            upper=upper,
        )


@dataclass(frozen=True)
class _Crossover:
    """The crossover's views of the candidate buffer: ``children[0]`` the particles crossed with their
    personal bests, ``children[1]`` with the global best; the segment-mask lookup table."""

    children: np.ndarray  # (2, n, D) = candidate rows n .. 3n-1
    moved_and_children: np.ndarray  # (3, n, D) = candidate rows 0 .. 3n-1
    fx: np.ndarray  # (3, n): their fitness
    rows: np.ndarray  # 0 .. n-1
    mask_table: np.ndarray | None  # (D*D, D): row lo*D + hi (either order) marks columns min..max
    end_weights: np.ndarray  # (2,): [D, 1], a pair of ends -> its row of mask_table


@dataclass(frozen=True)
class _Mutation:
    """The mutants' views of the candidate buffer (its last ``n_mut`` rows) and of their fitness."""

    n_mut: int
    mutants: np.ndarray  # (n_mut, D)
    f_mut: np.ndarray  # (n_mut,)


@dataclass(eq=False)
class _Swarm:
    """One run's state: the swarm, its bests, the random generator and the buffers every iteration
    reuses (allocated once by :func:`_init`, updated in place by :func:`_step`).

    One candidate array ``cand`` holds, per iteration, the moved swarm (rows 0..n-1, which is also
    the swarm itself: ``x`` is a view), both crossover children and the mutants; ``fitness`` gets a
    read-only view of it, so one call evaluates everything and nothing is concatenated. The two
    attractors are stacked in ``partner``: ``partner[0]`` IS the personal bests, ``partner[1]`` the
    global best in every row, so the move and both crossovers each take one operation for both."""

    opts: _Settings
    fitness: Fitness
    rng: np.random.Generator
    kernel: ModuleType | None  # the compiled steps (swarm_kernel()), or None: NumPy
    n_rows: int  # candidates per iteration
    cand: np.ndarray  # (n_rows, D)
    cand_ro: np.ndarray  # read-only view of cand, what fitness sees
    fc: np.ndarray  # (n_rows,) candidates' fitness
    x: np.ndarray  # (n, D) = cand[:n]: positions
    f: np.ndarray  # (n,) their fitness
    v: np.ndarray  # (n, D) velocities
    partner: np.ndarray  # (2, n, D): personal bests, global best
    pbest_f: np.ndarray  # (n,) personal bests' fitness
    coef: np.ndarray  # (2, 1, 1): c1, c2
    r: np.ndarray  # (2, n, D): r1, r2 of the move
    scratch: np.ndarray  # (2, n, D): attractor - x (the children's rows, before they are written)
    xover: _Crossover | None
    mut: _Mutation | None
    gbest_x: np.ndarray
    gbest_f: float
    nfev: int = 0

    @property
    def pbest_x(self) -> np.ndarray:
        return self.partner[0]


def _init(fitness: Fitness, opts: _Settings, rng: np.random.Generator) -> _Swarm:
    """The buffers and the evaluated initial swarm ``x0 + sigma * z`` (zero velocity, iteration 0)."""
    n, dim = opts.n, opts.x0.size
    n_rows = candidates_per_iteration(
        n, crossover=opts.crossover, mutation=opts.mutation, mutation_rate=opts.mutation_rate
    )
    cand = np.empty((n_rows, dim))
    cand_ro = cand.view()
    cand_ro.flags.writeable = False
    fc = np.empty(n_rows)
    xover: _Crossover | None = None
    mut: _Mutation | None = None
    if opts.crossover:
        scratch = cand[n : 3 * n].reshape(2, n, dim)
        xover = _Crossover(
            scratch,
            cand[: 3 * n].reshape(3, n, dim),
            fc[: 3 * n].reshape(3, n),
            np.arange(n),
            _mask_table(dim),
            np.array([dim, 1]),
        )
    else:
        scratch = np.empty((2, n, dim))
    if opts.mutation:
        n_mut = n_rows - n - (2 * n if opts.crossover else 0)
        mut = _Mutation(n_mut, cand[n_rows - n_mut :], fc[n_rows - n_mut :])
    s = _Swarm(
        opts,
        fitness,
        rng,
        _SWARM,
        n_rows,
        cand,
        cand_ro,
        fc,
        x=cand[:n],
        f=np.empty(n),
        v=np.zeros((n, dim)),
        partner=np.empty((2, n, dim)),
        pbest_f=np.empty(n),
        coef=np.array([opts.c1, opts.c2]).reshape(2, 1, 1),
        r=np.empty((2, n, dim)),
        scratch=scratch,
        xover=xover,
        mut=mut,
        gbest_x=np.empty(dim),
        gbest_f=np.inf,
    )
    rng.standard_normal((n, dim), out=s.x)
    s.x *= opts.sigma
    s.x += opts.x0
    if opts.lower is not None:
        np.clip(s.x, opts.lower, opts.upper, out=s.x)
    s.f[:] = _evaluate(s, n)
    s.pbest_x[...] = s.x
    s.pbest_f = s.f.copy()
    g = int(s.pbest_f.argmin())
    s.gbest_x, s.gbest_f = s.pbest_x[g].copy(), float(s.pbest_f[g])
    s.partner[1] = s.gbest_x
    return s


def _mask_table(dim: int) -> np.ndarray | None:
    """Crossover segment masks by lookup, up to :data:`_MASK_TABLE_MAX_DIM`: row ``lo*D + hi`` (either
    order) marks columns ``min .. max``; None above (the masks are then computed per draw)."""
    if dim > _MASK_TABLE_MAX_DIM:
        return None
    cols = np.arange(dim)
    ends = np.arange(dim * dim)
    lo_t = np.minimum(ends // dim, ends % dim)[:, None]
    hi_t = np.maximum(ends // dim, ends % dim)[:, None]
    return (cols >= lo_t) & (cols <= hi_t)


def _step(s: _Swarm) -> None:
    """One iteration (module docstring, steps 1 to 5): move, cross over, mutate, evaluate every
    candidate in one call, keep the best of each particle's, update the bests. Random numbers are
    drawn in this order: ``r``, the crossover ends, the mutants' particles, scales and directions."""
    n, dim = s.opts.n, s.opts.x0.size
    s.rng.random((2, n, dim), out=s.r)
    _move(s)
    if s.xover is not None:
        _crossover(s, s.xover)
    idx = _mutate(s, s.mut) if s.mut is not None else None
    _evaluate(s, s.n_rows)
    if s.xover is not None:
        _select(s, s.xover)
    else:
        s.f[:] = s.fc[:n]
    if s.mut is not None and idx is not None:
        # elitist: a mutant replaces its particle only if better
        better = s.mut.f_mut < s.f[idx]
        if better.any():
            won = idx[better]
            s.x[won], s.f[won] = s.mut.mutants[better], s.mut.f_mut[better]
    _update_bests(s)


def _evaluate(s: _Swarm, rows: int) -> np.ndarray:
    """Fitness of the first ``rows`` candidates, into ``fc`` (NaN -> +inf); counted in ``nfev``."""
    pos = s.cand_ro if rows == s.n_rows else s.cand_ro[:rows]
    values = np.asarray(s.fitness(pos), dtype=float)
    if values.shape != (rows,):
        raise ValueError(
            f"fitness must return shape ({rows},) for an input of shape {pos.shape}, got shape {values.shape}"
        )
    s.nfev += rows
    out = s.fc[:rows]
    np.fmin(values, np.inf, out=out)  # copies into our buffer; NaN -> +inf
    return out


def _move(s: _Swarm) -> None:
    """Eqs (14) and (15) in place, with ``r`` drawn: v = w v + (c1 r1) (pbest - x) +
    (c2 r2) (gbest - x); x = x + v; then clipped into the bounds."""
    o, x, v, r = s.opts, s.x, s.v, s.r
    if s.kernel is not None:
        s.kernel.move(x, v, s.partner, r, o.w, o.c1, o.c2, o.lower, o.upper)
        return
    np.multiply(r, s.coef, out=r)
    np.multiply(r, np.subtract(s.partner, x, out=s.scratch), out=r)  # (children written after this)
    np.multiply(v, o.w, out=v)
    np.add(v, r[0], out=v)
    np.add(v, r[1], out=v)
    np.add(x, v, out=x)
    if o.lower is not None:
        np.clip(x, o.lower, o.upper, out=x)


def _crossover(s: _Swarm, xo: _Crossover) -> None:
    """Steps 2 and 3: each moved particle crossed with its personal best and, separately, with the
    global best, over segments whose ends are uniform in 0 .. D-1 (one (2, n, 2) draw: the same
    draws, in the same order, as one (n, 2) draw per crossover)."""
    ends = s.rng.integers(0, s.opts.x0.size, size=(2, s.opts.n, 2))
    if s.kernel is not None:
        s.kernel.children(xo.children, s.x, s.partner, ends)
        return
    xo.children[...] = s.x
    if xo.mask_table is not None:
        masks = xo.mask_table.take(ends @ xo.end_weights, axis=0)
    else:
        lo = ends.min(axis=2, keepdims=True)
        hi = ends.max(axis=2, keepdims=True)
        cols = np.arange(s.opts.x0.size)
        masks = (cols >= lo) & (cols <= hi)
    np.copyto(xo.children, s.partner, where=masks)


def _mutate(s: _Swarm, mu: _Mutation) -> np.ndarray:
    """Step 4: mutants normally distributed around the global best with a log-uniform step scale,
    each aimed at one particle drawn without replacement; returns those particles' indices."""
    o = s.opts
    idx = s.rng.choice(o.n, size=mu.n_mut, replace=False)
    scale = o.sigma * 10.0 ** (-o.mutation_decades * s.rng.random((mu.n_mut, 1)))
    mutants = mu.mutants
    s.rng.standard_normal((mu.n_mut, o.x0.size), out=mutants)
    mutants *= scale
    mutants += s.gbest_x
    if o.lower is not None:
        np.clip(mutants, o.lower, o.upper, out=mutants)
    return idx


def _select(s: _Swarm, xo: _Crossover) -> None:
    """Elitist: each particle becomes the best of (particle, child with pbest, child with gbest);
    ties keep the particle (argmin takes the first)."""
    if s.kernel is not None:
        s.kernel.select(xo.moved_and_children, xo.fx, s.f)
        return
    pick = xo.fx.argmin(axis=0)
    s.x[...] = xo.moved_and_children[pick, xo.rows]  # the gather copies before x is written
    xo.fx.min(axis=0, out=s.f)


def _update_bests(s: _Swarm) -> None:
    """Step 5: personal bests where improved; the global best where the least of them is lower."""
    if s.kernel is not None:
        g = s.kernel.bests(s.pbest_x, s.pbest_f, s.x, s.f)
    else:
        improved = s.f < s.pbest_f
        np.copyto(s.pbest_x, s.x, where=improved[:, None])
        np.copyto(s.pbest_f, s.f, where=improved)
        g = int(s.pbest_f.argmin())
    if s.pbest_f[g] < s.gbest_f:
        s.gbest_x, s.gbest_f = s.pbest_x[g].copy(), float(s.pbest_f[g])
        s.partner[1] = s.gbest_x


def pso(fitness: Fitness, x0: np.ndarray, sigma: float | np.ndarray, **kwargs: Any) -> OptimizeResult:
    """Plain global-best PSO (eqs 14, 15): :func:`hybrid_pso` with crossover and mutation off.

    Accepts the same keyword arguments as :func:`hybrid_pso` except ``crossover`` and
    ``mutation``.
    """
    for key in ("crossover", "mutation"):
        if key in kwargs:
            raise ValueError(f"pso() runs without crossover and mutation; do not pass {key!r}")
    return hybrid_pso(fitness, x0, sigma, crossover=False, mutation=False, **kwargs)
