"""Monte Carlo planner: how accurate will a calibration plan be in this cell, before you run it?

For each plan, ``runs`` independent sessions are simulated (fresh robot and detection noise each,
see :mod:`eyetohand.sim.simulate`), calibrated as ``eyetohand calibrate`` would (default model
``auto``: chosen by cross-validation on the first run, then kept for the others so that the runs
differ by noise only), and scored on noise-free check points. The prediction is the median over runs
of the check RMS and of the check max; the 90th percentiles say how unlucky a session can be.

The recommended plan is the one with the fewest pairs whose predicted error (max by default, or RMS)
meets the target.
"""

from __future__ import annotations

import numpy as np

from eyetohand.calibration import calibrate
from eyetohand.cell import MAX_POINTS, is_whole_in, parse_plan
from eyetohand.core import InputError
from eyetohand.sim.cell import Cell
from eyetohand.sim.simulate import simulate
from eyetohand.solve import check_seed

DEFAULT_PLANS = ("grid:3x3", "grid:4x4", "grid:5x5", "radial:17", "random:25", "grid:7x7")
METRICS = ("max", "rms")


MAX_RUNS = 10_000
"""Most simulated sessions per plan (each is a calibration)."""


def predict_plan(
    cell: Cell,
    plan: str,
    heights_mm=(150.0,),
    *,
    runs: int = 20,
    n_check: int = 30,
    check_heights_mm=None,
    model: str = "auto",
    optimizer: str = "lm",
    seed: int = 0,
) -> dict:
    """Predicted check RMS and max (mm) of ``plan`` at ``heights_mm`` over ``runs`` simulated sessions."""
    if not is_whole_in(runs, 1, MAX_RUNS):
        raise InputError(f"runs: expected a whole number from 1 to {MAX_RUNS}, got {runs!r}")
    if not is_whole_in(n_check, 1, MAX_POINTS):
        raise InputError(
            f"check points: expected a whole number from 1 to {MAX_POINTS} per height (the prediction is "
            f"the check error), got {n_check!r}"
        )
    seed = check_seed(seed)
    p = parse_plan(plan)
    seeds = np.random.SeedSequence(seed).generate_state(runs)
    rms_runs: list[float] = []
    max_runs: list[float] = []
    chosen = model
    n_pairs = None
    for i, s in enumerate(seeds):
        sim = simulate(cell, p, heights_mm, n_check=n_check, check_heights_mm=check_heights_mm, seed=int(s))
        n_pairs = len(sim.pairs)
        try:
            cal = calibrate(
                sim.pairs,
                model=chosen,
                optimizer=optimizer,
                check=sim.check,
                image_size=cell.image_size,
                seed=int(s),
                loo=False,
            )
        except InputError as exc:
            return {
                "plan": p.label,
                "heights": [float(h) for h in np.atleast_1d(heights_mm)],
                "n_pairs": n_pairs,
                "error": str(exc),
                "predicted_rms_mm": None,
                "predicted_max_mm": None,
            }
        if i == 0:
            chosen = cal.model_name
        assert cal.check is not None  # n_check >= 1
        rms_runs.append(cal.check.rms_mm)
        max_runs.append(cal.check.max_mm)
    rms, mx = np.array(rms_runs), np.array(max_runs)
    return {
        "plan": p.label,
        "heights": [float(h) for h in np.atleast_1d(heights_mm)],
        "n_pairs": n_pairs,
        "model": chosen,
        "runs": int(runs),
        "predicted_rms_mm": float(np.median(rms)),
        "predicted_max_mm": float(np.median(mx)),
        "rms_p90_mm": float(np.percentile(rms, 90)),
        "max_p90_mm": float(np.percentile(mx, 90)),
        "rms_runs_mm": [float(v) for v in rms],
    }


def plan_study(
    cell: Cell,
    plans=DEFAULT_PLANS,
    heights_mm=(150.0,),
    *,
    target_error_mm: float | None = None,
    metric: str = "max",
    runs: int = 20,
    n_check: int = 30,
    check_heights_mm=None,
    model: str = "auto",
    seed: int = 0,
) -> dict:
    """Predictions for every plan and the smallest plan that meets ``target_error_mm``."""
    if metric not in METRICS:
        raise InputError(f"target metric {metric!r}: choose one of {', '.join(METRICS)}")
    if target_error_mm is not None and not (np.isfinite(target_error_mm) and target_error_mm > 0):
        raise InputError(f"target error: expected a positive number of mm, got {target_error_mm!r}")
    labels = [parse_plan(p).label for p in plans]  # validate all before the long part
    if not labels:
        raise InputError("plan: give at least one plan")
    rows = [
        predict_plan(
            cell,
            p,
            heights_mm,
            runs=runs,
            n_check=n_check,
            check_heights_mm=check_heights_mm,
            model=model,
            seed=seed,
        )
        for p in labels
    ]
    key = f"predicted_{metric}_mm"
    recommended = None
    if target_error_mm is not None:
        for r in rows:
            r["meets_target"] = r.get(key) is not None and r[key] <= target_error_mm
        ok = [r for r in rows if r["meets_target"]]
        if ok:
            best = min(ok, key=lambda r: (r["n_pairs"], r[key]))
            recommended = best["plan"]
    return {
        "plans": rows,
        "recommended": recommended,
        "target_error_mm": target_error_mm,
        "target_metric": metric,
        "runs": int(runs),
        "check_points_per_height": int(n_check),
    }


def plot_study(study: dict, path) -> None:
    """Bar chart of predicted RMS and max per plan (fewest pairs first), the target as a line (PNG):
    :func:`eyetohand.reports.plots.plot_plan_study`, same size and palette as the report's plots."""
    import io

    from eyetohand.core import atomic_write_bytes
    from eyetohand.reports import plot_plan_study

    ax = plot_plan_study(study)
    buf = io.BytesIO()
    ax.figure.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())
