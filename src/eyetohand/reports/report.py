"""The HTML report of a calibration (``eyetohand report``).

A report is a folder with ``index.html`` and the PNG plots. ``index.html`` is self-contained: inline
CSS, the plots embedded as base64, so the one file can be mailed or archived alone; the PNGs are
written beside it for reuse. Everything is computed in memory first and then written file by file
atomically, ``index.html`` last: a run that fails leaves an earlier report as it was.

The page is built with :mod:`eyetohand.reports.html`; its calibration parts (statistics, per-point
residuals, fit, parameters) are those of :mod:`eyetohand.reports.sections`, which the paper
reproduction's page (:func:`eyetohand.reports.demo.write_demo_report`) shows too.

Units everywhere: robot errors, fitness and statistics in mm, image positions in px.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eyetohand.calibration import Calibration, as_fitted
from eyetohand.core import InputError, PointPairs
from eyetohand.reports.diff_section import against_section, budget_section
from eyetohand.reports.html import Document, mm, write_folder
from eyetohand.reports.sections import (
    fit_table,
    fitness_unit,
    image_jacobian,
    params_section,
    points_table,
    selection_table,
    stats_table,
)
from eyetohand.solve import Stats, evaluate, find_objective

__all__ = ["build_report", "load_history", "trust_map", "write_report"]


def _fitness_label(objective: str) -> str:
    obj = find_objective(objective)
    return "best fitness [mm]" if obj is None else obj.fitness_label


# ------------------------------------------------------------------ one calibration


@dataclass
class _Evaluated:
    """The statistics a report shows, recomputed on the pairs it was given."""

    check: Stats | None
    train: Stats
    #: "train", or "given pairs" when the pairs given are not the ones the calibration was fitted on
    train_label: str
    train_what: str
    notes: list[str]
    warnings: list[str]

    @property
    def fitted(self) -> bool:
        """True when ``train`` is the calibration's own training residuals."""
        return self.train_label == "train"


def _evaluate(cal: Calibration, check_pairs: PointPairs | None, train_pairs: PointPairs | None) -> _Evaluated:
    notes = list(cal.notes)
    warnings: list[str] = []
    check = cal.check
    if check_pairs is not None:
        check = evaluate(cal, check_pairs)
        notes.append(f"check statistics computed on {check_pairs.source} ({len(check_pairs)} pairs)")
    train, train_label, train_what = cal.train, "train", "fit residuals on the training pairs"
    train_matches = False
    if train_pairs is not None:
        train_matches = bool(cal.data_sha256) and train_pairs.sha256() == cal.data_sha256
        if not train_matches:
            train = evaluate(cal, train_pairs)
            train_label, train_what = "given pairs", f"residuals on {train_pairs.source}"
            warnings.append(
                f"{train_pairs.source} is not the data this calibration was fitted on "
                f"(SHA-256 differs{'' if cal.data_sha256 else ': the calibration records none'}): "
                "its statistics are shown as 'given pairs', not as training residuals"
            )
    return _Evaluated(check, train, train_label, train_what, notes, warnings)


def build_report(
    calibration: Calibration,
    check_pairs: PointPairs | None = None,
    train_pairs: PointPairs | None = None,
    extra: Mapping | None = None,
    *,
    title: str | None = None,
    history: Sequence[Mapping] | None = None,
    limit_mm: float | None = None,
    against: tuple[Calibration, str] | None = None,
) -> tuple[str, dict[str, bytes]]:
    """The report of one calibration, in memory: ``(index.html text, {png name: bytes})``.

    ``check_pairs``: pairs not used for fitting; the check statistics are recomputed on them (and
    replace any stored ones). ``train_pairs``: the pairs the calibration was fitted on, for the image
    positions of the residual-vector plot; if their SHA-256 differs from the calibration's, they
    are shown as "given pairs" with a warning. ``extra``: more name → value rows for the header.
    ``history``: the calibration's checks (verification entries, CAL CHECK records: see
    :func:`eyetohand.reports.plots.plot_drift`), drawn over time in a "Drift" section against
    ``limit_mm`` (default: the tolerance they record). ``against``: an earlier calibration and its
    label, compared with this one in a section (``calibration.diff``).
    """
    cal = calibration
    if not isinstance(cal, Calibration):
        raise InputError(f"write_report needs a Calibration, got {type(cal).__name__}")
    check_pairs, train_pairs = as_fitted(cal, check_pairs), as_fitted(cal, train_pairs)  # circle centres
    ev = _evaluate(cal, check_pairs, train_pairs)
    doc = Document(title or f"Calibration report — {cal.model_name} + {cal.fit.optimizer}")
    doc.add(
        '<nav><a href="#summary">summary</a><a href="#accuracy">accuracy</a><a href="#plots">plots</a>'
        + ('<a href="#drift">drift</a>' if history is not None else "")
        + ('<a href="#against">compared</a>' if against is not None else "")
        + '<a href="#points">per point</a><a href="#fit">fit</a><a href="#params">parameters</a></nav>'
    )
    _summary(doc, cal, ev, extra)
    _accuracy(doc, cal, ev)
    budget_section(doc, cal)
    _plots(doc, cal, ev, check_pairs, train_pairs)
    if history is not None:
        _drift(doc, history, limit_mm)
    if against is not None:
        against_section(doc, cal, *against)
    doc.h2("Per point residuals", "points")
    if ev.check is not None:
        doc.h3("Check points")
        points_table(doc, ev.check, check_pairs)
    doc.h3("Training points" if ev.fitted else "Given pairs")
    points_table(doc, ev.train, train_pairs, cal.loo if ev.fitted else None)
    doc.h2("Fit", "fit")
    fit_table(doc, cal)
    doc.h2("Parameters", "params")
    params_section(doc, cal)
    return doc.render(), doc.files


def _summary(doc: Document, cal: Calibration, ev: _Evaluated, extra: Mapping | None) -> None:
    """Key figures, the caller's extra rows, the warnings."""
    doc.h2("Summary", "summary")
    cards = [
        ("model", cal.model_name, ""),
        ("optimizer", cal.fit.optimizer, ""),
        ("training fitness", f"{cal.fit.fitness:.5f}", fitness_unit(cal.fit.objective)),
    ]
    if ev.check is not None:
        cards += [("check RMS", mm(ev.check.rms_mm), "mm"), ("check max", mm(ev.check.max_mm), "mm")]
    elif cal.loo is not None:
        cards += [
            ("leave-one-out RMS", mm(cal.loo.rms_mm), "mm"),
            ("leave-one-out max", mm(cal.loo.max_mm), "mm"),
        ]
    cards.append((f"{ev.train_label} RMS", mm(ev.train.rms_mm), "mm"))
    doc.cards(cards)
    if extra:
        doc.table(None, [[str(k), str(v)] for k, v in extra.items()])
    if ev.check is None:
        doc.p(
            "No check pairs: accuracy on unseen points is estimated by leave-one-out only. "
            "Give check pairs (--check) to measure it.",
            "warn",
        )
    if ev.warnings:
        doc.notes(ev.warnings, warn=True)


def _accuracy(doc: Document, cal: Calibration, ev: _Evaluated) -> None:
    """The statistics of each set, the model selection, the notes."""
    doc.h2("Accuracy", "accuracy")
    stats_table(
        doc,
        [
            (ev.train_label, ev.train, ev.train_what),
            ("leave-one-out", cal.loo, "each training pair predicted by a fit without it"),
            ("check", ev.check, "pairs not used for fitting"),
        ],
    )
    if cal.selection:
        doc.h3("Model selection")
        selection_table(doc, cal.selection)
    doc.h3("Notes")
    doc.notes(ev.notes)


def _plots(
    doc: Document,
    cal: Calibration,
    ev: _Evaluated,
    check_pairs: PointPairs | None,
    train_pairs: PointPairs | None,
) -> None:
    """Convergence, the errors per check and per training point, residual vectors, the sigma map."""
    from eyetohand.reports import plots

    doc.h2("Plots", "plots")
    hist = cal.fit.history
    if len(hist) > 1:
        ax = plots.plot_convergence(
            {f"{cal.model_name} + {cal.fit.optimizer}": hist},
            ylabel=_fitness_label(cal.fit.objective),
            title=f"Convergence of {cal.fit.optimizer}",
        )
        doc.figure("convergence.png", ax, "Best fitness of the swarm per iteration, training pairs.")
    else:
        doc.p(
            f"No convergence plot: optimizer '{cal.fit.optimizer}' records no iteration history "
            "(only hybrid-pso and pso do).",
            "muted",
        )
    if ev.check is not None:
        label = f"{cal.model_name} + {cal.fit.optimizer}"
        ax = plots.plot_point_errors(
            {label: [p.error_mm for p in ev.check.points]},
            [p.id for p in ev.check.points],
            title="Error per check point",
        )
        doc.figure("check_errors.png", ax, "Error norm of each check point, robot space.")
    tr = {f"{ev.train_label} (fit residual)": [p.error_mm for p in ev.train.points]}
    if cal.loo is not None and ev.fitted:
        tr["leave-one-out"] = [p.error_mm for p in cal.loo.points]
    ax = plots.plot_point_errors(
        tr, [p.id for p in ev.train.points], xlabel="training point id", title="Error per training point"
    )
    doc.figure(
        "train_errors.png",
        ax,
        "Fit residual of each training point and, when computed, its "
        "leave-one-out error (the point predicted by a fit without it).",
    )
    # the pairs given, else the ones the calibration file carries (every schema-2 file does)
    stored_train = cal.pairs if ev.train_label == "train" else None
    sets = [(ev.train_label, train_pairs or stored_train), ("check", check_pairs or cal.check_pairs)]
    _residual_plot(doc, cal, sets)
    _sigma_map(doc, cal)


def _residual_plot(
    doc: Document,
    cal: Calibration,
    sets: list[tuple[str, PointPairs | None]],
    name: str = "residual_vectors.png",
) -> None:
    """One quiver plot of the given pair sets (same scale); a note when no positions are known."""
    from eyetohand.reports import plots

    given = [(label, p) for label, p in sets if p is not None]
    if not given:
        doc.p(
            "Residual vectors: not drawn. This calibration carries no pairs (their image positions); "
            "give them (--pairs TRAIN and/or --check CHECK) to draw them.",
            "muted",
        )
        return
    data: list[tuple[str, PointPairs, np.ndarray, np.ndarray | None]] = []
    for label, pairs in given:
        res = cal.model.residuals(pairs.uv_px, pairs.xyz_mm)
        jac: np.ndarray | None
        try:
            jac = image_jacobian(cal.model, pairs.uv_px, pairs.xyz_mm[:, 2])
            if not np.isfinite(jac).all() or (np.abs(np.linalg.det(jac)) < 1e-15).any():
                jac = None
        except (InputError, ValueError, FloatingPointError):
            jac = None
        data.append((label, pairs, res, jac))
    all_uv = np.vstack([p.uv_px for _, p, _, _ in data])
    all_mag = np.concatenate([np.linalg.norm(r[:, :2], axis=1) for _, _, r, _ in data])
    extent = max(cal.image_size) if cal.image_size else float(max(np.ptp(all_uv, axis=0).max(), 1.0))
    scale = 0.1 * extent / all_mag.max() if all_mag.max() > 0 else 1.0
    ax = None
    directions = (
        "image direction of the error" if all(j is not None for *_, j in data) else "dx along +u, dy along +v"
    )
    for i, (label, pairs, res, jac) in enumerate(data):
        ax = plots.plot_residual_vectors(
            pairs.uv_px,
            res,
            ax,
            cal.image_size,
            scale,
            jacobian_mm_per_px=jac,
            ids=pairs.ids,
            label=f"{label} ({len(pairs)} points)",
            color=plots.COLORS[i],
            title=f"Residual vectors — {cal.model_name} + {cal.fit.optimizer}",
        )
    doc.figure(
        name,
        ax,
        f"Predicted − actual robot position (mm) drawn at each pair's image position "
        f"(px), arrows magnified {scale:.3g} px per mm (see the key); arrows point in the "
        f"{directions}. A systematic pattern (rotation, radial flow) means the model misses "
        "something; random directions mean measurement noise.",
    )


def _drift(doc: Document, history: Sequence[Mapping], limit_mm: float | None) -> None:
    """The checks of the calibration over time against the limit (or a note that there are none)."""
    from eyetohand.reports import plots

    doc.h2("Drift", "drift")
    if not history:
        doc.p("No checks in the history given: nothing to draw yet.", "muted")
        return
    ax = plots.plot_drift(history, limit_mm=limit_mm)
    pts = plots.drift_points(history)
    worst = max(pts, key=lambda p: p["error_mm"])
    doc.figure(
        "drift.png",
        ax,
        f"The largest point error of each of the {len(pts)} checks over time (a verification's max, a "
        "CAL CHECK's one point), the limit dashed, version changes as vertical lines. A rising trend "
        f"is the camera or the cell moving; the worst was {worst['error_mm']:.4f} mm on "
        f"{worst['utc']:%Y-%m-%d %H:%M} UTC.",
    )


def load_history(path: str | os.PathLike) -> list[dict]:
    """The entries of a check history in JSON lines (``eyetohand verify``'s ``CAL.json.history.jsonl``,
    a collection's ``<name>.checks.jsonl``), file order. A line that is not a JSON object is an
    :class:`InputError` naming it, except a torn last line (a crash mid-write), which is left out."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise InputError(f"{p}: cannot read the history ({exc.strerror or exc})") from None
    out = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
        except json.JSONDecodeError:
            if i == len(lines):
                break
            raise InputError(f"{p} line {i}: not JSON") from None
        if not isinstance(d, dict):
            raise InputError(f"{p} line {i}: not a JSON object")
        out.append(d)
    return out


SIGMA_GRID = 120


def _sigma_map(doc: Document, cal: Calibration) -> None:
    """sigma_mm over the image with the calibrated region outlined: where it can be trusted."""
    if cal.region is None or cal.uncertainty is None:
        doc.p(
            "No sigma map: this calibration records no calibrated region or uncertainty (a pre-0.2 file).",
            "muted",
        )
        return
    ax, caption = trust_map(cal)
    doc.figure("sigma_map.png", ax, caption)


def trust_map(cal: Calibration, ax=None, *, background=None):
    """The trust map of ``cal`` (which must record its region and uncertainty): ``(axes, caption)`` —
    sigma_mm over the image as a heat map, the calibrated region and the refused-beyond line, and the
    pixel of the region where one more training pair lowers the mean sigma_mm inside it most
    (:func:`eyetohand.solve.best_new_point`). ``background``: an image of the camera (H, W[, 3]) drawn
    under the map; it must be the calibration's image size when the calibration records one."""
    from eyetohand.models import HeightRule
    from eyetohand.reports import plots
    from eyetohand.solve import best_new_point

    assert cal.region is not None and cal.uncertainty is not None
    hull = cal.region.hull_px
    size = cal.image_size
    if background is not None:
        bh, bw = np.asarray(background).shape[:2]
        if size is not None and tuple(size) != (bw, bh):
            raise InputError(
                f"background: the image is {bw} x {bh} px, the calibration's images {size[0]} x {size[1]} px"
            )
        size = (bw, bh)
    if size is not None:
        w, h = size
        lo, hi = np.array([0.0, 0.0]), np.array([w - 1.0, h - 1.0])
    else:
        span = hull.max(axis=0) - hull.min(axis=0)
        lo, hi = hull.min(axis=0) - 0.25 * span, hull.max(axis=0) + 0.25 * span
    n_u = SIGMA_GRID
    n_v = max(int(round(SIGMA_GRID * (hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-9))), 2)
    u, v = np.linspace(lo[0], hi[0], n_u), np.linspace(lo[1], hi[1], n_v)
    uv = np.column_stack([g.ravel() for g in np.meshgrid(u, v)])
    if cal.region.plane_z_mm is not None:
        z, where = cal.region.plane_z_mm, f"on the plane z = {cal.region.plane_z_mm:g} mm"
    else:
        lo_z, hi_z = cal.region.z_range_mm or (0.0, 0.0)
        z, where = 0.5 * (lo_z + hi_z), f"at z = {0.5 * (lo_z + hi_z):g} mm, mid calibrated range"
    computed = cal.model.height_rule is HeightRule.COMPUTED
    zq = np.zeros(len(uv)) if computed else np.full(len(uv), z)
    with np.errstate(all="ignore"):
        s = cal.uncertainty.sigma_mm(cal.model, uv, zq).reshape(n_v, n_u)
        if cal.plate is not None:  # the touches' error, shared by every point (docs/plate.md)
            xyz = cal.model.image_to_robot(uv, zq if cal.model.height_rule is HeightRule.GIVEN else None)
            s = np.sqrt(
                s**2 + cal.plate.placement_variance_mm2(xyz, cal.uncertainty.n_coords).reshape(n_v, n_u)
            )
    inside = (cal.region.outside_px(uv) <= cal.region.margin_px) & np.isfinite(s.ravel())
    inner = s.ravel()[inside]
    best = None
    if inner.size and cal.plate is None:  # one more pair does not lessen a plate's touches error
        # candidates: every 4th grid pixel inside the refused-beyond line (where parts are mapped; a
        # pair far outside would score best by leverage alone, somewhere the robot may not reach)
        sub = np.zeros((n_v, n_u), bool)
        sub[::4, ::4] = True
        cand = uv[sub.ravel() & inside] if (sub.ravel() & inside).any() else uv[inside]
        with np.errstate(all="ignore"):
            k, means = best_new_point(cal.uncertainty, cal.model, cand, zq[0], uv[inside], zq[0])
        if np.isfinite(means[k]):
            best = (cand[k], float(np.mean(inner)), float(means[k]))
    pts = cal.fitted_pairs.uv_px if cal.fitted_pairs is not None else None
    ax = plots.plot_sigma_map(
        u,
        v,
        s,
        hull,
        ax,
        points_px=pts,
        image_size=size,
        margin_hull_px=grown_hull(hull, cal.region.margin_px),
        add_point_px=None if best is None else best[0],
        background=background,
    )
    rng = f"{np.nanmin(inner):.4f}–{np.nanmax(inner):.4f} mm" if inner.size else "–"
    add = (
        f" The star marks where one more training pair helps most: at (u, v) = ({best[0][0]:.0f}, "
        f"{best[0][1]:.0f}) px the mean sigma_mm inside falls from {best[1]:.4f} to {best[2]:.4f} mm "
        "(predicted, same noise)."
        if best is not None
        else ""
    )
    caption = (
        f"Where this calibration can be trusted: the predicted error "
        f"sigma_mm of a mapped point ({where}), the calibrated region (training hull) in white "
        f"and its margin dashed — mappings beyond it are refused. Inside: {rng}.{add}"
    )
    return ax, caption


def grown_hull(hull: np.ndarray, margin_px: float, step_deg: float = 2.0) -> np.ndarray:
    """(M, 2) the outline of the points within ``margin_px`` of the convex ``hull`` (K, 2): the hull
    grown by the margin — its Minkowski sum with a disc: each edge moved out along its normal, joined
    by an arc of radius ``margin_px`` round each vertex (sampled every ``step_deg``; the chords stay
    within r·(1 − cos(step/2)) of the arc, 0.008 px for a 50 px margin). This is where
    :meth:`CalibratedRegion.check` starts refusing (``outside_px`` > margin)."""
    a = np.asarray(hull, float)
    e = np.roll(a, -1, axis=0) - a
    area2 = float(np.sum(a[:, 0] * np.roll(a[:, 1], -1) - np.roll(a[:, 0], -1) * a[:, 1]))
    turn = 1.0 if area2 > 0 else -1.0  # +1: counter-clockwise in (u, v) as written
    n = (
        turn
        * np.column_stack([e[:, 1], -e[:, 0]])
        / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)
    )
    out = []
    for i in range(len(a)):
        t0 = np.arctan2(n[i - 1, 1], n[i - 1, 0])
        t1 = np.arctan2(n[i, 1], n[i, 0])
        d = (t1 - t0 + np.pi) % (2 * np.pi) - np.pi  # the turn at vertex i, signed as the polygon turns
        k = max(1, int(np.ceil(abs(np.degrees(d)) / step_deg)))
        th = t0 + d * np.linspace(0.0, 1.0, k + 1)
        out.append(a[i] + margin_px * np.column_stack([np.cos(th), np.sin(th)]))
    return np.vstack(out)


def write_report(
    out_dir: str | os.PathLike,
    calibration: Calibration,
    check_pairs: PointPairs | None = None,
    train_pairs: PointPairs | None = None,
    extra: Mapping | None = None,
    *,
    history: Sequence[Mapping] | None = None,
    limit_mm: float | None = None,
    against: tuple[Calibration, str] | None = None,
) -> Path:
    """Write the report of ``calibration`` into ``out_dir``; returns the path of ``index.html``.

    See :func:`build_report` for the arguments. All plots and the HTML are built in memory before
    anything is written, so a failure leaves an earlier report in ``out_dir`` unchanged.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    text, files = build_report(
        calibration, check_pairs, train_pairs, extra, history=history, limit_mm=limit_mm, against=against
    )
    return write_folder(out, text, files)
