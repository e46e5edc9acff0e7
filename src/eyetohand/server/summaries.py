"""A calibration's summary for the app (statistics, residual vectors, the expected accuracy) and the
mapping of points for the mapping routes, without HTTP."""

from __future__ import annotations

import numpy as np

from eyetohand.calibration import (
    Calibration,
    as_fitted,
)
from eyetohand.core import InputError, PointPairs
from eyetohand.server.errors import ApiError
from eyetohand.solve import Stats, stats_from_residuals


def split_excluded(pairs: PointPairs, exclude) -> tuple[PointPairs, PointPairs | None]:
    ids = list(pairs.ids)
    for i, pid in enumerate(exclude):
        if pid not in ids:
            raise ApiError(422, f"exclude[{i}]: no pair with id {pid!r}", f"exclude[{i}]")
    mask = np.array([pid in set(exclude) for pid in ids], bool)
    if mask.all():
        raise ApiError(422, "exclude: every pair is excluded; nothing is left to fit", "exclude")
    kept = pairs.subset(~mask)
    return kept, (pairs.subset(mask) if mask.any() else None)


def finite_or_none(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _vectors(cal: Calibration, pairs: PointPairs | None) -> list[dict]:
    """Per pair: the image displacement that its robot-space error corresponds to (px)."""
    if pairs is None:
        return []
    try:
        with np.errstate(all="ignore"):
            back = cal.robot_to_image(pairs.xyz_mm)
            d = pairs.uv_px - back
    except Exception:  # a model without a usable inverse: no arrows, the table still shows errors
        d = np.full((len(pairs), 2), np.nan)
    return [
        {
            "id": pid,
            "u": float(uv[0]),
            "v": float(uv[1]),
            "du_px": finite_or_none(dd[0]),
            "dv_px": finite_or_none(dd[1]),
        }
        for pid, uv, dd in zip(pairs.ids, pairs.uv_px, d, strict=True)
    ]


def _stats(s: Stats | None) -> dict | None:
    return None if s is None else s.to_dict()


def expected_accuracy(cal: Calibration) -> dict | None:
    """The error budget as ``calibrate`` prints it (``line``) and its figures; None without an
    uncertainty record."""
    from eyetohand.calibration import error_budget

    b = error_budget(cal)
    if b is None:
        return None
    return {
        **{k: v if isinstance(v, str) or v is None else finite_or_none(v) for k, v in b.to_dict().items()},
        "line": b.describe(),
    }


def summarize(cal: Calibration, pairs: PointPairs, check: PointPairs | None, excluded=()) -> dict:
    """The fit's summary; ``pairs`` and ``check`` as given (detected), their per-pair errors taken in
    the form the calibration was fitted on (centres corrected when it records a target diameter)."""
    pairs, check = as_fitted(cal, pairs), as_fitted(cal, check)
    kept, out = split_excluded(pairs, list(excluded)) if excluded else (pairs, None)
    ex_stats = None
    if out is not None:
        ex_stats = stats_from_residuals(cal.model.residuals(out.uv_px, out.xyz_mm), out.ids)
    fit = cal.fit
    return {
        "model": cal.model_name,
        "optimizer": fit.optimizer,
        "objective": fit.objective,
        "fitness_mm": finite_or_none(fit.fitness),
        "history": [finite_or_none(h) for h in fit.history],
        "nfev": int(fit.nfev),
        "seconds": float(fit.seconds),
        "seed": fit.seed,
        "uses_z": bool(cal.model.uses_z),
        "plane_z_mm": cal.model.plane_z_mm,
        "circle_diameter_mm": cal.image_points.circle_diameter_mm,
        "n_pairs": len(kept),
        "excluded_ids": list(excluded),
        "notes": list(cal.notes),
        "selection": cal.selection,
        "expected_accuracy": expected_accuracy(cal),
        "train": cal.train.to_dict(),
        "loo": _stats(cal.loo),
        "check": _stats(cal.check),
        "excluded": _stats(ex_stats),
        "vectors": {
            "train": _vectors(cal, kept),
            "check": _vectors(cal, check),
            "excluded": _vectors(cal, out),
        },
    }


def map_points(
    cal: Calibration,
    points: np.ndarray,
    z,
    *,
    angles=None,
    symmetry: int = 1,
    tool_rz_offset_deg=None,
    allow_outside: bool = False,
    sigma: bool = True,
    part_diameter_mm: float | list[float] | None = None,
):
    """(N, 2) px → the calibration's guarded :class:`~eyetohand.calibration.file.Mapped`, with the
    request's ``z`` (None, a number, or one per point), ``angles`` (one per point) and the part's
    diameter (``Calibration.map``'s ``part_diameter_mm``)."""
    if isinstance(z, list):
        if len(z) != len(points):
            raise ApiError(
                422, f"z: {len(z)} heights for {len(points)} points; give one, or one per point", "z"
            )
        z = np.asarray(z, float)
    if isinstance(part_diameter_mm, list) and len(part_diameter_mm) != len(points):
        raise ApiError(
            422,
            f"part_diameter_mm: {len(part_diameter_mm)} diameters for {len(points)} points; "
            "give one, or one per point",
            "part_diameter_mm",
        )
    if angles is not None and len(angles) != len(points):
        raise ApiError(
            422, f"angles: {len(angles)} angles for {len(points)} points; give one per point", "angles"
        )
    try:
        with np.errstate(all="ignore"):
            return cal.map(
                points,
                z,
                angle_deg=angles,
                symmetry=symmetry,
                tool_rz_offset_deg=tool_rz_offset_deg,
                allow_outside=allow_outside,
                with_sigma=sigma,
                part_diameter_mm=part_diameter_mm,
            )
    except InputError as exc:
        raise ApiError(422, str(exc), exc.field_path or "z") from None
