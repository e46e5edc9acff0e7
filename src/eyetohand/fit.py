"""calibrate(): point pairs × model × solver → Calibration, with automatic model choice.

``model="auto"`` scores every candidate the pairs can support by cross-validation (leave-one-out up
to 40 pairs, else 10 folds) and keeps the simplest whose held-out RMS is within 2 % of the best.
A candidate is considered only when the pairs give at least 8 more equations than it has unknowns
(2n ≥ unknowns + 8), so that its held-out score means something; the report says why each
candidate was or was not taken.
"""

from __future__ import annotations

import numpy as np

from .calibration import Calibration
from .errors import InputError
from .evaluate import stats_from_residuals
from .models import MODELS, Model, get_model
from .objectives import SMOOTH_OBJECTIVES
from .pairs import PointPairs
from .solvers import check_optimizer, refine
from .tcp_offset import correct_pairs, estimate_tcp_offset, has_turns

AUTO_TOLERANCE = 0.02
SPARE_EQUATIONS = 8
LOO_MAX_PAIRS = 40


def fit_model(
    pairs: PointPairs,
    model: str,
    optimizer: str = "lm",
    objective: str = "l2",
    *,
    image_size=None,
    seed=None,
    callback=None,
    **solver_options,
):
    """Estimate ``model`` on ``pairs`` and refine it: returns ``(Model, FitInfo)``."""
    cls = get_model(model)
    try:
        base = cls.from_pairs(pairs.uv_px, pairs.xyz_mm, image_size=image_size)
    except InputError as exc:
        raise type(exc)(f"{pairs.source}: {exc}") from None
    return refine(
        base, pairs.uv_px, pairs.xyz_mm, optimizer=optimizer, objective=objective, seed=seed,
        callback=callback, **solver_options,
    )


def cross_validate(
    pairs: PointPairs, model: str, optimizer: str = "lm", objective: str = "l2", *,
    image_size=None, seed=0,
):
    """Held-out residuals (N, 3) mm: leave-one-out up to 40 pairs, else 10 seeded folds."""
    n = len(pairs)
    if n <= LOO_MAX_PAIRS:
        folds = [np.array([i]) for i in range(n)]
    else:
        perm = np.random.default_rng(seed).permutation(n)
        folds = np.array_split(perm, 10)
    res = np.full((n, 3), np.nan)
    for held in folds:
        keep = np.setdiff1d(np.arange(n), held)
        m, _ = fit_model(pairs.subset(keep), model, optimizer, objective,
                         image_size=image_size, seed=seed)
        test = pairs.subset(held)
        res[held] = m.residuals(test.uv_px, test.xyz_mm)
    return res


def candidate_models(pairs: PointPairs) -> list[type[Model]]:
    """Models that fit the pairs' geometry, simplest first: single-height or multi-height."""
    multi = len(pairs.z_levels_mm) > 1
    cands = [c for c in MODELS.values() if c.multi_height == multi and c.name != "paper"]
    return sorted(cands, key=lambda c: c.n_unknowns())


def select_model(pairs: PointPairs, *, image_size=None, seed=0) -> tuple[str, dict]:
    """Choose a model by cross-validated error; returns ``(name, report)``."""
    n = len(pairs)
    rows = []
    for cls in candidate_models(pairs):
        k = cls.n_unknowns()
        row = {"model": cls.name, "unknowns": k}
        if 2 * n < k + SPARE_EQUATIONS:
            need = -(-(k + SPARE_EQUATIONS) // 2)
            row.update(cv_rms_mm=None, considered=False, why=f"needs at least {need} pairs, have {n}")
        else:
            try:
                res = cross_validate(pairs, cls.name, image_size=image_size, seed=seed)
                e = np.linalg.norm(res, axis=1)
                row.update(cv_rms_mm=float(np.sqrt(np.mean(e**2))), cv_max_mm=float(e.max()),
                           considered=True)
            except InputError as exc:
                row.update(cv_rms_mm=None, considered=False, why=str(exc))
        rows.append(row)
    scored = [r for r in rows if r.get("cv_rms_mm") is not None and np.isfinite(r["cv_rms_mm"])]
    if not scored:
        fallback = next((c for c in candidate_models(pairs) if n >= c.min_pairs), None)
        if fallback is None:
            kind = "several heights" if len(pairs.z_levels_mm) > 1 else "one height"
            raise InputError(f"{pairs.source}: too few pairs ({n}) for any model of pairs at {kind}")
        reason = (f"too few pairs ({n}) to cross-validate any model; took '{fallback.name}', "
                  "the one with the fewest unknowns")
        return fallback.name, {"chosen": fallback.name, "reason": reason, "candidates": rows}
    best = min(r["cv_rms_mm"] for r in scored)
    chosen = next(r for r in scored if r["cv_rms_mm"] <= best * (1 + AUTO_TOLERANCE))
    if chosen["cv_rms_mm"] == best:
        reason = f"lowest held-out RMS ({best:.4f} mm)"
    else:
        reason = (f"simplest model within {AUTO_TOLERANCE:.0%} of the lowest held-out RMS "
                  f"({chosen['cv_rms_mm']:.4f} vs {best:.4f} mm)")
    method = "leave-one-out" if n <= LOO_MAX_PAIRS else "10-fold"
    return chosen["model"], {"chosen": chosen["model"], "reason": reason, "method": method,
                             "candidates": rows}


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

    Pairs with an ``angle`` column whose angles differ ("9 + 2") first give the tool-centre offset
    (:mod:`eyetohand.tcp_offset`); the pairs are moved to their tool points and the offset is kept in
    ``Calibration.tcp_offset``.

    ``check``: pairs not used for fitting, to measure accuracy. ``loo``: also report leave-one-out
    errors on the training pairs (refit without each pair; for the PSO solvers the leave-one-out
    refits use ``lm`` — or ``linear`` for a non-smooth objective — to keep it fast, and say so).
    """
    check_optimizer(optimizer, objective)
    if model != "auto":
        get_model(model)
    if image_size is not None:
        w, h = image_size
        if not (int(w) > 0 and int(h) > 0):
            raise InputError(f"image size must be two positive integers W x H, got {image_size!r}")
        image_size = (int(w), int(h))
    data_sha = pairs.sha256()
    tcp = None
    if has_turns(pairs):  # "9 + 2": pairs at other tool angles reveal the tool-centre offset
        tcp = estimate_tcp_offset(pairs, model, image_size=image_size, seed=0 if seed is None else seed)
        pairs = correct_pairs(pairs, tcp.offset_mm)
        if check is not None and check.angle_deg is not None:
            check = correct_pairs(check, tcp.offset_mm)
    selection = None
    if model == "auto":
        model, selection = select_model(pairs, image_size=image_size, seed=0 if seed is None else seed)
    fitted, info = fit_model(pairs, model, optimizer, objective, image_size=image_size, seed=seed,
                             callback=callback, **solver_options)
    notes = list(pairs.notes)
    if "init" in fitted.meta:
        notes.append(f"{model}: {fitted.meta['init']}")
    if not fitted.uses_z and model != "paper":
        notes.append(
            f"single-height model: x, y are mapped on the plane z = {fitted.meta['plane_z_mm']:g} mm"
        )
    train = stats_from_residuals(fitted.residuals(pairs.uv_px, pairs.xyz_mm), pairs.ids)
    loo_stats = None
    if loo and len(pairs) > fitted.min_pairs:
        loo_opt = optimizer if optimizer in ("linear", "lm") else (
            "lm" if objective in SMOOTH_OBJECTIVES else "linear")
        try:
            res = cross_validate(pairs, model, loo_opt, objective, image_size=image_size,
                                 seed=0 if seed is None else seed)
            loo_stats = stats_from_residuals(res, pairs.ids)
            if loo_opt != optimizer:
                notes.append(f"leave-one-out refits used optimizer '{loo_opt}'")
        except InputError as exc:
            notes.append(f"leave-one-out skipped: {exc}")
    check_stats = None
    if check is not None:
        check_stats = stats_from_residuals(fitted.residuals(check.uv_px, check.xyz_mm), check.ids)
    return Calibration(
        model=fitted,
        fit=info,
        train=train,
        check=check_stats,
        loo=loo_stats,
        data_sha256=data_sha,
        image_size=image_size,
        notes=tuple(notes),
        selection=selection,
        tcp_offset=tcp,
    )
