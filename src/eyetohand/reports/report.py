"""The HTML report of a calibration (``eyetohand report``); its building blocks also make the paper
reproduction's page (:func:`eyetohand.reports.demo.write_demo_report`).

A report is a folder with ``index.html`` and the PNG plots. ``index.html`` is self-contained: inline
CSS, the plots embedded as base64, so the one file can be mailed or archived alone; the PNGs are
written beside it for reuse. Everything is computed in memory first and then written file by file
atomically, ``index.html`` last: a run that fails leaves an earlier report as it was.

Units everywhere: robot errors, fitness and statistics in mm, image positions in px.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from eyetohand._version import __version__
from eyetohand.calibration import Calibration
from eyetohand.core import InputError, PointPairs, atomic_write_bytes, atomic_write_text
from eyetohand.solve import Stats, evaluate

__all__ = ["build_report", "write_report"]

PNG_NAMES = (
    "convergence.png",
    "check_errors.png",
    "train_errors.png",
    "residual_vectors.png",
    "point_errors.png",
)


# ------------------------------------------------------------------ small helpers


def _e(text) -> str:
    return html.escape(str(text), quote=True)


def mm(value, digits: int = 4) -> str:
    """A millimetre value as the tables print it (4 decimals: 0.1 µm); '—' for a missing value."""
    if value is None:
        return "—"
    v = float(value)
    if not np.isfinite(v):
        return "—"
    text = f"{v:.{digits}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # no "-0.0000"


_PLACEHOLDERS = ("", "—", "n/a", "illegible")


def _is_numeric(cell: str) -> bool:
    """True for a formatted number such as '0.0269', '-3', '+12 %', '16'."""
    text = str(cell).strip().removesuffix("%").strip()
    try:
        float(text)
    except ValueError:
        return False
    return True


def _png(ax) -> bytes:
    """The figure of ``ax`` as PNG bytes (rendered in memory)."""
    buf = io.BytesIO()
    ax.figure.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


def _fitness_label(objective: str) -> str:
    return {
        "l2": "best fitness, eq. (16): ‖residuals‖₂ [mm]",
        "linf": "best fitness: largest point error [mm]",
        "huber": "best fitness: Σ Huber loss [mm²]",
    }.get(objective, "best fitness [mm]")


def _jacobian(model, uv_px: np.ndarray, z_mm: np.ndarray, step_px: float = 0.5) -> np.ndarray:
    """(N, 2, 2) derivative of robot (x, y) [mm] with respect to image (u, v) [px], central differences."""
    cols = []
    for k in range(2):
        dv = np.zeros(2)
        dv[k] = step_px
        plus = model.image_to_robot(uv_px + dv, z_mm)[:, :2]
        minus = model.image_to_robot(uv_px - dv, z_mm)[:, :2]
        cols.append((plus - minus) / (2 * step_px))
    return np.stack(cols, axis=2)


class _Doc:
    """An HTML document being assembled, with the PNGs it embeds."""

    def __init__(self, title: str):
        self.title = title
        self.parts: list[str] = []
        self.files: dict[str, bytes] = {}

    def add(self, fragment: str) -> None:
        self.parts.append(fragment)

    def h2(self, text: str, anchor: str) -> None:
        self.add(f'<h2 id="{_e(anchor)}">{_e(text)}</h2>')

    def p(self, text: str, cls: str = "") -> None:
        c = f' class="{cls}"' if cls else ""
        self.add(f"<p{c}>{_e(text)}</p>")

    def figure(self, name: str, ax, caption: str) -> None:
        data = _png(ax)
        self.files[name] = data
        b64 = base64.b64encode(data).decode("ascii")
        self.add(
            f'<figure><img src="data:image/png;base64,{b64}" alt="{_e(caption)}">'
            f'<figcaption>{_e(caption)} <span class="muted">(also saved as {_e(name)})</span>'
            "</figcaption></figure>"
        )

    def table(
        self, header: list[str] | None, rows: list[list[str]], *, row_classes: list[str] | None = None
    ) -> None:
        """A table of already formatted cells. Numeric cells (and their columns' headers) are right
        aligned in tabular figures; ``header=None`` gives a key–value table without a header row."""
        ncol = max([len(header or [])] + [len(r) for r in rows])
        numeric_col = [
            all(_is_numeric(r[i]) for r in rows if i < len(r) and r[i] not in _PLACEHOLDERS)
            and any(i < len(r) and r[i] not in _PLACEHOLDERS for r in rows)
            for i in range(ncol)
        ]
        out = ['<div class="scroll"><table>']
        if header:
            out.append("<thead><tr>")
            for i, h in enumerate(header):
                out.append(f'<th class="{"num" if numeric_col[i] else ""}">{_e(h)}</th>')
            out.append("</tr></thead>")
        out.append("<tbody>")
        for r_i, row in enumerate(rows):
            rc = row_classes[r_i] if row_classes else ""
            out.append(f'<tr class="{rc}">' if rc else "<tr>")
            for i, cell in enumerate(row):
                cls = "num" if numeric_col[i] else ("key" if header is None and i == 0 else "")
                out.append(f'<td class="{cls}">{_e(cell)}</td>' if cls else f"<td>{_e(cell)}</td>")
            out.append("</tr>")
        out.append("</tbody></table></div>")
        self.add("".join(out))

    def render(self, subtitle: str = "") -> str:
        now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="generator" content="eyetohand {_e(__version__)}">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{_e(self.title)}</title><style>{CSS}</style></head><body><main>"
            f'<header><h1>{_e(self.title)}</h1><p class="muted">{_e(subtitle)}'
            f"{' · ' if subtitle else ''}generated {_e(now)} by eyetohand {_e(__version__)} · "
            "units: robot mm, image px</p></header>\n" + "\n".join(self.parts) + "\n</main></body></html>\n"
        )


CSS = """
:root { --fg:#1b1f24; --muted:#5b6570; --line:#d6dbe1; --zebra:#f5f7f9; --accent:#0072B2; --warn:#b35900; }
* { box-sizing: border-box; }
body { margin:0; color:var(--fg); background:#fff;
  font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1080px; margin: 0 auto; padding: 24px 28px 60px; }
header { border-bottom: 2px solid var(--accent); margin-bottom: 18px; }
h1 { font-size: 22px; margin: 0 0 4px; }
h2 { font-size: 17px; margin: 30px 0 8px; padding-bottom: 3px; border-bottom: 1px solid var(--line); }
h3 { font-size: 14.5px; margin: 18px 0 6px; }
p { margin: 6px 0; }
.muted { color: var(--muted); font-size: 12.5px; }
.warn { color: var(--warn); }
.cards { display: flex; flex-wrap: wrap; gap: 12px; margin: 10px 0 4px; }
.card { border: 1px solid var(--line); border-radius: 6px; padding: 8px 14px; min-width: 150px; }
.card .k { color: var(--muted); font-size: 12px; }
.card .v { font-size: 20px; font-weight: 600; font-variant-numeric: tabular-nums; }
.card .u { font-size: 12px; color: var(--muted); margin-left: 3px; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 13px; }
th, td { padding: 3px 10px; border-bottom: 1px solid var(--line); text-align: left; vertical-align: top; }
th { background: #eef1f4; font-weight: 600; vertical-align: bottom; }
th.num { text-align: right; }
td.num { text-align: right; font-variant-numeric: tabular-nums;
  font-family: ui-monospace, "SFMono-Regular", Menlo, Consolas, monospace; }
.scroll { overflow-x: auto; max-width: 100%; }
tbody tr:nth-child(even) { background: var(--zebra); }
td.key { color: var(--muted); white-space: nowrap; padding-right: 18px; }
tr.outlier td { background: #fff1e0; }
tr.summary td { font-weight: 600; border-top: 2px solid var(--line); }
figure { margin: 12px 0 18px; }
figure img { max-width: 100%; height: auto; border: 1px solid var(--line); }
figcaption { font-size: 12.5px; color: var(--muted); margin-top: 3px; }
ul.notes { margin: 4px 0; padding-left: 20px; }
pre { background: var(--zebra); padding: 6px 8px; overflow-x: auto; font-size: 12px; margin: 2px 0; }
details { margin: 8px 0; }
summary { cursor: pointer; font-weight: 600; }
nav a { margin-right: 12px; font-size: 13px; }
@media print { details { display: block; } main { padding: 0; } }
"""


def _cards(doc: _Doc, items: list[tuple[str, str, str]]) -> None:
    parts = ['<div class="cards">']
    for k, v, u in items:
        parts.append(
            f'<div class="card"><div class="k">{_e(k)}</div><div class="v">{_e(v)}'
            f'<span class="u">{_e(u)}</span></div></div>'
        )
    parts.append("</div>")
    doc.add("".join(parts))


def _stats_table(doc: _Doc, sets: list[tuple[str, Stats | None, str]]) -> None:
    rows, classes = [], []
    for label, s, what in sets:
        if s is None:
            continue
        outl = ("id " + ", ".join(s.outliers)) if s.outliers else "none"
        rows.append([label, str(s.n), mm(s.rms_mm), mm(s.mean_mm), mm(s.p95_mm), mm(s.max_mm), outl, what])
        classes.append("")
    if rows:
        doc.table(
            ["set", "n", "RMS [mm]", "mean [mm]", "p95 [mm]", "max [mm]", "outliers", "what it is"],
            rows,
            row_classes=classes,
        )
        doc.p(
            "Error of a point = ‖predicted − actual‖ in robot space. Outlier: error above median + "
            "3 robust σ (1.4826 × MAD) of the set's errors.",
            "muted",
        )


def _positions_by_id(pairs: PointPairs | None) -> dict[str, tuple[float, float, float]]:
    """id → (u px, v px, z mm) of the pairs, empty without pairs."""
    if pairs is None:
        return {}
    return {
        i: (float(uv[0]), float(uv[1]), float(xyz[2]))
        for i, uv, xyz in zip(pairs.ids, pairs.uv_px, pairs.xyz_mm, strict=True)
    }


LONG_TABLE_ROWS = 50


def _points_table(doc: _Doc, s: Stats, pairs: PointPairs | None, loo: Stats | None = None) -> None:
    """Per point residuals; positions from ``pairs`` when given (z only when it varies)."""
    pos = _positions_by_id(pairs)
    show_z = pairs is not None and bool(pos) and len(pairs.z_levels_mm) > 1
    loo_e = {p.id: p.error_mm for p in loo.points} if loo else {}
    show_dz = any(abs(p.dz_mm) > 0 for p in s.points)
    header = ["id"] + (["u [px]", "v [px]"] if pos else []) + (["z [mm]"] if show_z else [])
    header += ["dx [mm]", "dy [mm]"] + (["dz [mm]"] if show_dz else []) + ["‖Δ‖ [mm]"]
    header += (["leave-one-out ‖Δ‖ [mm]"] if loo else []) + ["flag"]
    rows, classes = [], []
    for p in s.points:
        row = [p.id]
        if pos:
            u, v, z = pos.get(p.id, (float("nan"),) * 3)
            row += [f"{u:.2f}" if np.isfinite(u) else "—", f"{v:.2f}" if np.isfinite(v) else "—"]
            if show_z:
                row.append(f"{z:g}" if np.isfinite(z) else "—")
        row += [mm(p.dx_mm), mm(p.dy_mm)] + ([mm(p.dz_mm)] if show_dz else []) + [mm(p.error_mm)]
        if loo:
            row.append(mm(loo_e.get(p.id)))
        row.append("outlier" if p.outlier else "")
        rows.append(row)
        classes.append("outlier" if p.outlier else "")
    long = len(rows) > LONG_TABLE_ROWS
    if long:
        n_out = sum(1 for p in s.points if p.outlier)
        doc.add(
            f"<details><summary>{len(rows)} points ({n_out} flagged as outliers): show the table</summary>"
        )
    doc.table(header, rows, row_classes=classes)
    if long:
        doc.add("</details>")


def _params_section(doc: _Doc, cal: Calibration) -> None:
    m = cal.model
    d = m.to_dict()
    doc.p(f"model '{m.name}': {type(m).summary}" if type(m).summary else f"model '{m.name}'")
    rows = [[f"p[{i}]", f"{v:.12g}"] for i, v in enumerate(d["params"])]
    doc.table(["parameter", "value"], rows)
    meta = d.get("meta") or {}
    if meta:
        doc.add("<h3>Model constants</h3>")
        parts = ["<table><thead><tr><th>name</th><th>value</th></tr></thead><tbody>"]
        for k, v in meta.items():
            text = json.dumps(v, indent=None) if isinstance(v, (list, dict)) else str(v)
            if isinstance(v, list) and v and isinstance(v[0], list):
                text = "\n".join(json.dumps(r) for r in v)
            parts.append(f"<tr><td>{_e(k)}</td><td><pre>{_e(text)}</pre></td></tr>")
        parts.append("</tbody></table>")
        doc.add("".join(parts))
    doc.p(
        "Parameters are in the model's normalised coordinates (see the constants); the calibration "
        "JSON holds them bit-exact.",
        "muted",
    )


def _fit_table(doc: _Doc, cal: Calibration) -> None:
    f = cal.fit
    unit = "mm²" if f.objective == "huber" else "mm"
    rows = [
        ["model", cal.model_name],
        ["optimizer", f.optimizer],
        ["objective", f.objective],
        ["fitness (training, objective value)", f"{f.fitness:.6f} {unit}"],
        ["iterations / function evaluations", f"{f.nit} / {f.nfev}"],
        ["solver time", f"{f.seconds:.2f} s"],
        ["seed", "—" if f.seed is None else str(f.seed)],
        ["solver message", f.message or "—"],
        ["image size", f"{cal.image_size[0]} × {cal.image_size[1]} px" if cal.image_size else "not given"],
        ["training data SHA-256", cal.data_sha256 or "—"],
        ["created (UTC)", cal.created_utc or "—"],
        ["eyetohand version", cal.version or "—"],
    ]
    for k, v in f.extra.items():
        rows.append([k, f"{v:.6g}" if isinstance(v, float) else str(v)])
    doc.table(None, rows)


def _selection_section(doc: _Doc, sel: Mapping) -> None:
    doc.p(
        f"auto selection chose '{sel.get('chosen')}': {sel.get('reason', '')}"
        + (f" ({sel['method']} cross-validation)" if sel.get("method") else "")
    )
    rows = []
    for r in sel.get("candidates", []):
        rows.append(
            [
                str(r.get("model")),
                str(r.get("unknowns", "")),
                mm(r.get("cv_rms_mm")),
                mm(r.get("cv_max_mm")),
                "chosen" if r.get("model") == sel.get("chosen") else ("yes" if r.get("considered") else "no"),
                r.get("why", ""),
            ]
        )
    doc.table(
        ["candidate", "unknowns", "held-out RMS [mm]", "held-out max [mm]", "considered", "why not"], rows
    )


def _notes(doc: _Doc, notes: list[str], warn: bool = False) -> None:
    if not notes:
        doc.p("none", "muted")
        return
    cls = ' class="warn"' if warn else ""
    doc.add('<ul class="notes">' + "".join(f"<li{cls}>{_e(n)}</li>" for n in notes) + "</ul>")


# ------------------------------------------------------------------ one calibration


def build_report(
    calibration: Calibration,
    check_pairs: PointPairs | None = None,
    train_pairs: PointPairs | None = None,
    extra: Mapping | None = None,
    *,
    title: str | None = None,
) -> tuple[str, dict[str, bytes]]:
    """The report of one calibration, in memory: ``(index.html text, {png name: bytes})``.

    ``check_pairs``: pairs not used for fitting; the check statistics are recomputed on them (and
    replace any stored ones). ``train_pairs``: the pairs the calibration was fitted on, for the image
    positions of the residual-vector plot; if their SHA-256 differs from the calibration's, they
    are shown as "given pairs" with a warning. ``extra``: more name → value rows for the header.
    """
    from eyetohand.reports import plots

    cal = calibration
    if not isinstance(cal, Calibration):
        raise InputError(f"write_report needs a Calibration, got {type(cal).__name__}")
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
    doc = _Doc(title or f"Calibration report — {cal.model_name} + {cal.fit.optimizer}")
    doc.add(
        '<nav><a href="#summary">summary</a><a href="#accuracy">accuracy</a><a href="#plots">plots</a>'
        '<a href="#points">per point</a><a href="#fit">fit</a><a href="#params">parameters</a></nav>'
    )

    # summary
    doc.h2("Summary", "summary")
    cards = [
        ("model", cal.model_name, ""),
        ("optimizer", cal.fit.optimizer, ""),
        ("training fitness", f"{cal.fit.fitness:.5f}", "mm²" if cal.fit.objective == "huber" else "mm"),
    ]
    if check is not None:
        cards += [("check RMS", mm(check.rms_mm), "mm"), ("check max", mm(check.max_mm), "mm")]
    elif cal.loo is not None:
        cards += [
            ("leave-one-out RMS", mm(cal.loo.rms_mm), "mm"),
            ("leave-one-out max", mm(cal.loo.max_mm), "mm"),
        ]
    cards.append((f"{train_label} RMS", mm(train.rms_mm), "mm"))
    _cards(doc, cards)
    if extra:
        doc.table(None, [[str(k), str(v)] for k, v in extra.items()])
    if check is None:
        doc.p(
            "No check pairs: accuracy on unseen points is estimated by leave-one-out only. "
            "Give check pairs (--check) to measure it.",
            "warn",
        )
    if warnings:
        _notes(doc, warnings, warn=True)

    doc.h2("Accuracy", "accuracy")
    _stats_table(
        doc,
        [
            (train_label, train, train_what),
            ("leave-one-out", cal.loo, "each training pair predicted by a fit without it"),
            ("check", check, "pairs not used for fitting"),
        ],
    )
    if cal.selection:
        doc.add("<h3>Model selection</h3>")
        _selection_section(doc, cal.selection)
    doc.add("<h3>Notes</h3>")
    _notes(doc, notes)

    # plots
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
    if check is not None:
        label = f"{cal.model_name} + {cal.fit.optimizer}"
        ax = plots.plot_point_errors(
            {label: [p.error_mm for p in check.points]},
            [p.id for p in check.points],
            title="Error per check point",
        )
        doc.figure("check_errors.png", ax, "Error norm of each check point, robot space.")
    tr = {f"{train_label} (fit residual)": [p.error_mm for p in train.points]}
    if cal.loo is not None and train_label == "train":
        tr["leave-one-out"] = [p.error_mm for p in cal.loo.points]
    ax = plots.plot_point_errors(
        tr, [p.id for p in train.points], xlabel="training point id", title="Error per training point"
    )
    doc.figure(
        "train_errors.png",
        ax,
        "Fit residual of each training point and, when computed, its "
        "leave-one-out error (the point predicted by a fit without it).",
    )
    _residual_plot(doc, cal, [(train_label, train_pairs), ("check", check_pairs)])
    _sigma_map(doc, cal)

    doc.h2("Per point residuals", "points")
    if check is not None:
        doc.add("<h3>Check points</h3>")
        _points_table(doc, check, check_pairs)
    doc.add(f"<h3>{_e('Training points' if train_label == 'train' else 'Given pairs')}</h3>")
    _points_table(doc, train, train_pairs, cal.loo if train_label == "train" else None)

    doc.h2("Fit", "fit")
    _fit_table(doc, cal)
    doc.h2("Parameters", "params")
    _params_section(doc, cal)
    return doc.render(), doc.files


def _residual_plot(
    doc: _Doc, cal: Calibration, sets: list[tuple[str, PointPairs | None]], name: str = "residual_vectors.png"
) -> None:
    """One quiver plot of the given pair sets (same scale); a note when no positions are known."""
    from eyetohand.reports import plots

    given = [(label, p) for label, p in sets if p is not None]
    if not given:
        doc.p(
            "Residual vectors: not drawn. The calibration file stores each point's error but not "
            "its image position; give the pairs (--pairs TRAIN and/or --check CHECK) to draw them.",
            "muted",
        )
        return
    data: list[tuple[str, PointPairs, np.ndarray, np.ndarray | None]] = []
    for label, pairs in given:
        res = cal.model.residuals(pairs.uv_px, pairs.xyz_mm)
        jac: np.ndarray | None
        try:
            jac = _jacobian(cal.model, pairs.uv_px, pairs.xyz_mm[:, 2])
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


SIGMA_GRID = 120


def _sigma_map(doc: _Doc, cal: Calibration) -> None:
    """sigma_mm over the image with the calibrated region outlined: where it can be trusted."""
    from eyetohand.models import HeightRule
    from eyetohand.reports import plots

    if cal.region is None or cal.uncertainty is None:
        doc.p(
            "No sigma map: this calibration records no calibrated region or uncertainty (a pre-0.2 file).",
            "muted",
        )
        return
    hull = cal.region.hull_px
    if cal.image_size is not None:
        w, h = cal.image_size
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
    zq = np.zeros(len(uv)) if cal.model.height_rule is HeightRule.COMPUTED else np.full(len(uv), z)
    with np.errstate(all="ignore"):
        s = cal.uncertainty.sigma_mm(cal.model, uv, zq).reshape(n_v, n_u)
    pts = cal.fitted_pairs.uv_px if cal.fitted_pairs is not None else None
    ax = plots.plot_sigma_map(
        u,
        v,
        s,
        hull,
        points_px=pts,
        image_size=cal.image_size,
        margin_hull_px=_grown(hull, cal.region.margin_px),
    )
    inner = s.ravel()[cal.region.outside_px(uv) <= cal.region.margin_px]
    rng = f"{np.nanmin(inner):.4f}–{np.nanmax(inner):.4f} mm" if inner.size else "–"
    doc.figure(
        "sigma_map.png",
        ax,
        f"Where this calibration can be trusted: the predicted error "
        f"sigma_mm of a mapped point ({where}), the calibrated region (training hull) in white "
        f"and its margin dashed — mappings beyond it are refused. Inside: {rng}.",
    )


def _grown(hull: np.ndarray, margin_px: float) -> np.ndarray:
    """The hull's outline moved out by ``margin_px`` (vertices pushed along their bisectors)."""
    c = hull.mean(axis=0)
    d = hull - c
    return hull + margin_px * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


def _write_all(out_dir: str | os.PathLike, html_text: str, files: Mapping[str, bytes]) -> Path:
    """Write the PNGs, then index.html, each atomically; drop our stale PNGs of an earlier run."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            atomic_write_bytes(out / name, data)
        index = atomic_write_text(out / "index.html", html_text)
        for name in PNG_NAMES:
            if name not in files and (out / name).is_file():
                (out / name).unlink()
    except OSError as exc:
        raise InputError(f"{out}: cannot write the report ({exc.strerror or exc})") from None
    return index


def write_report(
    out_dir: str | os.PathLike,
    calibration: Calibration,
    check_pairs: PointPairs | None = None,
    train_pairs: PointPairs | None = None,
    extra: Mapping | None = None,
) -> Path:
    """Write the report of ``calibration`` into ``out_dir``; returns the path of ``index.html``.

    See :func:`build_report` for the arguments. All plots and the HTML are built in memory before
    anything is written, so a failure leaves an earlier report in ``out_dir`` unchanged.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    text, files = build_report(calibration, check_pairs, train_pairs, extra)
    return _write_all(out, text, files)
