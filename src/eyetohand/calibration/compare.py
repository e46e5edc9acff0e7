"""Every model × solver on the same pairs, scored on check pairs: the paper's Fig. 5 as a table."""

from __future__ import annotations

import time

from eyetohand.calibration.fit import fit_model
from eyetohand.core import InputError
from eyetohand.models import MODELS, HeightRule
from eyetohand.solve import OPTIMIZERS, stats_from_residuals


def compare(pairs, check, *, image_size=None, seed=0, optimizers=OPTIMIZERS, progress=None) -> list[dict]:
    """One row per (model, optimizer): train fitness (eq. 16, mm), check RMS / max (mm), seconds.

    ``progress(done, total, row)``, when given, is called after each combination; a true answer stops
    the comparison there (the rows so far are returned).

    Models are every one that fits the pairs' geometry (single-height or multi-height), including
    those ``auto`` never chooses (the paper's own B), simplest first. A combination that cannot run
    gives a row with its reason.
    """
    models = compared_models(pairs)
    rows: list[dict] = []
    total = len(models) * len(optimizers)
    for cls in models:
        for opt in optimizers:
            if progress is not None and rows and progress(len(rows), total, rows[-1]):
                return rows
            t0 = time.perf_counter()
            row = {"model": cls.name, "optimizer": opt}
            try:
                m, info = fit_model(pairs, cls, opt, image_size=image_size, seed=seed)
            except InputError as exc:
                row["error"] = str(exc)
                rows.append(row)
                continue
            s = stats_from_residuals(m.residuals(check.uv_px, check.xyz_mm), check.ids)
            row.update(
                fitness_mm=info.fitness,
                check_rms_mm=s.rms_mm,
                check_max_mm=s.max_mm,
                check_errors_mm=[p.error_mm for p in s.points],
                seconds=time.perf_counter() - t0,
            )
            rows.append(row)
    if progress is not None and rows:
        progress(len(rows), total, rows[-1])
    return rows


def compared_models(pairs):
    """Every model for the pairs' geometry, simplest first (the paper's B with the one-height ones)."""
    multi = len(pairs.z_levels_mm) > 1
    cands = [
        c
        for c in MODELS.values()
        if c.needs_heights() == multi and not (multi and c.height_rule is HeightRule.COMPUTED)
    ]
    return sorted(cands, key=lambda c: (c.n_unknowns(), c.name))


def format_compare(rows: list[dict]) -> str:
    lines = [
        f"{'model':<18} {'optimizer':<11} {'fitness_mm':>10} {'check_rms_mm':>12} "
        f"{'check_max_mm':>12} {'seconds':>8}"
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['model']:<18} {r['optimizer']:<11} n/a: {r['error']}")
        else:
            lines.append(
                f"{r['model']:<18} {r['optimizer']:<11} {r['fitness_mm']:>10.5f} "
                f"{r['check_rms_mm']:>12.5f} {r['check_max_mm']:>12.5f} {r['seconds']:>8.2f}"
            )
    return "\n".join(lines)
