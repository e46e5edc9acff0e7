"""Accuracy statistics of a calibration on pairs: per point residuals (mm) and their summary.

``error_mm`` is the 3-D norm of (dx, dy, dz); for every model but the paper's, z is the object height
given with the pair, so dz = 0 and the error is the in-plane error. Outliers are flagged robustly:
an error above median + 3 × (1.4826 × MAD) of the errors.
"""

from __future__ import annotations

import numpy as np

from .records import PointError, Stats

OUTLIER_SIGMAS = 3.0


def outlier_mask(errors_mm: np.ndarray, sigmas: float = OUTLIER_SIGMAS) -> np.ndarray:
    """True where an error exceeds median + ``sigmas`` robust standard deviations (MAD-based)."""
    e = np.asarray(errors_mm, float)
    if len(e) < 5:
        return np.zeros(len(e), bool)
    med = np.median(e)
    mad = 1.4826 * np.median(np.abs(e - med))
    return e > med + sigmas * max(mad, 1e-9)


def stats_from_residuals(residuals_mm: np.ndarray, ids) -> Stats:
    """Stats from (N, 3) residuals (predicted − actual) and the pair ids."""
    r = np.asarray(residuals_mm, float).reshape(-1, 3)
    e = np.linalg.norm(r, axis=1)
    out = outlier_mask(e)
    pts = tuple(
        PointError(str(i), float(d[0]), float(d[1]), float(d[2]), float(x), bool(o))
        for i, d, x, o in zip(ids, r, e, out, strict=True)
    )
    return Stats(
        n=len(e),
        rms_mm=float(np.sqrt(np.mean(e**2))),
        mean_mm=float(e.mean()),
        max_mm=float(e.max()),
        p95_mm=float(np.percentile(e, 95)),
        points=pts,
    )


def evaluate(calibration, pairs) -> Stats:
    """Stats of ``calibration`` (a Calibration or a model) on ``pairs``, each mapped at its own z."""
    model = getattr(calibration, "model", calibration)
    return stats_from_residuals(model.residuals(pairs.uv_px, pairs.xyz_mm), pairs.ids)
