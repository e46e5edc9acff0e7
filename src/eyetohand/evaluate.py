"""Accuracy statistics of a calibration on pairs: per point residuals (mm) and their summary.

``error_mm`` is the 3-D norm of (dx, dy, dz); for every model but the paper's, z is the object height
given with the pair, so dz = 0 and the error is the in-plane error. Outliers are flagged robustly:
an error above median + 3 × (1.4826 × MAD) of the errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OUTLIER_SIGMAS = 3.0


@dataclass(frozen=True)
class PointError:
    id: str
    dx_mm: float
    dy_mm: float
    dz_mm: float
    error_mm: float
    outlier: bool = False


@dataclass(frozen=True)
class Stats:
    """Summary of point errors (mm): ``n``, ``rms_mm``, ``mean_mm``, ``max_mm``, ``p95_mm``, points."""

    n: int
    rms_mm: float
    mean_mm: float
    max_mm: float
    p95_mm: float
    points: tuple[PointError, ...]

    @property
    def outliers(self) -> list[str]:
        return [p.id for p in self.points if p.outlier]

    def to_dict(self) -> dict:
        return {
            "n": self.n,
            "rms_mm": self.rms_mm,
            "mean_mm": self.mean_mm,
            "max_mm": self.max_mm,
            "p95_mm": self.p95_mm,
            "outliers": self.outliers,
            "points": [
                {
                    "id": p.id,
                    "dx_mm": p.dx_mm,
                    "dy_mm": p.dy_mm,
                    "dz_mm": p.dz_mm,
                    "error_mm": p.error_mm,
                    "outlier": p.outlier,
                }
                for p in self.points
            ],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Stats:
        pts = tuple(
            PointError(p["id"], p["dx_mm"], p["dy_mm"], p.get("dz_mm", 0.0), p["error_mm"],
                       p.get("outlier", False))
            for p in d["points"]
        )
        return cls(d["n"], d["rms_mm"], d["mean_mm"], d["max_mm"], d["p95_mm"], pts)


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
