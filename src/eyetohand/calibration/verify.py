"""Re-check a deployed calibration with a few freshly measured pairs: per-point errors, whether the
camera moved (shift, rotation, scale) since calibration, pass/fail against a tolerance, and a history.
Pairs outside the calibrated region or heights are refused, counted and named, and a mixed-up
convention (swapped u/v or x/y, a flipped sign, metres) is named (:mod:`eyetohand.calibration.checking`).

The errors are ``predicted − measured`` robot points (mm), each pair mapped at its own z through the
guarded map. A camera bump or a warm-up drift moves all points together; random error does not. So
a 2-D similarity is fitted to the errors around the measured points' centroid::

    e_i = t + θ · R90 (q_i − c) + s · (q_i − c)

(``t`` the shift in mm, ``θ`` the rotation in rad, ``s`` the scale change as a fraction), by
generalised least squares with the errors' covariance under "nothing moved": ``Σ = J C Jᵀ + s² I``
from the calibration's own uncertainty (:mod:`eyetohand.solve.uncertainty`). The first term is the
calibration's own error — one smooth field (``J δp``) shared by every fresh point and by every
re-check of the same calibration, so correlated from point to point, and largely a small shift,
rotation and scale itself; weighting the points as independent (``sigma_mm² / 2`` each) mistook it
for a camera motion (false alarms on 0–34 % of clean re-checks per calibration, 5.7 % pooled over
10 calibrations, where 0.1 % was meant). The second is each measurement's own noise.
Under "nothing moved" the estimate's quadratic form ``β̂ᵀ (AᵀΣ⁻¹A) β̂`` is chi-square with 4
degrees of freedom when the noise s² is known. It is not: the calibration estimated it on its
residual dof, and ``Σ`` (C too) is proportional to it, so a calibration whose training noise came
out low by chance would call every re-check a motion. So s² is re-estimated from the training dof
and the fresh points' own residuals about the similarity (independent of the estimate), the
chi-square is rescaled by it and tested against ``4 F(4, dof)`` at 0.1 % (≈ 20.6 for 42 + 28 dof;
18.47 for a file without an uncertainty record); the shift is named on its 2-D test (``2 F(2,
dof)``), rotation and scale when ``|z|`` exceeds the two-sided t(dof) 0.1 % point (≈ 3.44).
The image shift in pixels is the shift in mm through the inverse local Jacobian (``J⁻¹ t``: the
pixels the scene appears moved by).

Pass/fail is against the tolerance: every point's error ≤ ``tolerance_mm`` — the user's tolerance,
never widened. What a failure means is reported beside it, from the same predicted errors: with no
motion, ``|e_i|² / (sigma_i² / 2)`` is chi-square with 2 dof, so ``P(|e_i| > t) = exp(−t² / sigma_i²)``
and a clean re-measurement of these points passes with probability ``expected_pass = Π (1 − exp(−t² /
sigma_i²))`` (a tolerance tighter than the calibration holds shows as a low ``expected_pass`` before
any drift). A point beyond the tolerance is *explained* by the calibration's own random error when
``|e_i| ≤ sqrt(ln(N / 0.001)) sigma_i`` (3.11 for 16 points: with no motion, any point beyond it
has probability 0.001). The verdict's ``cause`` is ``"drift"`` when the motion test
is significant, ``"calibration error"`` when every point beyond the tolerance is explained and no
motion is, and ``"unexplained"`` otherwise (a bad measurement, a local change); ``None`` on a pass.
A history entry (JSON lines beside the file, or the server's table) records each run so that drift
shows as a trend.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eyetohand.calibration.checking import coverage, guard, mixup
from eyetohand.calibration.circles import as_fitted
from eyetohand.calibration.file import Calibration
from eyetohand.core import InputError, PointPairs
from eyetohand.geometry import local_jacobian
from eyetohand.models import HeightRule
from eyetohand.solve import param_jacobian

CHI2_4_P001 = 18.467
"""The 0.1 % point of chi-square with 4 degrees of freedom: the drift test's threshold."""
Z_P001 = 3.2905
"""The two-sided 0.1 % point of the standard normal: a component is named above it."""
EXPLAIN_P = 0.001
"""Family-wise: with no motion, some point of N is beyond ``explain_limit · sigma_mm`` with P 0.001."""
CHI2_2_P001 = 13.816
"""The 0.1 % point of chi-square with 2 degrees of freedom: the shift's own test."""
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
    named: tuple[str, ...]  # "shift", "rotation", "scale": the components beyond their 0.1 % points
    z_scores: dict
    noise_ratio: float = 1.0  # the noise re-estimated (training dof + fresh residuals) / the training's
    noise_dof: int = 0  # its degrees of freedom (0: taken as known)

    def to_dict(self) -> dict:
        return {
            "shift_mm": list(self.shift_mm),
            "shift_px": list(self.shift_px),
            "rotation_deg": self.rotation_deg,
            "scale_change": self.scale_change,
            "chi2": self.chi2,
            "chi2_threshold": self.threshold,
            "dof": 4,
            "noise_ratio": self.noise_ratio,
            "noise_dof": self.noise_dof,
            "significant": self.significant,
            "named": list(self.named),
            "z_scores": self.z_scores,
        }

    def describe(self) -> str:
        if not self.significant:
            return (
                f"no significant camera motion (chi-square {self.chi2:.2f} <= {self.threshold:.2f}, "
                f"4 dof, p = 0.001{self._noise()})"
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
        return (
            f"camera {what} since calibration (chi-square {self.chi2:.1f} > {self.threshold:.2f}"
            f"{self._noise()})"
        )

    def _noise(self) -> str:
        return f", noise re-estimated on {self.noise_dof} dof" if self.noise_dof else ""


@dataclass(frozen=True)
class Verification:
    ids: tuple[str, ...]
    error_mm: np.ndarray  # (N, 3) predicted − measured
    norm_mm: np.ndarray  # (N,)
    sigma_mm: np.ndarray  # (N,) predicted error of each point
    tolerance_mm: float
    drift: Drift
    passed: bool
    warnings: tuple[str, ...] = ()  # a mixed-up convention named (calibration.checking)

    @property
    def beyond(self) -> np.ndarray:
        """(N,) bool: the points whose error exceeds the tolerance."""
        return self.norm_mm > self.tolerance_mm

    @property
    def explain_limit(self) -> float:
        """``sqrt(ln(N / 0.001))``: with no motion, any of the N points beyond this many sigma_mm has
        probability 0.001 (Bonferroni over the points; 3.11 for 16)."""
        return float(np.sqrt(np.log(len(self.norm_mm) / EXPLAIN_P)))

    @property
    def explained(self) -> np.ndarray:
        """(N,) bool: beyond the tolerance yet within the calibration's own predicted random error
        (``|e| ≤ explain_limit · sigma_mm``)."""
        return self.beyond & (self.norm_mm <= self.explain_limit * self.sigma_mm)

    @property
    def expected_pass(self) -> float:
        """The probability that a clean re-measurement of these points (nothing moved) passes the
        tolerance, predicted from each point's ``sigma_mm``."""
        s = np.maximum(self.sigma_mm, 1e-12)
        return float(np.prod(-np.expm1(-((self.tolerance_mm / s) ** 2))))

    @property
    def cause(self) -> str | None:
        """None on a pass; else "drift", "calibration error" or "unexplained" (module docstring)."""
        if self.passed:
            return None
        if self.drift.significant:
            return "drift"
        return "calibration error" if bool(self.explained[self.beyond].all()) else "unexplained"

    def describe(self) -> str:
        """The verdict in one line."""
        n_out = int(self.beyond.sum())
        tol = f"{self.tolerance_mm:g} mm"
        tight = (
            f"a clean re-measurement of these points passes {tol} with probability {self.expected_pass:.1%}"
        )
        if self.passed:
            return f"PASS ({tight})"
        head = f"FAIL: {n_out} point(s) beyond {tol}"
        if self.cause == "drift":
            d = self.drift  # fitted to predicted − measured: the motion since is its opposite
            return (
                f"{head}; the camera moved {float(np.hypot(*d.shift_mm)):.3g} mm at {-d.rotation_deg:+.3g}° "
                f"(scale {-100 * d.scale_change:+.3g} %; see above)"
            )
        if self.cause == "calibration error":
            return (
                f"{head}, all within the calibration's own predicted error "
                f"(|e| <= {self.explain_limit:.2f} sigma_mm) "
                f"and no camera motion: the tolerance is tighter than this calibration holds ({tight})"
            )
        n_un = n_out - int(self.explained.sum())
        return (
            f"{head}, {n_un} of them beyond {self.explain_limit:.2f} sigma_mm with no camera motion: "
            "a bad measurement or a local change"
        )

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.norm_mm**2)))

    @property
    def max_mm(self) -> float:
        return float(self.norm_mm.max())

    def to_dict(self) -> dict:
        return {
            "passed": self.passed,
            "cause": self.cause,
            "expected_pass": self.expected_pass,
            "explain_limit_sigma": self.explain_limit,
            "tolerance_mm": self.tolerance_mm,
            "n": len(self.ids),
            "rms_mm": self.rms_mm,
            "max_mm": self.max_mm,
            "drift": self.drift.to_dict(),
            "warnings": list(self.warnings),
            "points": [
                {
                    "id": i,
                    "dx_mm": float(e[0]),
                    "dy_mm": float(e[1]),
                    "dz_mm": float(e[2]),
                    "error_mm": float(n),
                    "sigma_mm": float(s),
                    "within": bool(n <= self.tolerance_mm),
                    "explained": bool(x),
                }
                for i, e, n, s, x in zip(
                    self.ids, self.error_mm, self.norm_mm, self.sigma_mm, self.explained, strict=True
                )
            ],
        }

    def history_entry(self, source: str = "") -> dict:
        d = self.drift
        return {
            "utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "source": source,
            "n": len(self.ids),
            "passed": self.passed,
            "cause": self.cause,
            "expected_pass": self.expected_pass,
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
    found = mixup(cal, pairs)  # before the region's refusal: swapped u and v put pairs outside it
    guard(pairs, coverage(cal, pairs), allow_outside=False, found=found, how="")
    pairs = as_fitted(cal, pairs)  # a circle target's centres corrected as the fit's were
    z = None if model.height_rule is HeightRule.COMPUTED else pairs.xyz_mm[:, 2]
    try:
        m = cal.map(pairs.uv_px, z, with_sigma=True, part_diameter_mm=0.0)  # centres as fitted
    except InputError as exc:
        raise InputError(f"{pairs.source}: {exc}") from None
    err = m.xyz_mm - pairs.xyz_mm
    if model.height_rule is not HeightRule.COMPUTED:
        err[:, 2] = 0.0
    norm = np.linalg.norm(err, axis=1)
    sigma = m.sigma_mm if m.sigma_mm is not None else np.full(len(pairs), cal.train.rms_mm)
    drift = fit_drift(cal, pairs, err[:, :2], sigma)
    return Verification(
        tuple(pairs.ids),
        err,
        norm,
        np.asarray(sigma, float),
        tol,
        drift,
        bool((norm <= tol).all()),
        () if found is None else (found.describe(),),
    )


def error_covariance(cal: Calibration, pairs: PointPairs, sigma_mm: np.ndarray) -> np.ndarray:
    """(2N, 2N) covariance of the x, y errors (x0, y0, x1, …) of fresh measurements when nothing
    moved: ``J C Jᵀ + s² I`` — the calibration's own error ``J δp`` (C the fit's parameter covariance,
    J the parameter Jacobian at each pair) is one field shared by all the points, correlated from
    point to point, plus each measurement's own noise s² per coordinate. Without an uncertainty
    record: independent, ``sigma_mm² / 2`` per coordinate."""
    n = len(pairs)
    unc = cal.uncertainty
    if unc is None:
        var = np.repeat(np.maximum(np.asarray(sigma_mm, float), 1e-12) ** 2 / 2.0, 2)
        return np.diag(var)
    model = cal.model
    z = pairs.xyz_mm[:, 2]
    J = param_jacobian(model, pairs.uv_px, z)[:, :2, :].reshape(2 * n, -1)
    JL = J @ unc.factor
    cov = JL @ JL.T
    cov[np.diag_indices(2 * n)] += max(unc.noise_mm**2, 1e-24)
    if cal.plate is not None:  # a plate's touches: one rigid error shared by every point
        cov += cal.plate.error_covariance_xy(pairs.xyz_mm)  # at the robot's points: as at the mapped
    return cov


def _inverse_products(cal: Calibration, pairs: PointPairs, sigma_mm: np.ndarray):
    """``X ↦ S⁻¹ X`` for the covariance ``S`` of :func:`error_covariance`, without forming it: ``S`` is
    a diagonal ``D`` plus the low-rank ``U Uᵀ`` (U = J L, 2N × k parameters), so by Woodbury
    ``S⁻¹ = D⁻¹ − D⁻¹ U (I + Uᵀ D⁻¹ U)⁻¹ Uᵀ D⁻¹``: memory O(N k), not the (2N)² of ``S`` (20 000 pairs
    would be 12.8 GB)."""
    n = len(pairs)
    unc = cal.uncertainty
    if unc is None:
        d = np.repeat(np.maximum(np.asarray(sigma_mm, float), 1e-12) ** 2 / 2.0, 2)
        return lambda X: X / (d if X.ndim == 1 else d[:, None])
    J = param_jacobian(cal.model, pairs.uv_px, pairs.xyz_mm[:, 2])[:, :2, :].reshape(2 * n, -1)
    U = J @ unc.factor
    if cal.plate is not None:  # a plate's touches: one rigid error shared by every point (low rank too)
        U = np.hstack([U, cal.plate.error_factor_xy(pairs.xyz_mm)])
    d_inv = 1.0 / max(unc.noise_mm**2, 1e-24)
    small = np.linalg.cholesky(np.eye(U.shape[1]) + d_inv * (U.T @ U))

    def solve(X: np.ndarray) -> np.ndarray:
        inner = np.linalg.solve(small.T, np.linalg.solve(small, d_inv * (U.T @ X)))
        return d_inv * (X - U @ inner)

    return solve


def fit_drift(cal: Calibration, pairs: PointPairs, err_xy: np.ndarray, sigma_mm: np.ndarray) -> Drift:
    """Generalised least squares of the similarity (shift, rotation, scale) to the errors, with their
    covariance under "nothing moved" (:func:`error_covariance`, applied as its inverse by
    :func:`_inverse_products`), and its test."""
    q = pairs.xyz_mm[:, :2]
    c = q.mean(axis=0)
    d = q - c
    n = len(q)
    A = np.zeros((2 * n, 4))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2], A[1::2, 2] = -d[:, 1], d[:, 0]  # θ · R90 d
    A[0::2, 3], A[1::2, 3] = d[:, 0], d[:, 1]  # s · d
    e = err_xy.reshape(-1)
    inv_S = _inverse_products(cal, pairs, sigma_mm)
    N = A.T @ inv_S(A)
    N = 0.5 * (N + N.T)
    rank = np.linalg.matrix_rank(N)
    if rank < 4:
        raise InputError(
            f"{pairs.source}: the pairs do not span the plane (collinear or repeated): "
            "cannot tell a rotation or scale change from a shift"
        )
    cov = np.linalg.inv(N)
    beta = cov @ (A.T @ inv_S(e))
    chi2 = float(beta @ N @ beta)
    zs = beta / np.sqrt(np.diag(cov))
    # The covariance is the training noise s² times a known matrix (C ∝ s² too), and s² is an
    # estimate on the fit's residual dof: a calibration whose training noise came out low (it does,
    # by chance) would see every re-check as a motion. So the scale is re-estimated from the training
    # dof and the fresh points' own residuals about the similarity, independent of β̂, and β̂ is tested
    # by F (4, dof_t + 2N − 4): the chi-square reported is the rescaled one, against 4 F.
    dof_t = cal.uncertainty.dof if cal.uncertainty is not None else 0
    dof_f = 2 * n - 4
    r = e - A @ beta
    rss = float(r @ inv_S(r))
    dof_all = dof_t + dof_f
    phi = (dof_t + rss) / dof_all if dof_all > 0 else 1.0
    phi = max(phi, 1e-12)
    chi2 /= phi
    zs = zs / np.sqrt(phi)
    threshold, shift_threshold, z_threshold = _thresholds(dof_all)
    names = ("shift", "shift", "rotation", "scale")
    z_scores = {
        "shift_x": float(zs[0]),
        "shift_y": float(zs[1]),
        "rotation": float(zs[2]),
        "scale": float(zs[3]),
    }
    # the shift is named on its own 2-D test
    shift_chi2 = float(beta[:2] @ np.linalg.inv(cov[:2, :2]) @ beta[:2]) / phi
    named = []
    if shift_chi2 > shift_threshold:
        named.append("shift")
    for k in (2, 3):
        if abs(zs[k]) > z_threshold:
            named.append(names[k])
    significant = chi2 > threshold
    J = local_jacobian(
        cal.xy_map(float(np.mean(pairs.xyz_mm[:, 2]))), pairs.uv_px.mean(axis=0, keepdims=True)
    )[0]
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
        threshold,
        significant,
        tuple(named) if significant else (),
        z_scores,
        float(phi),
        int(dof_all),
    )


def _thresholds(dof: int) -> tuple[float, float, float]:
    """The 0.1 % points of the rescaled tests with ``dof`` degrees of freedom in the noise estimate:
    4 F(4, dof), 2 F(2, dof), and the two-sided t(dof); chi-square 18.47, 13.82 and 3.29 when the
    noise is known (``dof`` 0: a file without an uncertainty record)."""
    if dof <= 0:
        return CHI2_4_P001, CHI2_2_P001, Z_P001
    from scipy import stats

    return (
        float(4 * stats.f.isf(0.001, 4, dof)),
        float(2 * stats.f.isf(0.001, 2, dof)),
        float(stats.t.isf(0.0005, dof)),
    )


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
