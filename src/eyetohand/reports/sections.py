"""The parts of a calibration's page that the report (:func:`eyetohand.reports.report.build_report`)
and the paper reproduction (:func:`eyetohand.reports.demo.build_demo_report`) both show: the
statistics, the per-point residuals, the fit and the parameters, each added to a
:class:`~eyetohand.reports.html.Document`.

Units: robot errors, fitness and statistics in mm, image positions in px.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from contextlib import nullcontext

import numpy as np

from eyetohand.calibration import Calibration
from eyetohand.core import PointPairs
from eyetohand.reports.html import Document, escape, mm
from eyetohand.solve import Stats, find_objective

__all__ = [
    "LONG_TABLE_ROWS",
    "fit_table",
    "image_jacobian",
    "params_section",
    "points_table",
    "selection_table",
    "stats_table",
]

#: a per-point table longer than this is folded away (a ``<details>``)
LONG_TABLE_ROWS = 50


def image_jacobian(model, uv_px: np.ndarray, z_mm: np.ndarray, step_px: float = 0.5) -> np.ndarray:
    """(N, 2, 2) derivative of robot (x, y) [mm] with respect to image (u, v) [px], central differences:
    turns a robot-space residual into its image direction for the residual-vector plots."""
    cols = []
    for k in range(2):
        dv = np.zeros(2)
        dv[k] = step_px
        plus = model.image_to_robot(uv_px + dv, z_mm)[:, :2]
        minus = model.image_to_robot(uv_px - dv, z_mm)[:, :2]
        cols.append((plus - minus) / (2 * step_px))
    return np.stack(cols, axis=2)


def stats_table(doc: Document, sets: list[tuple[str, Stats | None, str]]) -> None:
    """One row of error statistics per ``(label, stats, what it is)`` (a None ``stats`` is left out),
    with the definitions of an error and an outlier under it; nothing when all are None."""
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


def points_table(doc: Document, s: Stats, pairs: PointPairs | None, loo: Stats | None = None) -> None:
    """Per point residuals; positions from ``pairs`` when given (z only when it varies), the
    leave-one-out error from ``loo`` when given. Folded away when longer than :data:`LONG_TABLE_ROWS`."""
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
    n_out = sum(1 for p in s.points if p.outlier)
    folded = (
        doc.details(f"{len(rows)} points ({n_out} flagged as outliers): show the table")
        if len(rows) > LONG_TABLE_ROWS
        else nullcontext()
    )
    with folded:
        doc.table(header, rows, row_classes=classes)


def params_section(doc: Document, cal: Calibration) -> None:
    """The model, its parameters and its constants (the normalisation the parameters are in)."""
    m = cal.model
    d = m.to_dict()
    doc.p(f"model '{m.name}': {type(m).summary}" if type(m).summary else f"model '{m.name}'")
    rows = [[f"p[{i}]", f"{v:.12g}"] for i, v in enumerate(d["params"])]
    doc.table(["parameter", "value"], rows)
    meta = d.get("meta") or {}
    if meta:
        doc.h3("Model constants")
        parts = ["<table><thead><tr><th>name</th><th>value</th></tr></thead><tbody>"]
        for k, v in meta.items():
            text = json.dumps(v, indent=None) if isinstance(v, (list, dict)) else str(v)
            if isinstance(v, list) and v and isinstance(v[0], list):
                text = "\n".join(json.dumps(r) for r in v)
            parts.append(f"<tr><td>{escape(k)}</td><td><pre>{escape(text)}</pre></td></tr>")
        parts.append("</tbody></table>")
        doc.add("".join(parts))
    doc.p(
        "Parameters are in the model's normalised coordinates (see the constants); the calibration "
        "JSON holds them bit-exact.",
        "muted",
    )


def fitness_unit(objective: str) -> str:
    """The unit of a fit's fitness on the objective called ``objective`` (mm for one this version
    does not know)."""
    obj = find_objective(objective)
    return "mm" if obj is None else obj.fitness_unit


def fit_table(doc: Document, cal: Calibration) -> None:
    """The fit as a key–value table: model, optimizer, fitness, effort, seed, provenance."""
    f = cal.fit
    unit = fitness_unit(f.objective)
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


def selection_table(doc: Document, sel: Mapping) -> None:
    """An auto calibration's choice of model (``Calibration.selection``): the candidates, their
    held-out errors and why each was not chosen."""
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
