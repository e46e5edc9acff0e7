"""The records a calibration is made of: how it was fitted, how good it is, the tool offset.

Plain frozen data with ``to_dict``/``from_dict``; no behaviour that needs the models or the fitter, so
every layer can import them (:mod:`eyetohand.calibration.file` bundles them with the model).
"""

from __future__ import annotations

from dataclasses import dataclass, field


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
            PointError(
                p["id"], p["dx_mm"], p["dy_mm"], p.get("dz_mm", 0.0), p["error_mm"], p.get("outlier", False)
            )
            for p in d["points"]
        )
        return cls(d["n"], d["rms_mm"], d["mean_mm"], d["max_mm"], d["p95_mm"], pts)


@dataclass(frozen=True, kw_only=True)
class FitInfo:
    """How a model was refined: the final objective value (in its objective's unit), its history,
    the cost. Built by keywords."""

    optimizer: str
    objective: str
    fitness: float
    history: tuple[float, ...] = ()
    nfev: int = 0
    nit: int = 0
    seconds: float = 0.0
    seed: int | None = None
    message: str = ""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "optimizer": self.optimizer,
            "objective": self.objective,
            "fitness": self.fitness,
            "history": list(self.history),
            "nfev": self.nfev,
            "nit": self.nit,
            "seconds": self.seconds,
            "seed": self.seed,
            "message": self.message,
            **self.extra,
        }


@dataclass(frozen=True)
class TcpOffset:
    """Estimated offset ``offset_mm`` (ox, oy) in the tool frame, its standard error (mm, from the
    joint fit's Jacobian and residuals), the model used, and how many pairs were at other angles."""

    offset_mm: tuple[float, float]
    std_mm: tuple[float, float]
    model: str
    reference_angle_deg: float
    n_turned: int
    n_pairs: int
    rms_mm: float

    def to_dict(self) -> dict:
        return {
            "offset_mm": list(self.offset_mm),
            "std_mm": list(self.std_mm),
            "model": self.model,
            "reference_angle_deg": self.reference_angle_deg,
            "n_turned": self.n_turned,
            "n_pairs": self.n_pairs,
            "rms_mm": self.rms_mm,
        }

    @classmethod
    def from_dict(cls, d: dict) -> TcpOffset:
        return cls(
            tuple(d["offset_mm"]),
            tuple(d["std_mm"]),
            d["model"],
            d["reference_angle_deg"],
            d["n_turned"],
            d["n_pairs"],
            d["rms_mm"],
        )
