"""Is this accuracy normal? The error budget of a calibration beside its measured check error.

A check point's error (mapped − measured, mm) has two parts: the map's own error at that pixel
(the fit's, ``tr(J C Jᵀ)`` from :mod:`eyetohand.solve.uncertainty`) and the check measurement's own
noise. The training residuals give the noise per coordinate, ``s`` (mm): the detector's pixel noise
times the local scale (mm/px), the robot's repeatability and the target's (or a touch-off's) error,
together — the residuals cannot tell them apart, so the budget states ``s`` both ways: as pixels at
the local scale if it all came from the detector, as mm if it all came from the robot. The expected
check RMS is the RMS over the check points of ``sqrt(fit² + c·s²)`` (``sigma_mm``), or of the fit
part alone for check points that carry no measurement noise (a simulation's are exact). A plate's
calibration adds the error its touches put on every point alike (the placement's rigid fit,
:meth:`PlateRecord.placement_variance_mm2`, as ``sigma_mm`` does): part of the map's own error,
stated apart. Measured
check RMS well above both says something the budget does not hold: a mix-up, a moved camera, a
model that does not fit (``eyetohand crossval``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eyetohand.calibration.file import Calibration
from eyetohand.models import HeightRule


@dataclass(frozen=True)
class ErrorBudget:
    noise_mm: float  # per coordinate, from the training residuals
    n_coords: int
    scale_mm_per_px: float
    fit_rms_mm: float  # the map's own error, RMS over the points the budget is for
    where: str  # "check points" or "training pixels"
    measured_rms_mm: float | None
    touches_rms_mm: float = 0.0  # a plate's placement by its touches, RMS over the same points

    @property
    def map_rms_mm(self) -> float:
        """The map's own error: the fit's ⊕ the touches' (a plate's)."""
        return float(np.hypot(self.fit_rms_mm, self.touches_rms_mm))

    @property
    def measurement_mm(self) -> float:
        """RMS distance a fresh measurement's own noise adds: ``sqrt(c)·s``."""
        return float(np.sqrt(self.n_coords) * self.noise_mm)

    @property
    def expected_rms_mm(self) -> float:
        return float(np.hypot(self.map_rms_mm, self.measurement_mm))

    @property
    def noise_px(self) -> float:
        return self.noise_mm / self.scale_mm_per_px if self.scale_mm_per_px > 0 else float("nan")

    def to_dict(self) -> dict:
        return {
            "noise_mm": self.noise_mm,
            "noise_px_equivalent": self.noise_px,
            "scale_mm_per_px": self.scale_mm_per_px,
            "fit_rms_mm": self.fit_rms_mm,
            "touches_rms_mm": self.touches_rms_mm,
            "measurement_rms_mm": self.measurement_mm,
            "expected_rms_mm": self.expected_rms_mm,
            "measured_rms_mm": self.measured_rms_mm,
            "where": self.where,
        }

    def describe(self) -> str:
        touches = (
            f" ⊕ the plate's placement by the touches {self.touches_rms_mm:.4f} mm"
            if self.touches_rms_mm
            else ""
        )
        head = (
            f"expected accuracy at the {self.where}: RMS {self.expected_rms_mm:.4f} mm = the fit's own "
            f"{self.fit_rms_mm:.4f} mm{touches} ⊕ a measurement's noise {self.measurement_mm:.4f} mm "
            f"(residual noise {self.noise_mm:.4f} mm per axis: {self.noise_px:.3g} px at "
            f"{self.scale_mm_per_px:.4g} mm/px if all from detection, or robot repeatability and target "
            "noise together)"
        )
        if self.measured_rms_mm is None:
            return head
        return (
            f"{head}; measured check RMS {self.measured_rms_mm:.4f} mm "
            f"({self.measured_rms_mm / max(self.expected_rms_mm, 1e-12):.2f}× expected; exact check points "
            f"would show the {'map' if self.touches_rms_mm else 'fit'}'s own {self.map_rms_mm:.4f} mm)"
        )


def error_budget(cal: Calibration) -> ErrorBudget | None:
    """The budget at the check points the calibration carries (else at its training pixels); None
    without an uncertainty record."""
    unc = cal.uncertainty
    if unc is None:
        return None
    if cal.check_pairs is not None:
        uv, xyz, where = cal.check_pairs.uv_px, cal.check_pairs.xyz_mm, "check points"
    elif cal.pairs is not None:
        uv, xyz, where = cal.pairs.uv_px, cal.pairs.xyz_mm, "training pixels"
    else:
        return None
    zs = xyz[:, 2] if cal.model.height_rule is not HeightRule.COMPUTED else np.zeros(len(uv))
    sigma = unc.sigma_mm(cal.model, uv, zs)
    fit2 = np.maximum(sigma**2 - unc.n_coords * unc.noise_mm**2, 0.0)
    touch2 = np.zeros(1) if cal.plate is None else cal.plate.placement_variance_mm2(xyz, unc.n_coords)
    return ErrorBudget(
        unc.noise_mm,
        unc.n_coords,
        cal.local_frame().scale_mm_per_px,
        float(np.sqrt(np.mean(fit2))),
        where,
        None if cal.check is None else cal.check.rms_mm,
        float(np.sqrt(np.mean(touch2))),
    )
