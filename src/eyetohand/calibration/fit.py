"""calibrate(): point pairs × model × solver → Calibration, with automatic model choice.

``model="auto"`` scores every candidate the pairs can support by cross-validation (leave-one-out up
to 40 pairs, else 10 folds) on the user's objective (held-out RMS for ``l2``, the largest held-out
error for ``linf``, the Huber loss for ``huber``) and by its full fit's robot-space residual sum of
squares. Starting from the simplest, it moves to a candidate with more fitted numbers only when the
data support them: a nested-model F-test of the two fits' residual sums of squares (the extra
numbers' count as the numerator's degrees of freedom, the larger fit's residual degrees of freedom
as the denominator's) rejects "the extra terms are zero" at ``AUTO_ALPHA`` (2 %), and its held-out
score is lower too. The F-test holds only where the richer model nests the simpler (``Model.nests``:
the homography and the affine map); between models that do not (dlt3d with its skew, the camera with
its lens) Vuong's non-nested likelihood-ratio test, penalised by Schwarz's term, takes its place at
the same level. "Lowest held-out score wins" alone took a lens model on a lens-free cell in
2–24 % of trials (docs/limit.md). A candidate is considered only when the pairs give at least 8 more
equations than it has unknowns (2n ≥ unknowns + 8), so that its held-out score means something,
and when the pairs' geometry can determine its numbers (``Model.unobservable``: the camera's depth,
which a height span too small for its distance and pixel noise does not show); the report says why
each candidate was or was not taken. The chosen model's held-out residuals are
reused as the calibration's leave-one-out statistics (not computed twice).

Leave-one-out without n refits (:func:`loo_gauss_newton`), for the least-squares objective (``l2``)
with ``lm`` — or ``linear`` on a model linear in its parameters (affine) — on models whose subset
fit refines the same parameter family (``Model.loo_warm_start``; not homography-radial, whose lens is
re-fitted on every subset): all n held-out fits start from the full fit's parameters and take
Gauss–Newton steps together (one batched Jacobian per step, (n, D, D) normal equations) until the
steps vanish. On a model linear in its parameters the first step is exact (it is the hat-matrix
formula e_i / (1 − h_ii) written as a refit); on the others it converges to the refit's minimum from
a start one pair away. tests/test_speed_paths.py checks it against full refits (held-out residuals
within 1e-6 mm on the paper's data and on simulated cells). Anything else — a degenerate subset, a
step that does not settle, other objectives — falls back to refitting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from eyetohand.calibration.checking import check_warnings
from eyetohand.calibration.circles import fit_corrected
from eyetohand.calibration.file import Calibration
from eyetohand.calibration.proof import derived_region
from eyetohand.calibration.request import AutoModel, FitRequest, ModelChoice, resolve_model
from eyetohand.core import DegenerateError, InputError, PointPairs, TcpOffset
from eyetohand.geometry import ONE_HEIGHT_RULE, fit_height_plane
from eyetohand.models import MODELS, HeightRule, Model, get_model
from eyetohand.solve import (
    Objective,
    Solver,
    Uncertainty,
    check_fit,
    correct_pairs,
    estimate_tcp_offset,
    get_objective,
    get_solver,
    has_turns,
    huber_delta_mm,
    mapped_residuals,
    pair_leverage,
    reference_pairs,
    refine,
    stats_from_residuals,
)

# the tool offset's fits, resolved once: on l2, auto choosing its model with lm (calibrate's
# defaults), the offset fitted in closed form
TCP_OBJECTIVE = get_objective("l2")
TCP_CHOICE_SOLVER = get_solver("lm")
TCP_SOLVER = get_solver("linear")

AUTO_ALPHA = 0.02  # significance level of the nested-model F-test that admits more fitted numbers
SPARE_EQUATIONS = 8
LOO_MAX_PAIRS = 40


def _model_class(model: str | type[Model]) -> type[Model]:
    return model if isinstance(model, type) else get_model(model)


def fit_model(
    pairs: PointPairs,
    model: str | type[Model],
    optimizer: str | Solver = "lm",
    objective: str | Objective = "l2",
    *,
    image_size=None,
    seed=None,
    callback=None,
    **solver_options,
):
    """Estimate ``model`` (a name or a model class) on ``pairs`` and refine it with ``optimizer`` on
    ``objective`` (names, or the resolved objects): returns ``(Model, FitInfo)``."""
    cls = _model_class(model)
    try:
        base = cls.from_pairs(pairs.uv_px, pairs.xyz_mm, image_size=image_size)
    except InputError as exc:
        raise type(exc)(f"{pairs.source}: {exc}") from None
    except np.linalg.LinAlgError as exc:  # a singular system the model's own checks did not foresee
        raise _unsolvable(pairs, cls, exc) from None
    try:
        return refine(
            base,
            pairs.uv_px,
            pairs.xyz_mm,
            optimizer=optimizer,
            objective=objective,
            seed=seed,
            callback=callback,
            **solver_options,
        )
    except np.linalg.LinAlgError as exc:
        raise _unsolvable(pairs, cls, exc) from None


def _unsolvable(pairs: PointPairs, cls: type[Model], exc: np.linalg.LinAlgError) -> DegenerateError:
    return DegenerateError(f"{pairs.source}: model {cls.name!r} cannot be solved on these pairs ({exc})")


def folds_for(n: int, seed=0) -> list[np.ndarray]:
    """Held-out index sets: one per pair up to 40 pairs, else 10 seeded folds."""
    if n <= LOO_MAX_PAIRS:
        return [np.array([i]) for i in range(n)]
    perm = np.random.default_rng(seed).permutation(n)
    return np.array_split(perm, 10)


LOO_GN_MAX_STEPS = 12
LOO_GN_TOL_MM = 1e-7  # Gauss–Newton stops when no step moves the mapped pairs by more than this


def loo_gauss_newton(full: Model, uv_px: np.ndarray, xyz_mm: np.ndarray) -> np.ndarray | None:
    """Leave-one-out residuals (N, 3) mm by Gauss–Newton from the full least-squares fit ``full``,
    all N held-out fits at once (see the module docstring); None when a held-out fit is degenerate
    or does not settle (the caller then refits)."""
    uv = np.asarray(uv_px, float)
    xyz = np.asarray(xyz_mm, float)
    z = xyz[:, 2]
    n = len(uv)
    free = full.free_params()  # a gauge freedom's parameters stay at the full fit's, as lm holds them
    D = len(free)
    keep = 1.0 - np.eye(n)  # keep[i, j]: pair j is in held-out fit i
    P = np.tile(full.params, (n, 1))
    steps = 3 if full.linear_in_params else LOO_GN_MAX_STEPS  # linear: one step, then rounding
    last = np.inf
    with np.errstate(all="ignore"):
        for step in range(steps):
            R, J = _map_and_jacobian(full, P, uv, z)  # (n, N, 3), (n, N, 3, all parameters)
            R -= xyz
            if D < P.shape[1]:
                J = J[..., free]
            Jk = (J * keep[:, :, None, None]).reshape(n, -1, D)
            A = Jk.transpose(0, 2, 1) @ Jk  # (n, D, D)
            g = (Jk.transpose(0, 2, 1) @ R.reshape(n, -1, 1))[..., 0]
            s = np.sqrt(np.einsum("idd->id", A))
            if not (np.isfinite(A).all() and np.isfinite(g).all() and (s > 0).all()):
                return None
            As = A / (s[:, :, None] * s[:, None, :])
            try:
                scaled = -np.linalg.solve(As, (g / s)[..., None])[..., 0]  # ≈ mm the step moves the pairs
            except np.linalg.LinAlgError:
                return None
            biggest = float(np.abs(scaled).max())
            settled = biggest <= LOO_GN_TOL_MM
            if not settled and biggest > 0.5 * last:
                return None  # the steps stopped shrinking (a rounding floor above the tolerance): refit
            last = biggest
            # conditioned where the steps start and where they end (between, a step that an
            # ill-conditioned subset throws far does not settle); As is symmetric: its condition
            # number from its eigenvalues
            if step == 0 or settled:
                ev = np.linalg.eigvalsh(As)
                if not (ev[:, 0] > 1e-12 * ev[:, -1]).all():
                    return None  # a held-out subset that does not determine the model: refit says why
            P[:, free] += scaled / s  # every parameter but a gauge's (the same sums as P + step)
            if settled:
                break
        else:
            return None
        held = full.batch_image_to_robot(P, uv, z)  # (n, N, 3)
    res = held[np.arange(n), np.arange(n)] - xyz
    if full.height_rule is not HeightRule.COMPUTED:
        res[:, 2] = _held_out_plane_z(full, z)
    return res if np.isfinite(res).all() else None


def _map_and_jacobian(model: Model, P: np.ndarray, uv: np.ndarray, z: np.ndarray):
    """(P, N, 3) mapped pairs and (P, N, 3, D) their parameter derivative: the model's closed form
    when it has one, else central differences (all rows in one batched call)."""
    closed = model.batch_map_and_jacobian(P, uv, z)
    if closed is not None:
        return closed
    n, D = P.shape
    h = 1e-5 * np.maximum(np.abs(P), 1e-2)  # (n, D) central-difference steps
    rows = np.concatenate(
        [P[:, None, :] + h[:, :, None] * np.eye(D), P[:, None, :] - h[:, :, None] * np.eye(D)], axis=1
    )  # (n, 2D, D)
    out = model.batch_image_to_robot(np.vstack([P, rows.reshape(-1, D)]), uv, z)
    F = out[n:].reshape(n, 2 * D, len(uv), 3)
    J = (F[:, :D] - F[:, D:]) / (2 * h)[:, :, None, None]  # (n, D, N, 3)
    return out[:n], J.transpose(0, 2, 3, 1)


def height_notes(fitted: Model, pairs: PointPairs, *, auto: bool) -> list[str]:
    """What the one-height rule found, for the CLI's notes and the report: the plane a single-height
    model maps on (its tilt, RMS and tolerance when the pairs' z is not exactly constant), or why
    ``auto`` took a model of several heights."""
    plane = fit_height_plane(pairs.xyz_mm)
    if fitted.height_rule is HeightRule.PLANE:
        if plane.rms_mm == 0.0 and not plane.tilted:  # z exactly constant: the note as it always was
            return [f"single-height model: x, y are mapped on the plane z = {fitted.plane_z_mm:g} mm"]
        return [
            f"single-height model: x, y are mapped on the pairs' least-squares plane {plane.describe()}; "
            "z is that plane's at the mapped x, y"
        ]
    if auto and fitted.needs_heights():
        return [
            f"auto: the pairs are not one height ({plane.why_not_one()}), so a model of several heights "
            f"was chosen ({ONE_HEIGHT_RULE})"
        ]
    return []


def _held_out_plane_z(model: Model, z: np.ndarray) -> np.ndarray:
    """z residuals of the held-out pairs as the refits give them: a single-height model's plane is
    the mean of its training heights (0 for models that take z as given)."""
    if model.height_rule is not HeightRule.PLANE:
        return np.zeros(len(z))
    n = len(z)
    return (z.sum() - z) / (n - 1) - z


def _loo_warm(cls: type[Model], solver: Solver, objective: Objective) -> bool:
    if not objective.least_squares or not cls.loo_warm_start:
        return False
    return solver.is_least_squares or (solver.is_linear and cls.linear_in_params)


def cross_validate(
    pairs: PointPairs,
    model: str | type[Model],
    optimizer: str | Solver = "lm",
    objective: str | Objective = "l2",
    *,
    image_size=None,
    seed=0,
    full: Model | None = None,
    refit: bool = False,
):
    """Held-out residuals (N, 3) mm: leave-one-out up to 40 pairs, else 10 seeded folds.
    Leave-one-out takes Gauss–Newton from the full fit where it can (:func:`loo_gauss_newton`;
    ``full``: that fit, when the caller has it), unless ``refit``. A held-out pair that its fit maps
    to no finite point is refused by id (:class:`DegenerateError`): no score can be made of it.
    ``model``, ``optimizer``, ``objective``: names, or the resolved objects."""
    cls, solver, obj = _model_class(model), get_solver(optimizer), get_objective(objective)
    res = _held_out(pairs, cls, solver, obj, image_size, seed, full, refit)
    lost = ~np.isfinite(res).all(axis=1)
    if lost.any():
        i = int(np.argmax(lost))
        raise DegenerateError(
            f"model '{cls.name}': the fit without pair {pairs.ids[i]} maps it to no finite point (beyond "
            f"that fit's lens fold or horizon; {int(lost.sum())} of {len(res)} held-out pairs): it cannot be "
            "cross-validated on these pairs"
        )
    return res


def _held_out(
    pairs: PointPairs,
    cls: type[Model],
    solver: Solver,
    objective: Objective,
    image_size,
    seed,
    full: Model | None,
    refit: bool,
) -> np.ndarray:
    n = len(pairs)
    if not refit and n <= LOO_MAX_PAIRS and n - 1 >= cls.min_pairs and _loo_warm(cls, solver, objective):
        try:
            base = (
                full
                if full is not None
                else fit_model(pairs, cls, solver, objective, image_size=image_size, seed=seed)[0]
            )
            fast = loo_gauss_newton(base, pairs.uv_px, pairs.xyz_mm)
        except InputError:
            fast = None
        if fast is not None:
            return fast
    if not refit and n <= LOO_MAX_PAIRS and objective.least_squares and solver.is_least_squares:
        try:  # a model's own warm-started refits (Model.leave_one_out; None: it has none)
            fast = cls.leave_one_out(pairs.uv_px, pairs.xyz_mm, image_size=image_size)
        except InputError:
            fast = None
        if fast is not None:
            return fast
    res = np.full((n, 3), np.nan)
    for held in folds_for(n, seed):
        keep = np.setdiff1d(np.arange(n), held)
        m, _ = fit_model(pairs.subset(keep), cls, solver, objective, image_size=image_size, seed=seed)
        test = pairs.subset(held)
        res[held] = m.residuals(test.uv_px, test.xyz_mm)
    return res


def candidate_models(pairs: PointPairs) -> list[type[Model]]:
    """Models ``auto`` may choose for the pairs' geometry (one height or several, by the one-height
    rule: :func:`eyetohand.geometry.fit_height_plane`), simplest first."""
    multi = not fit_height_plane(pairs.xyz_mm).one_height
    cands = [c for c in MODELS.values() if c.auto_candidate and c.needs_heights() == multi]
    return sorted(cands, key=lambda c: c.n_unknowns())


def held_out_score(residuals_mm: np.ndarray, objective: str | Objective, delta_mm: float) -> float:
    """A held-out residual set scored on the objective, per pair: RMS (l2), max (linf), Huber loss
    (:meth:`~eyetohand.solve.Objective.held_out_score`)."""
    return get_objective(objective).held_out_score(residuals_mm, delta_mm)


@dataclass(frozen=True)
class Candidate:
    """One model ``auto`` weighed: its held-out errors (mm) when the pairs could score it, else ``why``
    not. :meth:`to_dict` is its row of the selection report (the calibration file's JSON)."""

    model: str
    unknowns: int
    cv_rms_mm: float | None = None
    cv_max_mm: float | None = None
    cv_score_mm: float | None = None  # held-out score on the objective (held_out_score)
    why: str | None = None  # why it was not considered
    dof: int | None = None  # the full fit's residual degrees of freedom (coordinates − numbers fitted)
    # the full fit's robot-space residuals (n, coordinates): the F-test's sum of squares, the
    # non-nested test's per-pair likelihoods; in the report as their sum of squares only
    fit_residuals_mm: np.ndarray | None = field(default=None, compare=False, repr=False)
    nests: tuple[str, ...] = field(default=(), compare=False, repr=False)  # its class's Model.nests

    @property
    def rss_mm2(self) -> float | None:
        """The full fit's robot-space residual sum of squares."""
        r = self.fit_residuals_mm
        return None if r is None else float((r * r).sum())

    @property
    def considered(self) -> bool:
        return self.why is None

    @property
    def score(self) -> float:
        """The held-out score; +inf for a candidate not considered."""
        return np.inf if self.cv_score_mm is None else self.cv_score_mm

    @property
    def scored(self) -> bool:
        """Considered, with a finite score to compare."""
        return bool(np.isfinite(self.score))

    def to_dict(self) -> dict[str, Any]:
        head: dict[str, Any] = {"model": self.model, "unknowns": self.unknowns}
        if not self.considered:
            return {**head, "cv_rms_mm": None, "considered": False, "why": self.why}
        return {
            **head,
            "cv_rms_mm": self.cv_rms_mm,
            "cv_max_mm": self.cv_max_mm,
            "cv_score_mm": self.cv_score_mm,
            "rss_mm2": self.rss_mm2,
            "dof": self.dof,
            "considered": True,
        }


def nested_f_test(simple: Candidate, rich: Candidate) -> float | None:
    """p-value of "the richer fit's extra numbers are zero": the F statistic of the two full fits'
    residual sums of squares, ((RSS₀ − RSS₁)/(dof₀ − dof₁)) / (RSS₁/dof₁); None when the richer fit
    fits no more numbers (the test does not apply) or has no residual degrees of freedom."""
    if None in (simple.rss_mm2, rich.rss_mm2, simple.dof, rich.dof):
        return None
    assert simple.rss_mm2 is not None and rich.rss_mm2 is not None
    assert simple.dof is not None and rich.dof is not None
    extra = simple.dof - rich.dof
    if extra <= 0 or rich.dof <= 0:
        return None
    if rich.rss_mm2 <= 0:
        return 0.0 if simple.rss_mm2 > 0 else 1.0
    from scipy import stats  # lazily: SciPy costs ~0.4 s of start-up

    f = max(simple.rss_mm2 - rich.rss_mm2, 0.0) / extra / (rich.rss_mm2 / rich.dof)
    return float(stats.f.sf(f, extra, rich.dof))


def non_nested_test(simple: Candidate, rich: Candidate) -> float | None:
    """p-value of "the richer fit is no closer to the truth" for two models neither of which is the
    other with numbers held (dlt3d, with its skew, and the camera, with its lens): Vuong's test
    (Econometrica 57, 1989, section 5) on the two full fits' Gaussian log-likelihoods per pair, each
    with its own maximum-likelihood variance, their ratio penalised by Schwarz's
    ``(extra numbers)/2 · ln n``; the statistic is standard normal under the hypothesis. None when the
    richer fit fits no more numbers, both fits are exact, or the two fits' per-pair likelihoods do not
    differ (the same map: the test does not apply); 0 when only the richer fit is exact."""
    r0, r1 = simple.fit_residuals_mm, rich.fit_residuals_mm
    if r0 is None or r1 is None or simple.dof is None or rich.dof is None or r0.shape != r1.shape:
        return None
    extra = simple.dof - rich.dof
    n, coords = r0.shape
    if extra <= 0 or n < 2:
        return None
    q0, q1 = (r0 * r0).sum(axis=1), (r1 * r1).sum(axis=1)
    v0, v1 = q0.sum() / (n * coords), q1.sum() / (n * coords)  # maximum-likelihood variances
    if v1 == 0.0 and v0 > 0.0:  # the richer fit exact, the simpler not (as nested_f_test)
        return 0.0
    if not (v0 > 0 and v1 > 0):
        return None
    d = 0.5 * coords * math.log(v0 / v1) + 0.5 * (q0 / v0 - q1 / v1)  # per-pair log-likelihood ratio
    omega = float(d.std())
    if not omega > 1e-12 * max(1.0, float(np.abs(d).max())):
        return None
    z = (float(d.sum()) - 0.5 * extra * math.log(n)) / (math.sqrt(n) * omega)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


@dataclass(frozen=True)
class Selection:
    """What ``auto`` chose and why: ``report`` is the JSON-able record kept in the calibration;
    ``residuals_mm`` the chosen model's held-out residuals (reused as its leave-one-out)."""

    model: type[Model]
    report: dict
    residuals_mm: np.ndarray | None
    optimizer: Solver


def select_model(
    pairs: PointPairs,
    *,
    optimizer: str | Solver = "lm",
    objective: str | Objective = "l2",
    image_size=None,
    seed=0,
) -> tuple[str, dict]:
    """Choose a model by cross-validated score on ``objective``; returns ``(name, report)``."""
    sel = _select(pairs, get_solver(optimizer), get_objective(objective), image_size=image_size, seed=seed)
    return sel.model.name, sel.report


def _nested_choice(scored: list[Candidate], what: str) -> tuple[Candidate, str]:
    """The simplest scored candidate, replaced in turn by each one with more fitted numbers that is
    significantly better at ``AUTO_ALPHA`` (:func:`nested_f_test` against a model it nests,
    :func:`non_nested_test` against any other) and scores lower held out too; the reason names the
    test that took the chosen one and each later candidate's that did not pay."""
    chosen = scored[0]
    reason = f"the simplest model that could be scored ({what} {chosen.score:.4f} mm)"
    declined: list[str] = []
    for rich in scored[1:]:
        nested = chosen.model in rich.nests
        p = nested_f_test(chosen, rich) if nested else non_nested_test(chosen, rich)
        test = "F-test" if nested else "non-nested (Vuong) test"
        if p is None:  # not more numbers, or the same map: the held-out score alone decides
            if rich.score < chosen.score:
                chosen, reason = rich, f"lower {what} ({rich.score:.4f} mm), no more numbers fitted"
                declined = []
            continue
        if p < AUTO_ALPHA and rich.score < chosen.score:
            reason = (
                f"its extra terms pay: {test} against '{chosen.model}' p = {p:.2g} < {AUTO_ALPHA:g}, "
                f"{what} {rich.score:.4f} vs {chosen.score:.4f} mm"
            )
            chosen, declined = rich, []
        else:
            why = f"{test} p = {p:.2g}" if p >= AUTO_ALPHA else f"{what} {rich.score:.4f} mm is not lower"
            declined.append(f"'{rich.model}' does not pay ({why})")
    return chosen, "; ".join([reason, *declined])


def _select(pairs: PointPairs, solver: Solver, objective: Objective, *, image_size=None, seed=0) -> Selection:
    n = len(pairs)
    cv_opt = solver.for_cross_validation(objective)
    cands: list[Candidate] = []
    classes: dict[str, type[Model]] = {}
    held: dict[str, np.ndarray] = {}
    delta = None
    for cls in candidate_models(pairs):
        k = cls.n_unknowns()
        classes[cls.name] = cls
        if 2 * n < k + SPARE_EQUATIONS:
            need = -(-(k + SPARE_EQUATIONS) // 2)
            cands.append(Candidate(cls.name, k, why=f"needs at least {need} pairs, have {n}"))
            continue
        why = cls.unobservable(pairs.uv_px, pairs.xyz_mm, image_size=image_size)
        if why is not None:  # enough pairs, but not the geometry its numbers need (a camera's depth)
            cands.append(Candidate(cls.name, k, why=why))
            continue
        try:
            full, _ = fit_model(pairs, cls, cv_opt, objective, image_size=image_size, seed=seed)
            res = cross_validate(pairs, cls, cv_opt, objective, image_size=image_size, seed=seed, full=full)
            fit_noise = Uncertainty.of_fit(full, pairs.uv_px, pairs.xyz_mm)
        except InputError as exc:
            cands.append(Candidate(cls.name, k, why=str(exc)))
            continue
        e = np.linalg.norm(res, axis=1)
        if delta is None:  # one Huber threshold for every candidate, from the simplest's errors
            delta = huber_delta_mm(e[np.isfinite(e)]) if np.isfinite(e).any() else 1.0
        score = objective.held_out_score(res, delta)
        cv_rms = float(np.sqrt(np.mean(e**2)))
        with np.errstate(all="ignore"):
            fit_res = full.residuals(pairs.uv_px, pairs.xyz_mm)[:, : fit_noise.n_coords]
        cands.append(
            Candidate(cls.name, k, cv_rms, float(e.max()), score, None, fit_noise.dof, fit_res, cls.nests)
        )
        held[cls.name] = res
    rows = [c.to_dict() for c in cands]
    scored = [c for c in cands if c.scored]
    method = "leave-one-out" if n <= LOO_MAX_PAIRS else "10-fold"
    if not scored:
        fallback = next((c for c in candidate_models(pairs) if n >= c.min_pairs), None)
        if fallback is None:
            kind = "one height" if fit_height_plane(pairs.xyz_mm).one_height else "several heights"
            raise InputError(f"{pairs.source}: too few pairs ({n}) for any model of pairs at {kind}")
        reason = (
            f"too few pairs ({n}) to cross-validate any model; took '{fallback.name}', "
            "the one with the fewest unknowns"
        )
        report: dict[str, Any] = {"chosen": fallback.name, "reason": reason, "candidates": rows}
        return Selection(fallback, report, None, cv_opt)
    chosen, reason = _nested_choice(scored, objective.held_out_what)
    report = {
        "chosen": chosen.model,
        "reason": reason,
        "method": method,
        "objective": objective.name,
        "scored_with": cv_opt.name,
        "candidates": rows,
    }
    return Selection(classes[chosen.model], report, held[chosen.model], cv_opt)


def tcp_offset_for(
    pairs: PointPairs, model: str | ModelChoice = "auto", *, image_size=None, seed=0
) -> TcpOffset:
    """The tool-centre offset of pairs with turns, estimated with ``model`` (a name, a model class or
    :data:`~eyetohand.calibration.request.AUTO`; "auto": chosen by cross-validation on the pairs at
    the most common angle, as :func:`calibrate` does)."""
    choice = resolve_model(model) if isinstance(model, str) else model
    cls: type[Model] | None = None
    if not isinstance(choice, AutoModel):
        cls = choice
    elif has_turns(pairs):  # (pairs without turns are refused below, before any fit)
        ref = reference_pairs(pairs)
        cls = _select(ref, TCP_CHOICE_SOLVER, TCP_OBJECTIVE, image_size=image_size, seed=seed).model

    def fit_linear(p: PointPairs) -> Model:
        assert cls is not None  # estimate_tcp_offset fits only pairs with turns
        return fit_model(p, cls, TCP_SOLVER, TCP_OBJECTIVE, image_size=image_size)[0]

    return estimate_tcp_offset(pairs, fit_linear)  # refuses pairs without turns, saying what they lack


def calibrate(
    pairs: PointPairs,
    model: str = "auto",
    optimizer: str = "lm",
    objective: str = "l2",
    *,
    check: PointPairs | None = None,
    image_size: tuple[int, int] | None = None,
    seed=None,
    callback=None,
    loo: bool = True,
    **solver_options,
) -> Calibration:
    """Fit a calibration: ``model`` (a name or "auto") refined by ``optimizer`` on ``objective``.

    The names and options are resolved and checked once (:meth:`FitRequest.from_names`), then fitted
    as :func:`calibrate_request` fits a request.

    Pairs with an ``angle`` column whose angles differ ("9 + 2") first give the tool-centre offset
    (:mod:`eyetohand.solve.tcp_offset`); the pairs are moved to their tool points and the offset is kept in
    ``Calibration.tcp_offset``.

    ``check``: pairs not used for fitting, to measure accuracy. ``loo``: also report leave-one-out
    errors on the training pairs (refit without each pair; for the PSO solvers the leave-one-out
    refits use ``lm`` — or ``linear`` for a non-smooth objective — to keep it fast, and say so).
    """
    if set(solver_options) - set(FitRequest.SOLVER_OPTIONS):
        check_fit(optimizer, objective, solver_options)  # refuses the unknown option, in its order and words
    request = FitRequest.from_names(
        model,
        optimizer,
        objective,
        seed=seed,
        image_size=image_size,
        loo=loo,
        **solver_options,
    )
    return _fit(request, pairs, check, callback, loo=loo)


def calibrate_request(
    request: FitRequest, pairs: PointPairs, *, check: PointPairs | None = None, callback=None
) -> Calibration:
    """The calibration of ``pairs`` as ``request`` says; ``check``: pairs not used for fitting;
    ``callback(iteration, best, x)`` after each of a swarm's iterations (a true return stops it).
    With ``request.target_diameter_mm``: fit, correct the centres with the fit's maps, refit, twice
    (the intermediate fits without leave-one-out); the file records the diameter."""

    def fit(train: PointPairs, held: PointPairs | None, last: bool = True) -> Calibration:
        return _fit(request, train, held, callback, loo=request.loo and last)

    if request.target_diameter_mm is None:
        return fit(pairs, check)
    return fit_corrected(fit, pairs, check, request.target_diameter_mm)


def _fit(
    request: FitRequest, pairs: PointPairs, check: PointPairs | None, callback, *, loo: bool
) -> Calibration:
    """The one fit of a resolved request: the model chosen (once, for :data:`AUTO`), fitted, scored."""
    solver, objective, image_size, seed = request.solver, request.objective, request.image_size, request.seed
    cv_seed = 0 if seed is None else seed
    data_sha = pairs.sha256()
    original, original_check = pairs, check
    tcp = None
    if has_turns(pairs):  # "9 + 2": pairs at other tool angles reveal the tool-centre offset
        tcp = tcp_offset_for(pairs, request.model, image_size=image_size, seed=cv_seed)
        pairs = correct_pairs(pairs, tcp.offset_mm)
        if check is not None and check.angle_deg is not None:
            check = correct_pairs(check, tcp.offset_mm)
    selection = None
    if isinstance(request.model, AutoModel):
        selection = _select(pairs, solver, objective, image_size=image_size, seed=cv_seed)
        cls = selection.model
    else:
        cls = request.model
    fitted, info = fit_model(
        pairs,
        cls,
        solver,
        objective,
        image_size=image_size,
        seed=seed,
        callback=callback,
        **request.solver_options,
    )
    notes = list(pairs.notes)
    if fitted.init_note is not None:
        notes.append(f"{cls.name}: {fitted.init_note}")
    notes.extend(height_notes(fitted, pairs, auto=selection is not None))
    lev = pair_leverage(fitted, pairs.uv_px, pairs.xyz_mm)
    train = stats_from_residuals(fitted.residuals(pairs.uv_px, pairs.xyz_mm), pairs.ids, leverage=lev)
    loo_stats = None
    if loo and len(pairs) > fitted.min_pairs:
        loo_opt = solver.for_cross_validation(objective)
        try:
            reused = (
                selection.residuals_mm if selection is not None and selection.optimizer is loo_opt else None
            )
            if reused is not None:
                res = reused
            else:
                full = fitted if loo_opt is solver else None
                res = cross_validate(
                    pairs, cls, loo_opt, objective, image_size=image_size, seed=cv_seed, full=full
                )
            loo_stats = stats_from_residuals(res, pairs.ids, leverage=lev, held_out=True)
            if loo_opt is not solver:
                notes.append(f"leave-one-out refits used optimizer '{loo_opt.name}'")
        except InputError as exc:
            notes.append(f"leave-one-out skipped: {exc}")
    check_stats = None
    if check is not None:
        check_res = mapped_residuals(fitted, check, "check pair")
        check_stats = stats_from_residuals(check_res, check.ids)
    region = derived_region(fitted, pairs)  # the one rule, which loading re-checks
    uncertainty = Uncertainty.of_fit(fitted, pairs.uv_px, pairs.xyz_mm)
    cal = Calibration(
        model=fitted,
        fit=info,
        train=train,
        check=check_stats,
        loo=loo_stats,
        data_sha256=data_sha,
        image_size=image_size,
        notes=tuple(notes),
        selection=None if selection is None else selection.report,
        tcp_offset=tcp,
        region=region,
        uncertainty=uncertainty,
        pairs=original,
        check_pairs=original_check,
    )
    return replace(cal, warnings=tuple(sanity_warnings(cal)))


SCALE_RANGE_MM_PER_PX = (0.001, 10.0)


def sanity_warnings(cal: Calibration) -> list[str]:
    """What no real cell produces: a scale outside 0.001..10 mm per pixel (suspect units) at the
    calibrated region's centre, a check set whose errors a mixed-up convention explains, and a check set
    that repeats training pairs (it then measures nothing)."""
    out = []
    pairs, check = cal.pairs, cal.check_pairs
    assert pairs is not None  # calibrate records the pairs it was given
    scale = cal.local_frame().scale_mm_per_px
    lo, hi = SCALE_RANGE_MM_PER_PX
    if not lo <= scale <= hi:
        guess = "metres (use --robot-units m)" if scale < lo else "micrometres or the wrong columns"
        out.append(
            f"{pairs.source}: the scale is {scale:.3g} mm per pixel, outside the {lo:g}..{hi:g} mm/px "
            f"of any real cell: are the robot coordinates in {guess}? They are read as millimetres"
        )
    if check is not None:
        out.extend(check_warnings(cal))  # a mixed-up convention (u <-> v, x <-> y, a sign, metres), named
        train_uv = {tuple(r) for r in np.round(pairs.uv_px, 6)}
        train_xyz = {tuple(r) for r in np.round(pairs.xyz_mm, 6)}
        same = [
            cid
            for cid, uv, xyz in zip(
                check.ids, np.round(check.uv_px, 6), np.round(check.xyz_mm, 6), strict=True
            )
            if tuple(uv) in train_uv or tuple(xyz) in train_xyz
        ]
        if len(same) == len(check):
            out.append(f"{check.source}: the check pairs are the training pairs: the check measures nothing")
        elif same:
            shown = ", ".join(same[:8]) + (" …" if len(same) > 8 else "")
            out.append(
                f"{check.source}: {len(same)} check pair(s) repeat training pairs (ids {shown}): "
                "those say nothing about accuracy"
            )
    return out
