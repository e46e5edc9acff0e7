"""What a calibration's guarded mapping answers (:class:`Mapped`), and the check of its results."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eyetohand.models import opencv


@dataclass(frozen=True)
class Mapped:
    """Image points mapped by a calibration: per point the pixel, the robot point (mm), the robot
    angle (deg, when image angles were given), the predicted error ``sigma_mm``, whether it lies in
    the calibrated region and how far outside it is (px)."""

    uv_px: np.ndarray
    xyz_mm: np.ndarray
    rz_deg: np.ndarray | None
    sigma_mm: np.ndarray | None
    inside: np.ndarray
    outside_px: np.ndarray

    def records(self) -> list[dict]:
        """One dict per point, full precision: u, v, x, y, z, [rz], sigma_mm, inside."""
        out = []
        for i in range(len(self.uv_px)):
            rec = {
                "u": float(self.uv_px[i, 0]),
                "v": float(self.uv_px[i, 1]),
                "x": float(self.xyz_mm[i, 0]),
                "y": float(self.xyz_mm[i, 1]),
                "z": float(self.xyz_mm[i, 2]),
            }
            if self.rz_deg is not None:
                rec["rz"] = float(self.rz_deg[i])
            rec["sigma_mm"] = None if self.sigma_mm is None else float(self.sigma_mm[i])  # type: ignore[assignment]
            rec["inside"] = bool(self.inside[i])
            out.append(rec)
        return out


_CV_FINITE_MIN = 1 << 12


def all_finite(a: np.ndarray) -> bool:
    """Whether every element of the C-ordered float64 ``a`` is finite: from ``_CV_FINITE_MIN`` elements by
    OpenCV's L1 norm (one SIMD pass: a NaN or ±inf makes it non-finite; an overflow of the sum says
    False, and the caller's exact check then finds every element finite), else by NumPy."""
    if a.size >= _CV_FINITE_MIN:
        cv2 = opencv()
        if cv2 is not None:
            return math.isfinite(cv2.norm(a.reshape(-1), cv2.NORM_L1))
    return bool(np.isfinite(a).all())
