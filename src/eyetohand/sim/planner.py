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


# ---------------------------------------------------------------- the rectangle from what the camera sees

VIEW_MARGIN = 0.08
"""Default fraction of the image kept clear at each edge by ``plan --from-view`` (the cell's plan margin)."""


def _rough_map(uv: np.ndarray, xy: np.ndarray):
    """Pixel → robot (x, y) mm from 3 jogged pairs (affine, exact) or 4 and more (a homography, least
    squares): no lens, no refinement — a day-one map for choosing where to collect, not for picking."""
    if len(uv) == 3:
        A = np.column_stack([uv, np.ones(3)])
        if abs(np.linalg.det(A)) < 1e-6 * max(1.0, float(np.ptp(uv)) ** 2):
            raise InputError(
                "corners: the 3 pixels are on one line; jog the target to 3 corners of the image"
            )
        M = np.linalg.solve(A, xy)  # (3, 2)
        return lambda q: np.column_stack([q, np.ones(len(q))]) @ M
    import cv2

    H, _ = cv2.findHomography(uv.astype(np.float64), xy.astype(np.float64), 0)
    if H is None or not np.all(np.isfinite(H)):
        raise InputError("corners: no map from these pairs (three or more on one line?); jog to the corners")

    def apply(q):
        p = np.column_stack([q, np.ones(len(q))]) @ H.T
        return p[:, :2] / p[:, 2:3]

    return apply


def _largest_rectangle(poly: np.ndarray, step_mm: float) -> tuple[float, float, float, float]:
    """The largest axis-aligned rectangle (x0, y0, x1, y1) inside the convex polygon ``poly`` (closed
    loop of points), on a grid of ``step_mm`` in x, its edges rounded inwards to ``step_mm``."""
    xs = np.arange(np.ceil(poly[:, 0].min() / step_mm), np.floor(poly[:, 0].max() / step_mm) + 1) * step_mm
    lo = np.full(len(xs), np.inf)
    hi = np.full(len(xs), -np.inf)
    for (xa, ya), (xb, yb) in zip(poly[:-1], poly[1:], strict=True):  # the polygon's y range at each x
        if xa == xb:
            continue
        t = (xs - xa) / (xb - xa)
        ok = (t >= 0) & (t <= 1)
        y = ya + t * (yb - ya)
        lo[ok] = np.minimum(lo[ok], y[ok])
        hi[ok] = np.maximum(hi[ok], y[ok])
    best, rect = 0.0, None
    for i in range(len(xs)):
        top = np.maximum.accumulate(lo[i:])  # the rectangle's y range over [xs[i], xs[j]]
        bottom = np.minimum.accumulate(hi[i:])
        y0 = np.ceil(top / step_mm) * step_mm
        y1 = np.floor(bottom / step_mm) * step_mm
        area = (xs[i:] - xs[i]) * np.maximum(y1 - y0, 0.0)
        area[~np.isfinite(area)] = 0.0
        j = int(np.argmax(area))
        if area[j] > best:
            best, rect = float(area[j]), (float(xs[i]), float(y0[j]), float(xs[i + j]), float(y1[j]))
    if rect is None:
        raise InputError(
            "corners: the view they describe holds no rectangle; jog closer to the image corners"
        )
    return rect


def view_rectangle(pairs, image_size, *, margin: float = VIEW_MARGIN, step_mm: float = 1.0) -> dict:
    """Where to collect, from what the camera sees, before any calibration: ``pairs`` (3 or more, from
    jogging the target near the image's corners, all at the work height) give a rough map; the image less
    ``margin`` at each edge, mapped through it, is the view at that height; the answer is the largest
    axis-aligned rectangle (robot x, y mm, rounded inwards to ``step_mm``) inside it."""
    w, h = image_size
    uv, xyz = np.asarray(pairs.uv_px, float), np.asarray(pairs.xyz_mm, float)
    if not 3 <= len(uv) <= 50:
        raise InputError(f"corners: expected 3 or 4 jogged pairs (pixel and robot), got {len(uv)}")
    if not 0 <= margin < 0.45:
        raise InputError(f"--margin: expected a fraction of the image from 0 to 0.45, got {margin!r}")
    z = xyz[:, 2]
    if np.ptp(z) > 0.5:
        raise InputError(
            f"corners: the pairs are at z = {z.min():g} to {z.max():g} mm; jog them all at the work height "
            "(the view is a different size at each height)"
        )
    outside = (uv[:, 0] < 0) | (uv[:, 0] > w - 1) | (uv[:, 1] < 0) | (uv[:, 1] > h - 1)
    if outside.any():
        raise InputError(f"corners: pair {pairs.ids[int(np.argmax(outside))]} is outside the {w}x{h} image")
    to_robot = _rough_map(uv, xyz[:, :2])
    m = margin * min(w, h)
    t = np.linspace(0.0, 1.0, 65)[:-1, None]
    c = np.array([[m, m], [w - 1 - m, m], [w - 1 - m, h - 1 - m], [m, h - 1 - m]])
    border = np.vstack([c[k] + t * (c[(k + 1) % 4] - c[k]) for k in range(4)])  # the image's edge, in order
    poly = to_robot(border)
    poly = np.vstack([poly, poly[:1]])
    x0, y0, x1, y1 = _largest_rectangle(poly, step_mm)
    reach = np.linalg.norm(to_robot(uv) - xyz[:, :2], axis=1)  # exact for 3 and for 4 good pairs
    return {
        "rect_mm": [x0, y0, x1, y1],
        "z_mm": float(np.mean(z)),
        "size_mm": [x1 - x0, y1 - y0],
        "view_mm": [[float(a), float(b)] for a, b in to_robot(c)],
        "margin": float(margin),
        "image_size": [int(w), int(h)],
        "n_pairs": len(uv),
        "map": "affine" if len(uv) == 3 else "homography",
        "pair_residual_max_mm": float(reach.max()),
    }
