"""Re-check a deployed calibration with a few freshly measured pairs: per-point errors, whether the
camera moved (shift, rotation, scale) since calibration, pass/fail against a tolerance, and a history.

The errors are ``predicted − measured`` robot points (mm), each pair mapped at its own z through the
guarded map. A camera bump or a warm-up drift moves all points together; random error does not. So
a 2-D similarity is fitted to the errors around the measured points' centroid::

    e_i = t + θ · R90 (q_i − c) + s · (q_i − c)

(``t`` the shift in mm, ``θ`` the rotation in rad, ``s`` the scale change as a fraction), weighted by
each point's predicted error: per coordinate variance ``sigma_mm² / 2`` from the calibration's own
uncertainty (:mod:`eyetohand.uncertainty`, the fit's error at that pixel plus its measured noise).
Under "nothing moved" the weighted estimate's quadratic form ``β̂ᵀ (AᵀWA) β̂`` is chi-square with 4
degrees of freedom; the drift is significant when it exceeds the 0.1 % point (18.47), and each
component is named when its own z-score exceeds 3.29 (two-sided 0.1 %). The image shift in pixels
is the shift in mm through the inverse local Jacobian (``J⁻¹ t``: the pixels the scene appears moved by).

Pass/fail is against the tolerance: every point's error ≤ ``tolerance_mm``. A history entry (JSON
lines beside the file, or the server's table) records each run so that drift shows as a trend.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .calibration import Calibration
from .errors import InputError
from .models import HeightRule
from .orientation import local_jacobian
from .pairs import PointPairs

CHI2_4_P001 = 18.467
"""The 0.1 % point of chi-square with 4 degrees of freedom: the drift test's threshold."""
Z_P001 = 3.2905
"""The two-sided 0.1 % point of the standard normal: a component is named above it."""
MIN_PAIRS = 3
HISTORY_SUFFIX = ".history.jsonl"


@dataclass(frozen=True)
class Drift:
    """The similarity between predicted and measured points, and whether it is significant."""

    shift_mm: tuple[float, float]
    shift_px: tuple[float, float]
    rotation_deg: float
    scale_change: float  # fraction: 0.001 is 0.1 % larger predicted than measured
    chi2: float
    threshold: float
    significant: bool
    named: tuple[str, ...]  # "shift", "rotation", "scale": the components beyond Z_P001
    z_scores: dict

    def to_dict(self) -> dict:
        return {
            "shift_mm": list(self.shift_mm),
            "shift_px": list(self.shift_px),
            "rotation_deg": self.rotation_deg,
            "scale_change": self.scale_change,
            "chi2": self.chi2,
            "chi2_threshold": self.threshold,
            "dof": 4,
            "significant": self.significant,
            "named": list(self.named),
            "z_scores": self.z_scores,
        }

    def describe(self) -> str:
        if not self.significant:
            return (
                f"no significant camera motion (chi-square {self.chi2:.2f} <= {self.threshold:.2f}, "
                "4 dof, p = 0.001)"
            )
        parts = []
        if "shift" in self.named:
            parts.append(
                f"shifted ({self.shift_px[0]:+.2f}, {self.shift_px[1]:+.2f}) px = "
                f"({self.shift_mm[0]:+.4f}, {self.shift_mm[1]:+.4f}) mm"
            )
        if "rotation" in self.named:
            parts.append(f"rotated {self.rotation_deg:+.4f} deg")
        if "scale" in self.named:
            parts.append(f"scale changed {100 * self.scale_change:+.3f} %")
        what = ", ".join(parts) if parts else "moved (no single component stands out)"
        return f"camera {what} since calibration (chi-square {self.chi2:.1f} > {self.threshold:.2f})"


@dataclass(frozen=True)
class Verification:
    ids: tuple[str, ...]
    error_mm: np.ndarray  # (N, 3) predicted − measured
    norm_mm: np.ndarray  # (N,)
    sigma_mm: np.ndarray  # (N,) predicted error of each point
    tolerance_mm: float
    drift: Drift
    passed: bool

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.norm_mm**2)))

    @property
    def max_mm(self) -> float:
        return float(self.norm_mm.max())

    def to_dict(self) -> dict:
        return {
            "passed": self.passed,
            "tolerance_mm": self.tolerance_mm,
            "n": len(self.ids),
            "rms_mm": self.rms_mm,
            "max_mm": self.max_mm,
            "drift": self.drift.to_dict(),
            "points": [
                {
                    "id": i,
                    "dx_mm": float(e[0]),
                    "dy_mm": float(e[1]),
                    "dz_mm": float(e[2]),
                    "error_mm": float(n),
                    "sigma_mm": float(s),
                    "within": bool(n <= self.tolerance_mm),
                }
                for i, e, n, s in zip(self.ids, self.error_mm, self.norm_mm, self.sigma_mm, strict=True)
            ],
        }

    def history_entry(self, source: str = "") -> dict:
        d = self.drift
        return {
            "utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "source": source,
            "n": len(self.ids),
            "passed": self.passed,
            "tolerance_mm": self.tolerance_mm,
            "rms_mm": self.rms_mm,
            "max_mm": self.max_mm,
            "shift_mm": list(d.shift_mm),
            "shift_px": list(d.shift_px),
            "rotation_deg": d.rotation_deg,
            "scale_change": d.scale_change,
            "chi2": d.chi2,
            "drift_significant": d.significant,
            "named": list(d.named),
        }


def check_tolerance(tolerance_mm) -> float:
    if (
        isinstance(tolerance_mm, bool)
        or not isinstance(tolerance_mm, (int, float))
        or not (np.isfinite(tolerance_mm) and tolerance_mm > 0)
    ):
        raise InputError(f"tolerance: expected a positive number of mm, got {tolerance_mm!r}")
    return float(tolerance_mm)


def verify(cal: Calibration, pairs: PointPairs, tolerance_mm: float) -> Verification:
    """Freshly measured ``pairs`` against ``cal`` (see the module docstring)."""
    tol = check_tolerance(tolerance_mm)
    if len(pairs) < MIN_PAIRS:
        raise InputError(
            f"{pairs.source}: verify needs at least {MIN_PAIRS} pairs to estimate a camera "
            f"motion, got {len(pairs)}"
        )
    model = cal.model
    z = None if model.height_rule is HeightRule.COMPUTED else pairs.xyz_mm[:, 2]
    try:
        m = cal.map(pairs.uv_px, z, with_sigma=True)
    except InputError as exc:
        raise InputError(f"{pairs.source}: {exc}") from None
    err = m.xyz_mm - pairs.xyz_mm
    if model.height_rule is not HeightRule.COMPUTED:
        err[:, 2] = 0.0
    norm = np.linalg.norm(err, axis=1)
    sigma = m.sigma_mm if m.sigma_mm is not None else np.full(len(pairs), cal.train.rms_mm)
    drift = fit_drift(cal, pairs, err[:, :2], sigma)
    return Verification(
        tuple(pairs.ids), err, norm, np.asarray(sigma, float), tol, drift, bool((norm <= tol).all())
    )


def fit_drift(cal: Calibration, pairs: PointPairs, err_xy: np.ndarray, sigma_mm: np.ndarray) -> Drift:
    """Weighted least squares of the similarity (shift, rotation, scale) to the errors, and its test."""
    q = pairs.xyz_mm[:, :2]
    c = q.mean(axis=0)
    d = q - c
    n = len(q)
    A = np.zeros((2 * n, 4))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2], A[1::2, 2] = -d[:, 1], d[:, 0]  # θ · R90 d
    A[0::2, 3], A[1::2, 3] = d[:, 0], d[:, 1]  # s · d
    var = np.repeat(np.maximum(np.asarray(sigma_mm, float), 1e-12) ** 2 / 2.0, 2)
    w = 1.0 / var
    e = err_xy.reshape(-1)
    N = A.T @ (A * w[:, None])
    rank = np.linalg.matrix_rank(N)
    if rank < 4:
        raise InputError(
            f"{pairs.source}: the pairs do not span the plane (collinear or repeated): "
            "cannot tell a rotation or scale change from a shift"
        )
    cov = np.linalg.inv(N)
    beta = cov @ (A.T @ (w * e))
    chi2 = float(beta @ N @ beta)
    zs = beta / np.sqrt(np.diag(cov))
    names = ("shift", "shift", "rotation", "scale")
    z_scores = {
        "shift_x": float(zs[0]),
        "shift_y": float(zs[1]),
        "rotation": float(zs[2]),
        "scale": float(zs[3]),
    }
    # the shift is named on its own 2-D test (chi-square, 2 dof, 0.1 %: 13.82)
    shift_chi2 = float(beta[:2] @ np.linalg.inv(cov[:2, :2]) @ beta[:2])
    named = []
    if shift_chi2 > 13.816:
        named.append("shift")
    for k in (2, 3):
        if abs(zs[k]) > Z_P001:
            named.append(names[k])
    significant = chi2 > CHI2_4_P001
    J = local_jacobian(_map_xy(cal, pairs), pairs.uv_px.mean(axis=0, keepdims=True))[0]
    try:
        shift_px = np.linalg.solve(J, beta[:2])
    except np.linalg.LinAlgError:
        shift_px = np.full(2, np.nan)
    return Drift(
        (float(beta[0]), float(beta[1])),
        (float(shift_px[0]), float(shift_px[1])),
        float(np.rad2deg(beta[2])),
        float(beta[3]),
        chi2,
        CHI2_4_P001,
        significant,
        tuple(named) if significant else (),
        z_scores,
    )


def _map_xy(cal: Calibration, pairs: PointPairs):
    model = cal.model
    zq = None if model.height_rule is HeightRule.COMPUTED else float(np.mean(pairs.xyz_mm[:, 2]))

    def f(uv):
        return model.image_to_robot(uv, zq)[:, :2]

    return f


# ---------------------------------------------------------------- history beside a file


def history_path(calibration_path: str | os.PathLike) -> Path:
    """``CAL.json`` → ``CAL.json.history.jsonl``."""
    p = Path(calibration_path)
    return p.with_name(p.name + HISTORY_SUFFIX)


def append_history(calibration_path: str | os.PathLike, entry: dict) -> Path:
    """Append one JSON line to the history beside the file (one write of one whole line)."""
    path = history_path(calibration_path)
    line = (json.dumps(entry, allow_nan=False) + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)
    return path


def read_history(calibration_path: str | os.PathLike) -> list[dict]:
    """The history's entries, oldest first (a torn last line, from a crash mid-write, is left out)."""
    path = history_path(calibration_path)
    if not path.exists():
        return []
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            d = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(d, dict):
            out.append(d)
    return out
