"""Plots of a calibration: convergence (the paper's Fig. 4), per-point errors (Fig. 5), residual vectors.

Every function takes ``ax=None`` and returns the axes it drew on. Given an axes, it draws there and
touches nothing else (use your own ``plt.subplots()`` to show a plot interactively). Without one, it
creates a figure attached to matplotlib's Agg canvas — no pyplot, no global state, safe in a server —
which you save with ``ax.figure.savefig(...)``. matplotlib is imported only when a function is called.

Units: robot errors and fitness in millimetres (mm), image positions in pixels (px).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from eyetohand.core import InputError

__all__ = [
    "drift_points",
    "plot_convergence",
    "plot_drift",
    "plot_model_comparison",
    "plot_plan_study",
    "plot_point_errors",
    "plot_residual_vectors",
    "plot_sigma_map",
    "nice_step",
]

# A colour-blind-safe cycle (Okabe–Ito), so methods keep their colour from plot to plot.
MAX_TICK_LABELS = 40
MAX_ID_LABELS = 40
COLORS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#F0E442")


def _new_axes(figsize: tuple[float, float]):
    """A fresh axes on a figure with an Agg canvas (lazy import, no pyplot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig.add_subplot()


def nice_step(value: float) -> float:
    """The largest 1, 2 or 5 × 10^k not above ``value`` (> 0): a round number for scale keys."""
    if not (value > 0 and math.isfinite(value)):
        return 1.0
    exp = math.floor(math.log10(value))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**exp <= value * (1 + 1e-9):
            return m * 10.0**exp
    return 10.0**exp


def _fmt_mm(v: float) -> str:
    """A millimetre value with enough digits for sub-micron differences to show."""
    return f"{v:.4f}" if abs(v) < 10 else f"{v:.2f}"


# ------------------------------------------------------------------ Fig. 4: convergence


def plot_convergence(
    history_or_dict,
    ax=None,
    *,
    log: bool | None = None,
    reference_lines: Mapping[str, float] | None = None,
    title: str | None = "Optimiser convergence",
    ylabel: str = "best fitness, eq. (16) [mm]",
):
    """Best fitness (mm) against iteration: the paper's Fig. 4.

    ``history_or_dict``: one sequence of best-fitness values (one per iteration, mm) or a mapping
    label → sequence (e.g. ``{"hybrid PSO": h1, "plain PSO": h2}``). ``log``: logarithmic fitness
    axis; None chooses it when the values span more than a factor of 20. Each curve's final value is
    written at its end. ``reference_lines``: label → fitness (mm) drawn dashed, e.g. a known optimum.
    Returns the axes.
    """
    if isinstance(history_or_dict, Mapping):
        series = {str(k): v for k, v in history_or_dict.items()}
    else:
        series = {"best fitness": history_or_dict}
    curves = {}
    for label, hist in series.items():
        h = np.asarray(hist, dtype=float).reshape(-1)
        h = h[np.isfinite(h)]
        if h.size == 0:
            raise InputError(f"convergence history {label!r} has no finite values")
        curves[label] = h
    if not curves:
        raise InputError("plot_convergence: no history given")
    if ax is None:
        ax = _new_axes((7.0, 4.2))
    lo = min(float(h.min()) for h in curves.values())
    hi = max(float(h.max()) for h in curves.values())
    if log is None:
        log = lo > 0 and hi / lo > 20
    for i, (label, h) in enumerate(curves.items()):
        color = COLORS[i % len(COLORS)]
        it = np.arange(1, h.size + 1)
        ax.plot(
            it,
            h,
            color=color,
            lw=1.8,
            label=f"{label} (final {h[-1]:.5f} mm)",
            drawstyle="steps-post" if h.size > 1 else "default",
            marker=None if h.size > 1 else "o",
        )
        ax.annotate(
            f"{h[-1]:.5f}",
            (it[-1], h[-1]),
            xytext=(-4, 6),
            textcoords="offset points",
            ha="right",
            va="bottom",
            fontsize=8,
            color=color,
        )
    for i, (label, value) in enumerate((reference_lines or {}).items()):
        ax.axhline(
            float(value),
            color="0.3",
            ls=("--", ":", "-.")[i % 3],
            lw=1.0,
            label=f"{label}: {float(value):.5f} mm",
        )
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="major", alpha=0.35)
    if log:
        ax.grid(True, which="minor", alpha=0.12)
    ax.set_xlim(left=0)
    ax.legend(loc="upper right", fontsize=8, frameon=True)
    if title:
        ax.set_title(title)
    return ax


# ------------------------------------------------------------------ Fig. 5: per-point errors


MAX_BARS = 400
"""Most points :func:`plot_point_errors` draws as bars (each its own patch); past it, one line per point
(the legend still counts the n/a ones)."""


def plot_point_errors(
    errors_by_method: Mapping[str, Sequence[float | None]],
    ids: Sequence[str] | None = None,
    ax=None,
    *,
    reference_lines: Mapping[str, float] | None = None,
    title: str | None = "Error per check point",
    ylabel: str = "error norm ‖Δ‖ [mm]",
    xlabel: str = "check point id",
):
    """Grouped bars of per-point error norms (mm), one bar per method: the paper's Fig. 5.

    ``errors_by_method``: label → errors, all the same length; a None or NaN error (a value the
    source does not give) is drawn as a small "n/a" mark instead of a bar. ``ids``: the point
    labels on the x axis (default 1..N). ``reference_lines``: label → value (mm) drawn as dashed
    horizontal lines (e.g. a published maximum). The legend gives each method's RMS and max over
    its known values. Returns the axes.
    """
    if not errors_by_method:
        raise InputError("plot_point_errors: no methods given")
    arrays = {}
    for label, errs in errors_by_method.items():
        arrays[str(label)] = np.array([np.nan if e is None else float(e) for e in errs], dtype=float)
    lengths = {a.size for a in arrays.values()}
    if len(lengths) != 1:
        raise InputError(f"plot_point_errors: methods give different numbers of points {sorted(lengths)}")
    n = lengths.pop()
    if n == 0:
        raise InputError("plot_point_errors: no points")
    if ids is None:
        ids = [str(i + 1) for i in range(n)]
    ids = [str(i) for i in ids]
    if len(ids) != n:
        raise InputError(f"plot_point_errors: {len(ids)} ids for {n} points")
    if ax is None:
        ax = _new_axes((min(11.0, max(7.0, 0.16 * n * (len(arrays) + 1) + 2.5)), 4.2 + 0.17 * len(arrays)))
    k = len(arrays)
    width = 0.8 / k
    x = np.arange(n)
    top = max([float(np.nanmax(a)) for a in arrays.values() if np.isfinite(a).any()] + [0.0])
    for j, (label, e) in enumerate(arrays.items()):
        color = COLORS[j % len(COLORS)]
        ok = np.isfinite(e)
        pos = x - 0.4 + width * (j + 0.5)
        known = e[ok]
        summary = (
            f"rms {_fmt_mm(float(np.sqrt(np.mean(known**2))))}, max {_fmt_mm(float(known.max()))} mm"
            if known.size
            else "no values"
        )
        if (~ok).any():
            summary += f", {int((~ok).sum())} n/a"
        if n <= MAX_BARS:
            ax.bar(pos[ok], known, width=width * 0.95, color=color, label=f"{label} ({summary})")
            for p in pos[~ok]:
                ax.text(p, top * 0.01, "n/a", rotation=90, ha="center", va="bottom", fontsize=7, color=color)
        else:  # a large collection: one line per point in one artist (a bar each is ~8 ms a point)
            ax.vlines(pos[ok], 0.0, known, color=color, lw=0.6, label=f"{label} ({summary})")
    for i, (label, value) in enumerate((reference_lines or {}).items()):
        ax.axhline(
            float(value),
            color="0.25",
            ls=("--", ":", "-.")[i % 3],
            lw=1.1,
            label=f"{label}: {_fmt_mm(float(value))} mm",
        )
    step = max(1, math.ceil(n / MAX_TICK_LABELS))  # thin the labels of long point lists
    shown = [_short_id(i) for i in ids[::step]]
    longest = max(len(i) for i in shown)
    upright = step == 1 and n <= 20 and longest * n <= 60  # short ids side by side, others turned
    ax.set_xticks(
        x[::step], shown, rotation=0 if upright else 90, fontsize=None if n <= 20 and longest <= 8 else 7
    )
    ax.set_xlim(-0.6, n - 0.4)
    n_entries = len(arrays) + len(reference_lines or {})
    refs = [float(v) for v in (reference_lines or {}).values()]
    high = max([top, *refs]) or 1.0
    # headroom above the tallest bar for a legend inside the axes (a row of ~7 % of the height each)
    ax.set_ylim(0, high * (1.12 + 0.1 * n_entries) if n_entries <= 3 else high * 1.08)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", alpha=0.35)
    ax.set_axisbelow(True)
    if n_entries <= 3:
        ax.legend(fontsize=8, loc="upper right", frameon=True)
    else:  # many methods: the legend goes under the axes, so it never hides a bar
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    if title:
        ax.set_title(title)
    return ax


def _short_id(pid: str, limit: int = 16) -> str:
    """A point id short enough for an axis: an image path by its file's stem, then its last characters."""
    if len(pid) <= limit:
        return pid
    if "/" in pid or "\\" in pid or "." in pid:
        pid = pid.replace("\\", "/").rsplit("/", 1)[-1].rsplit(".", 1)[0] or pid
    return pid if len(pid) <= limit else "…" + pid[-(limit - 1) :]


# ------------------------------------------------------------------ residual vectors


def plot_residual_vectors(
    uv_px,
    residuals_mm,
    ax=None,
    image_size: tuple[int, int] | None = None,
    scale: float | None = None,
    *,
    jacobian_mm_per_px=None,
    ids: Sequence[str] | None = None,
    label: str | None = None,
    color: str | None = None,
    key: bool = True,
    label_largest: int = 8,
    title: str | None = "Residual vectors over the image",
):
    """Arrows of the in-plane residuals (predicted − actual, mm) at the pairs' image positions (px).

    The axes are image axes: u to the right, v down; equal aspect. ``residuals_mm``: (N, 2) or
    (N, 3) (dz is ignored). ``jacobian_mm_per_px``: (N, 2, 2) or (2, 2) derivative of the robot
    (x, y) with respect to (u, v) at each point; when given, each arrow points in the image
    direction of its robot-space error (length still proportional to mm), so arrows read as "the
    mapped point lies this way". Without it, dx is drawn along +u and dy along +v.
    ``scale``: arrow length in image pixels per mm of error; None makes the longest arrow about a
    tenth of the image (or point spread). ``image_size``: (W, H) px, sets the limits. A scale key
    with a round number of mm is drawn when ``key``. ``ids``: point labels, written next to every
    point when there are at most 40, else next to the ``label_largest`` largest errors only.
    Returns the axes; the scale used is stored in ``ax._eyetohand_scale_px_per_mm``, so a second
    set of arrows drawn on the same axes (another colour and label) uses the same scale.
    """
    uv = np.asarray(uv_px, dtype=float)
    res = np.asarray(residuals_mm, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"uv_px must have shape (N, 2), got {uv.shape}")
    if res.ndim != 2 or res.shape[1] not in (2, 3) or len(res) != len(uv):
        raise InputError(f"residuals_mm must have shape ({len(uv)}, 2|3), got {res.shape}")
    if len(uv) == 0:
        raise InputError("plot_residual_vectors: no points")
    d = res[:, :2]
    mag = np.linalg.norm(d, axis=1)
    direction = _arrow_directions(d, mag, jacobian_mm_per_px)
    if ax is None:
        ax = _new_axes((7.0, 6.4))
    all_uv, extent, scale = _extent_and_scale(ax, uv, mag, image_size, scale)
    vec = direction * mag[:, None] * scale  # px on the image axes
    n_sets = getattr(ax, "_eyetohand_sets", 0)
    ax._eyetohand_sets = n_sets + 1
    color = color or COLORS[n_sets % len(COLORS)]
    ax.scatter(uv[:, 0], uv[:, 1], s=14, color=color, zorder=3, label=label)
    q = ax.quiver(
        uv[:, 0],
        uv[:, 1],
        vec[:, 0],
        vec[:, 1],
        angles="xy",
        scale_units="xy",
        scale=1.0,
        color=color,
        width=0.004,
        headwidth=3.5,
        headlength=4.5,
        zorder=4,
    )
    if ids is not None:
        _label_points(ax, uv, mag, ids, color, label_largest)
    if image_size is not None:
        ax.set_xlim(0, float(image_size[0]))
        ax.set_ylim(float(image_size[1]), 0)
    else:
        pad = 0.12 * extent
        ax.set_xlim(all_uv[:, 0].min() - pad, all_uv[:, 0].max() + pad)
        ax.set_ylim(all_uv[:, 1].max() + pad, all_uv[:, 1].min() - pad)  # v down
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px] (down)")
    ax.grid(True, alpha=0.25)
    if key and not getattr(ax, "_eyetohand_key", False):
        _scale_key(ax, q, extent, scale)
    if label:
        ax.legend(fontsize=8, loc="best", framealpha=0.9)
    if title:
        ax.set_title(title, loc="left", fontsize=10.5)
    return ax


def _extent_and_scale(
    ax, uv: np.ndarray, mag: np.ndarray, image_size: tuple[int, int] | None, scale: float | None
) -> tuple[np.ndarray, float, float]:
    """``(all_uv, extent px, scale px per mm)`` of a set of arrows drawn on ``ax``: the positions of
    every set drawn there so far (kept on the axes), the image's or their spread's larger side, and
    the scale given, else the one of the axes' earlier sets, else a tenth of the extent for the
    largest error (kept on the axes too)."""
    all_uv = np.vstack([getattr(ax, "_eyetohand_uv", np.empty((0, 2))), uv])
    ax._eyetohand_uv = all_uv
    if image_size is not None:
        extent = max(float(image_size[0]), float(image_size[1]))
    else:
        extent = float(max(np.ptp(all_uv, axis=0).max(), 1.0))
    if scale is None:
        scale = getattr(ax, "_eyetohand_scale_px_per_mm", None)
    if scale is None:
        biggest = float(mag.max())
        scale = 0.1 * extent / biggest if biggest > 0 else 1.0
    scale = float(scale)
    if not (scale > 0 and math.isfinite(scale)):
        raise InputError(f"scale must be a positive number of px per mm, got {scale!r}")
    ax._eyetohand_scale_px_per_mm = scale
    return all_uv, extent, scale


def _arrow_directions(d: np.ndarray, mag: np.ndarray, jacobian_mm_per_px) -> np.ndarray:
    """(N, 2) unit image directions of the residuals ``d`` (N, 2) mm of norms ``mag``: through the
    Jacobian when given (``d`` turned into pixels), else dx along +u and dy along +v; 0 for no error."""
    if jacobian_mm_per_px is None:
        return np.divide(d, mag[:, None], out=np.zeros_like(d), where=mag[:, None] > 0)
    J = np.broadcast_to(np.asarray(jacobian_mm_per_px, dtype=float), (len(d), 2, 2))
    try:
        duv = np.linalg.solve(J, d[..., None])[..., 0]
    except np.linalg.LinAlgError:
        raise InputError("plot_residual_vectors: singular Jacobian") from None
    nrm = np.linalg.norm(duv, axis=1)
    return np.divide(duv, nrm[:, None], out=np.zeros_like(duv), where=nrm[:, None] > 0)


def _label_points(ax, uv: np.ndarray, mag: np.ndarray, ids: Sequence[str], color: str, largest: int) -> None:
    """Each point's id beside it; beyond :data:`MAX_ID_LABELS` points, only the ``largest`` errors'."""
    if len(ids) != len(uv):
        raise InputError(f"plot_residual_vectors: {len(ids)} ids for {len(uv)} points")
    shown = (
        np.arange(len(uv)) if len(uv) <= MAX_ID_LABELS else np.argsort(-mag, kind="stable")[: max(0, largest)]
    )
    for (u, v), name in zip(uv[shown], np.asarray(ids, dtype=object)[shown], strict=True):
        ax.annotate(
            str(name),
            (u, v),
            xytext=(3, -3),
            textcoords="offset points",
            fontsize=7,
            color=color,
            ha="left",
            va="top",
        )


def _scale_key(ax, q, extent: float, scale: float) -> None:
    """The arrows' key above the axes: a round number of mm near a tenth of ``extent`` px."""
    ref_mm = nice_step(0.1 * extent / scale)
    ax.quiverkey(
        q,
        0.93,
        1.025,
        ref_mm * scale,
        f"key: {_fmt_mm(ref_mm).rstrip('0').rstrip('.')} mm",
        labelpos="W",
        coordinates="axes",
        color="0.2",
        fontproperties={"size": 8},
    )
    ax._eyetohand_key = True


# ------------------------------------------------------------------ compare rows


def plot_model_comparison(rows: Sequence[Mapping], ax=None, *, title: str | None = "Models × optimisers"):
    """Horizontal bars of check RMS and max (mm) for the rows of
    :func:`eyetohand.calibration.compare.compare`.

    Rows with an ``error`` are listed with "n/a" and no bars. Sorted as given (top = first row).
    Returns the axes.
    """
    rows = list(rows)
    if not rows:
        raise InputError("plot_model_comparison: no rows")
    labels = [f"{r.get('model', '?')} + {r.get('optimizer', '?')}" for r in rows]
    rms = np.array([r.get("check_rms_mm", np.nan) if "error" not in r else np.nan for r in rows], float)
    mx = np.array([r.get("check_max_mm", np.nan) if "error" not in r else np.nan for r in rows], float)
    if ax is None:
        ax = _new_axes((7.5, 0.32 * len(rows) + 1.6))
    y = np.arange(len(rows))
    ok = np.isfinite(rms)
    ax.barh(y[ok] - 0.2, rms[ok], height=0.38, color=COLORS[0], label="check RMS")
    ok_m = np.isfinite(mx)
    ax.barh(y[ok_m] + 0.2, mx[ok_m], height=0.38, color=COLORS[1], label="check max")
    for yi in y[~ok]:
        ax.text(0, yi, " n/a", va="center", fontsize=7, color="0.4")
    ax.set_yticks(y, labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("check error [mm]")
    ax.grid(True, axis="x", alpha=0.35)
    ax.set_axisbelow(True)
    ax.legend(fontsize=8, loc="lower right")
    if title:
        ax.set_title(title)
    return ax


# ------------------------------------------------------------------ plan study (eyetohand plan)


def plot_plan_study(study: Mapping, ax=None, *, title: str | None = None):
    """Predicted check RMS and max (mm) per plan of :func:`eyetohand.sim.planner.plan_study`.

    Bars: the median over the simulated sessions; whiskers: their 90th percentile (one session in
    ten is worse), both named in the legend. Plans sorted by number of pairs; the target error is a
    dashed line, the recommended plan is marked under its bars. Plans that could not be calibrated
    are left out. Returns the axes."""
    rows = sorted(
        [r for r in study.get("plans", ()) if r.get("predicted_rms_mm") is not None],
        key=lambda r: r["n_pairs"],
    )
    if not rows:
        raise InputError("plot: no plan could be calibrated, nothing to plot")
    if ax is None:
        ax = _new_axes((7.0, 4.2))
    n = len(rows)
    x = np.arange(n)
    runs = int(study.get("runs") or rows[0].get("runs") or 0)
    rms = np.array([r["predicted_rms_mm"] for r in rows], float)
    mx = np.array([r["predicted_max_mm"] for r in rows], float)
    rms90 = np.array([r.get("rms_p90_mm", r["predicted_rms_mm"]) for r in rows], float)
    mx90 = np.array([r.get("max_p90_mm", r["predicted_max_mm"]) for r in rows], float)
    w = 0.38
    ax.bar(x - w / 2, rms, w * 0.95, color=COLORS[0], label="check RMS, median of the runs")
    ax.bar(x + w / 2, mx, w * 0.95, color=COLORS[1], label="check max, median of the runs")
    ax.errorbar(
        np.concatenate([x - w / 2, x + w / 2]),
        np.concatenate([rms, mx]),
        yerr=[np.zeros(2 * n), np.concatenate([rms90 - rms, mx90 - mx])],
        fmt="none",
        ecolor="0.2",
        elinewidth=1.0,
        capsize=3,
        label=f"whisker: 90th percentile of {runs} runs (1 session in 10 is worse)",
    )
    target = study.get("target_error_mm")
    if target is not None:
        ax.axhline(
            float(target),
            color="0.25",
            ls="--",
            lw=1.1,
            label=f"target: {study.get('target_metric', 'max')} ≤ {_fmt_mm(float(target))} mm",
        )
    recommended = study.get("recommended")
    labels = [
        f"{r['plan']}\n{r['n_pairs']} pairs" + ("\nrecommended" if r["plan"] == recommended else "")
        for r in rows
    ]
    ax.set_xticks(x, labels, fontsize=8)
    for tick, r in zip(ax.get_xticklabels(), rows, strict=True):
        if r["plan"] == recommended:
            tick.set_fontweight("bold")
    n_entries = 3 + (target is not None)
    high = max(float(mx90.max()), float(target or 0.0)) or 1.0
    ax.set_ylim(0, high * (1.1 + 0.09 * n_entries))  # headroom: the legend never covers a bar
    ax.set_xlim(-0.6, n - 0.4)
    ax.set_ylabel("predicted check error [mm]")
    ax.set_xlabel("calibration plan (fewest pairs first)")
    ax.grid(True, axis="y", alpha=0.35)
    ax.set_axisbelow(True)
    ax.legend(fontsize=8, loc="upper right", frameon=True)
    if title is None:
        heights = ", ".join(f"{h:g}" for h in rows[0].get("heights", ()))
        title = f"Planned accuracy: Monte Carlo over {runs} simulated sessions per plan, z = {heights} mm"
    if title:
        ax.set_title(title, fontsize=10.5)
    return ax


# ------------------------------------------------------------------ where a calibration can be trusted


def plot_sigma_map(
    u_px,
    v_px,
    sigma_mm,
    hull_px,
    ax=None,
    *,
    margin_hull_px=None,
    points_px=None,
    image_size: tuple[int, int] | None = None,
    add_point_px=None,
    background=None,
    title: str | None = "Predicted error sigma_mm over the image",
):
    """sigma_mm (mm) as a colour map over the image, the calibrated region outlined.

    ``u_px`` (W,), ``v_px`` (H,): the grid's pixel coordinates; ``sigma_mm`` (H, W) (NaN where the
    map has no answer). ``hull_px`` (K, 2): the training pixels' hull, drawn closed; optional
    ``margin_hull_px`` the hull grown by the margin (dashed: beyond it mappings are refused);
    ``points_px`` (N, 2) the training pixels; ``add_point_px`` (u, v) where to add a pair (a star);
    ``background`` (H, W) or (H, W, 3) a camera image (BGR, as OpenCV reads it) drawn in grey under a
    half-transparent heat map, pixel (0, 0) at (u, v) = (0, 0).
    Image axes: u right, v down, equal aspect. Returns the axes."""
    u = np.asarray(u_px, float)
    v = np.asarray(v_px, float)
    s = np.asarray(sigma_mm, float)
    if s.shape != (len(v), len(u)):
        raise InputError(f"sigma_mm must have shape ({len(v)}, {len(u)}), got {s.shape}")
    hull = np.asarray(hull_px, float)
    if hull.ndim != 2 or hull.shape[1] != 2 or len(hull) < 3:
        raise InputError("hull_px must be three or more (u, v) points")
    if ax is None:
        ax = _new_axes((7.2, 5.4))
    finite = s[np.isfinite(s)]
    vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
    alpha = None
    if background is not None:
        img = np.asarray(background)
        if img.ndim == 3:  # BGR → luminance
            img = img[..., :3].astype(float) @ np.array([0.114, 0.587, 0.299])
        h, w = img.shape[:2]
        ax.imshow(img, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="antialiased")
        alpha = 0.55
    mesh = ax.pcolormesh(u, v, s, shading="nearest", cmap="viridis", vmin=0.0, vmax=vmax, alpha=alpha)
    ax.figure.colorbar(mesh, ax=ax, label="sigma_mm [mm]")
    closed = np.vstack([hull, hull[:1]])
    ax.plot(closed[:, 0], closed[:, 1], color="white", lw=2.0, label="calibrated region (training hull)")
    if margin_hull_px is not None:
        m = np.asarray(margin_hull_px, float)
        m = np.vstack([m, m[:1]])
        ax.plot(m[:, 0], m[:, 1], color="white", lw=1.0, ls="--", label="+ margin: refused beyond")
    if points_px is not None:
        pts = np.asarray(points_px, float)
        ax.plot(pts[:, 0], pts[:, 1], "o", ms=3, color="#D55E00", label="training pairs")
    if add_point_px is not None:
        ax.plot(
            [add_point_px[0]],
            [add_point_px[1]],
            "*",
            ms=16,
            color="#F0E442",
            mec="black",
            label="add a pair here",
        )
    if image_size is not None:
        ax.set_xlim(-0.5, image_size[0] - 0.5)
        ax.set_ylim(image_size[1] - 0.5, -0.5)
    else:
        ax.set_xlim(u.min(), u.max())
        ax.set_ylim(v.max(), v.min())
    ax.set_aspect("equal")
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px]")
    # under the axes: inside, it hid the top of the region's outline
    ax.legend(
        loc="upper center",
        bbox_to_anchor=(0.5, -0.12),
        ncol=3,
        fontsize="small",
        facecolor="0.45",
        labelcolor="white",
    )
    if title:
        ax.set_title(title)
    return ax


# ------------------------------------------------------------------ drift: the checks over time


def _utc(value, what: str):
    """A timezone-aware datetime (UTC when the text names no zone) from an ISO 8601 text or datetime."""
    import datetime as dt

    if isinstance(value, dt.datetime):
        t = value
    else:
        try:
            t = dt.datetime.fromisoformat(str(value))
        except ValueError:
            raise InputError(f"{what}: 'utc' {value!r} is not an ISO 8601 time") from None
    return t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)


def drift_points(entries: Sequence[Mapping]) -> list[dict]:
    """The checks of a verification history as the drift plot draws them, oldest first: ``utc``
    (datetime), ``error_mm`` (the check's largest point error: a verification's ``max_mm``, the one
    point of a collection's CAL CHECK's ``error_mm``; what a tolerance is held against), ``rms_mm``
    (verifications only, else None), ``tolerance_mm`` (None when not recorded), ``version`` (None when
    not recorded) and ``kind`` ("verify" or "CAL CHECK"). An entry with neither error is named."""
    out = []
    for i, e in enumerate(entries):
        what = f"history entry {i + 1}"
        if "utc" not in e:
            raise InputError(f"{what}: no 'utc'")
        if e.get("max_mm") is not None:
            err, rms, kind = float(e["max_mm"]), e.get("rms_mm"), "verify"
        elif e.get("error_mm") is not None:
            err, rms, kind = float(e["error_mm"]), None, "CAL CHECK"
        else:
            raise InputError(f"{what}: neither 'max_mm' (a verification) nor 'error_mm' (a CAL CHECK)")
        tol, ver = e.get("tolerance_mm"), e.get("version")
        out.append(
            {
                "utc": _utc(e["utc"], what),
                "error_mm": err,
                "rms_mm": None if rms is None else float(rms),
                "tolerance_mm": None if tol is None else float(tol),
                "version": None if ver is None else int(ver),
                "kind": kind,
            }
        )
    out.sort(key=lambda p: p["utc"])  # stable: entries of one second keep their order
    return out


def plot_drift(
    entries: Sequence[Mapping],
    ax=None,
    *,
    limit_mm: float | None = None,
    versions: Sequence[tuple] | None = None,
    title: str | None = "Drift: the error of each check over time",
):
    """The error of each check of a calibration over time, against the limit.

    ``entries``: verification history entries (``eyetohand verify``'s ``CAL.json.history.jsonl``, the
    server's ``/history``: ``utc``, ``max_mm``, ``rms_mm``, ``tolerance_mm``, ``version``) and/or a
    collection's CAL CHECK records (``<name>.checks.jsonl``: ``utc``, ``error_mm``, ``version``), in any
    order (see :func:`drift_points`). One line, oldest first, of each check's largest point error (mm)
    — what the tolerance is held against — with verifications as circles and CAL CHECKs as diamonds,
    the verifications' RMS dotted under it, and checks beyond the limit ringed.
    ``limit_mm``: the limit, a horizontal dashed line; default the entries' ``tolerance_mm`` (a step
    line when it changed, none when no entry records one). ``versions``: ``(utc, version)`` of each
    calibration version (when it was made); default the first check of each new version. A version
    change is a vertical line labelled ``v<N>`` on the time axis. Returns the axes."""
    import matplotlib.dates as mdates

    pts = drift_points(entries)
    if not pts:
        raise InputError("plot_drift: no checks in the history")
    if limit_mm is not None and not (math.isfinite(limit_mm) and limit_mm > 0):
        raise InputError(f"plot_drift: limit_mm must be a positive number of mm, got {limit_mm!r}")
    if ax is None:
        ax = _new_axes((7.6, 4.2))
    t = [p["utc"] for p in pts]
    err = np.array([p["error_mm"] for p in pts])
    ax.plot(t, err, "-", color=COLORS[0], lw=1.4, label="check error (largest point)", gid="drift-error")
    for kind, marker in (("verify", "o"), ("CAL CHECK", "D")):
        sel = [i for i, p in enumerate(pts) if p["kind"] == kind]
        if sel:
            ax.plot(
                [t[i] for i in sel], err[sel], marker, ms=5, color=COLORS[0], label=f"{kind} ({len(sel)})"
            )
    rms = [(p["utc"], p["rms_mm"]) for p in pts if p["rms_mm"] is not None]
    if rms:
        ax.plot(*zip(*rms, strict=True), ":", color=COLORS[2], lw=1.2, label="verify: RMS of its points")
    top = float(err.max())
    limits = _limit_steps(pts, limit_mm)
    if limits:
        if len({v for _, v in limits}) == 1:
            value = limits[0][1]
            ax.axhline(value, color=COLORS[1], ls="--", lw=1.3, label=f"limit {value:g} mm", gid="limit")
        else:
            xs = [x for x, _ in limits] + [t[-1]]
            ys = [v for _, v in limits] + [limits[-1][1]]
            ax.step(
                xs,
                ys,
                where="post",
                color=COLORS[1],
                ls="--",
                lw=1.3,
                label="limit (as recorded)",
                gid="limit",
            )
        tol = np.array([_limit_at(limits, x) for x in t])
        over = err > tol
        if over.any():
            ax.plot(
                [t[i] for i in np.flatnonzero(over)],
                err[over],
                "o",
                ms=11,
                mfc="none",
                mec=COLORS[1],
                mew=1.6,
                label=f"beyond the limit ({int(over.sum())})",
            )
        top = max(top, max(v for _, v in limits))
    marks = _version_marks(ax, pts, versions)
    _time_limits(ax, t + marks)
    ax.set_ylim(0, 1.12 * top if top > 0 else 1.0)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(ax.xaxis.get_major_locator()))
    ax.set_xlabel("time of the check (UTC)")
    ax.set_ylabel("error [mm]")
    ax.grid(True, alpha=0.35)
    ax.set_axisbelow(True)
    # under the axes: inside, it would hide the checks of whichever corner it took
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
    if title:
        ax.set_title(title)
    return ax


def _limit_steps(pts: list[dict], limit_mm: float | None) -> list[tuple]:
    """[(from utc, limit mm)]: the given limit throughout, else each change of the recorded tolerance."""
    if limit_mm is not None:
        return [(pts[0]["utc"], float(limit_mm))]
    steps: list[tuple] = []
    for p in pts:
        tol = p["tolerance_mm"]
        if tol is not None and (not steps or steps[-1][1] != tol):
            steps.append((p["utc"], tol))
    return steps


def _limit_at(steps: list[tuple], when) -> float:
    """The limit in force at ``when`` (the first one before the first step)."""
    value = steps[0][1]
    for start, v in steps:
        if start <= when:
            value = v
    return value


def _time_limits(ax, times: list) -> None:
    """The time axis over ``times`` with a margin, at least a minute either side: checks made within
    one second (a script, a test) would otherwise be spread over years by matplotlib's autoscale."""
    import datetime as dt

    lo, hi = min(times), max(times)
    pad = max((hi - lo) * 0.04, dt.timedelta(minutes=1))
    ax.set_xlim(lo - pad, hi + pad)


def _version_marks(ax, pts: list[dict], versions: Sequence[tuple] | None) -> list:
    """A vertical line labelled ``v<N>`` at each version change within (or after) the checks' times;
    returns their times."""
    if versions is not None:
        marks = sorted((_utc(u, f"version {v}"), int(v)) for u, v in versions)
        first = pts[0]["utc"]
        marks = [(u, v) for u, v in marks if u > first]
    else:
        marks, prev = [], None
        for p in pts:
            if p["version"] is not None and prev is not None and p["version"] != prev:
                marks.append((p["utc"], p["version"]))
            prev = p["version"] if p["version"] is not None else prev
    for u, v in marks:
        ax.axvline(u, color="0.35", ls="-.", lw=1.0, gid=f"version-{v}")
        ax.text(
            u,
            0.98,
            f" v{v}",
            transform=ax.get_xaxis_transform(),
            ha="left",
            va="top",
            fontsize=8,
            color="0.25",
        )
    return [u for u, _ in marks]
