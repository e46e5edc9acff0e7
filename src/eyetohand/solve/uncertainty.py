"""How far a mapped point may be from where the robot would measure it: ``sigma_mm``.

At the fit, the residual Jacobian J (the coordinates a model maps — x, y; and z for a model that
computes it — of every training pair, by each number fitted from the pairs: the parameters but a
gauge freedom's (``Model.gauge_params``, held as least squares holds them), and the
``Model.fitted_constants`` such as a lens's k1, k2) gives their covariance ``C = s² (JᵀJ)⁺`` with
``s² = SSR / (c·N − rank J)`` the point-level noise per coordinate. For a new
pixel with parameter Jacobian ``J_p`` (c × D), the expected squared distance between the mapped
position and a fresh robot measurement of that point is ``tr(J_p C J_pᵀ) + c·s²`` — the fit's own
error at that pixel plus the noise any single measurement carries — and ``sigma_mm`` is its root.
It grows where the training points are sparse or far away, which is what the report's map shows.
The noise is measured in robot space (the fit's residuals), so the detector's pixel noise mapped
through the local scale and the robot's repeatability are both in it, as they are in any measured
check point. Checked for calibration on simulated cells with known noise: over 40 cells (all five
models ``auto`` picks, 0.05–0.3 px, one and two heights, 16–49 pairs) RMS(sigma_mm) / measured check
RMS lies in 0.74..1.15, median 1.01 (``benchmarks/bench_uncertainty.py``; tests/test_guarded.py);
per model, all six, pooled over 16 cells: 1.06..1.12 (tests/test_sigma_models.py, docs/guarded.md).
That holds inside the calibrated region, where mappings are answered: beyond it a model's
extrapolation error (a lens term it lacks) is not in the parameter covariance, and sigma_mm there is
a lower bound.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from eyetohand.core import DegenerateError, InputError
from eyetohand.models import HeightRule, Model

_CHUNK = 1 << 15


def _coords(model: Model) -> int:
    return 3 if model.height_rule is HeightRule.COMPUTED else 2


def _steps(p: np.ndarray) -> np.ndarray:
    return 1e-6 * np.maximum(np.abs(p), 1e-3)


def param_jacobian(
    model: Model, uv_px: np.ndarray, z_mm: np.ndarray, *, constants: bool = True
) -> np.ndarray:
    """(N, c, D + E) derivative of the mapped coordinates at each pixel by each parameter — the model's
    closed form when it has one, else central differences (all 2D parameter rows in one batched
    call) — and, unless ``constants`` is False, by each of its E ``fitted_constants`` (a lens's k1,
    k2: fitted from the pairs too, so their error is the map's error), by central differences."""
    J = model.params_jacobian(uv_px, z_mm)
    if J is None:
        p = model.params
        h = _steps(p)
        rows = np.vstack([p + np.diag(h), p - np.diag(h)])
        out = model.batch_image_to_robot(rows, uv_px, z_mm)[..., : _coords(model)]  # (2D, N, c)
        D = len(p)
        J = np.moveaxis((out[:D] - out[D:]) / (2 * h)[:, None, None], 0, -1)
    if not constants or not model.fitted_constants:
        return J
    return np.concatenate([J, _constants_jacobian(model, uv_px, z_mm)], axis=-1)


def _constants_jacobian(model: Model, uv_px: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """(N, c, E) derivative of the mapped coordinates by each of the model's ``fitted_constants``:
    central differences (``Model.fitted_constant_steps``), the model rebuilt with the constant moved
    (parameters held)."""
    c = _coords(model)
    cols = []
    for key, h in zip(model.fitted_constants, model.fitted_constant_steps().tolist(), strict=True):
        out = [
            model.with_constant_moved(key, sgn * h).batch_image_to_robot(model.params[None], uv_px, z_mm)[0][
                :, :c
            ]
            for sgn in (1.0, -1.0)
        ]
        cols.append((out[0] - out[1]) / (2 * h))
    return np.stack(cols, axis=-1)


def fitted_columns(model: Model) -> np.ndarray:
    """Columns of :func:`param_jacobian` the fit determines: every parameter but a gauge freedom's
    (``Model.gauge_params``: numbers the mapping does not determine, which least squares holds; their
    columns are exactly dependent on the others, but numerical derivatives leave them a trace, 1e-8 of
    the largest singular value for the paper's B, that a pseudo-inverse would turn into a huge
    variance) and every fitted constant."""
    return np.r_[model.free_params(), model.n_params + np.arange(len(model.fitted_constants))].astype(np.intp)


def _scaled_svd(model: Model, uv: np.ndarray, xyz: np.ndarray, cols: np.ndarray | None = None):
    """SVD of the training pairs' parameter Jacobian (N c, D) — restricted to the columns ``cols``
    when given (:func:`fitted_columns`), else the model's parameters — columns scaled first (the
    paper's B spans six orders of magnitude): ``(norms, U, s, Vt, keep)``."""
    if cols is None:
        J = param_jacobian(model, uv, xyz[:, 2], constants=False).reshape(-1, model.n_params)
    else:
        J = param_jacobian(model, uv, xyz[:, 2]).reshape(-1, model.n_covariance())[:, cols]
    if not np.isfinite(J).all():
        raise DegenerateError(
            f"model '{model.name}': its parameter Jacobian at the training pairs is not finite (a pair "
            "sits at its lens's fold or its horizon): the pairs do not determine it"
        )
    norms = np.linalg.norm(J, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    U, s, Vt = np.linalg.svd(J / norms, full_matrices=False)
    return norms, U, s, Vt, s > 1e-10 * s[0]


def pair_leverage(model: Model, uv_px, xyz_mm) -> np.ndarray:
    """(N, c, c) the hat matrix's diagonal block of each training pair (its c coordinates): how much
    the fit follows the pair (0: not at all; eigenvalues near 1: it passes through it). For a
    linear least-squares fit a training residual's covariance is (I − H_ii)·s², a left-out one's
    (I − H_ii)⁻¹·s² (:mod:`eyetohand.solve.evaluate` studentizes with it before testing for outliers)."""
    uv = np.asarray(uv_px, float)
    xyz = np.asarray(xyz_mm, float)
    _, U, _, _, keep = _scaled_svd(model, uv, xyz)
    Ui = U[:, keep].reshape(len(uv), _coords(model), -1)
    return np.einsum("nck,ndk->ncd", Ui, Ui)


@dataclass(frozen=True)
class Uncertainty:
    """The fit's parameter covariance (D, D) and the point-level noise per coordinate (mm)."""

    covariance: np.ndarray
    noise_mm: float
    n_coords: int
    dof: int

    @classmethod
    def of_fit(cls, model: Model, uv_px, xyz_mm) -> Uncertainty:
        uv = np.asarray(uv_px, float)
        xyz = np.asarray(xyz_mm, float)
        c = _coords(model)
        r = model.residuals(uv, xyz)[:, :c]
        cols = fitted_columns(model)
        norms, _, s, Vt, keep = _scaled_svd(model, uv, xyz, cols)
        rank = int(keep.sum())
        dof = max(r.size - rank, 1)
        s2 = float((r * r).sum()) / dof
        inv = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
        cov = np.zeros((model.n_covariance(), model.n_covariance()))
        cov[np.ix_(cols, cols)] = s2 * inv / np.outer(norms, norms)
        return cls(cov, float(np.sqrt(s2)), c, dof)

    @cached_property
    def factor(self) -> np.ndarray:
        """L (D, D) with L Lᵀ = covariance (from its symmetric eigen-decomposition: a covariance of a
        rank-deficient fit is only positive semi-definite, where Cholesky would refuse it)."""
        w, V = np.linalg.eigh(0.5 * (self.covariance + self.covariance.T))
        return V * np.sqrt(np.maximum(w, 0.0))

    def sigma_mm(self, model: Model, uv_px, z_mm) -> np.ndarray:
        """(N,) predicted RMS distance (mm) between the mapped point and a robot measurement of it:
        ``tr(J C Jᵀ) = |J L|²`` with the precomputed factor L of the covariance."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        z = np.broadcast_to(np.asarray(z_mm, float), (len(uv),))
        noise = self.n_coords * self.noise_mm**2
        L = self.factor
        if len(uv) == 1:
            JL = param_jacobian(model, uv, z)[0] @ L  # (c, D)
            return np.array([np.sqrt(max(float((JL * JL).sum()), 0.0) + noise)])
        out = np.empty(len(uv))
        for s in range(0, len(uv), _CHUNK):
            JL = param_jacobian(model, uv[s : s + _CHUNK], z[s : s + _CHUNK]) @ L  # (n, c, D)
            out[s : s + _CHUNK] = np.sqrt(np.einsum("ncd,ncd->n", JL, JL) + noise)
        return out

    def to_dict(self) -> dict:
        return {
            "covariance": self.covariance.tolist(),
            "noise_mm": self.noise_mm,
            "n_coords": self.n_coords,
            "dof": self.dof,
        }

    @classmethod
    def from_dict(cls, d: dict, n_params: int) -> Uncertainty:
        cov = np.asarray(d["covariance"], float)
        if cov.shape != (n_params, n_params) or not np.isfinite(cov).all():
            raise InputError(f"uncertainty 'covariance' must be a finite {n_params}×{n_params} matrix")
        noise = float(d["noise_mm"])
        if not (np.isfinite(noise) and noise >= 0):
            raise InputError("uncertainty 'noise_mm' must be a finite number ≥ 0")
        return cls(cov, noise, int(d["n_coords"]), int(d["dof"]))


def best_new_point(
    uncertainty: Uncertainty, model: Model, candidates_px, candidates_z, targets_px, targets_z
) -> tuple[int, np.ndarray]:
    """Where one more training pair helps most: ``(index of the best candidate, (K,) mean sigma_mm over
    the targets after adding each candidate)``.

    A pair at pixel p (parameter Jacobian J_p, c × D, measured with the fit's noise s per coordinate)
    updates the covariance by the rank-c Woodbury step C' = C − C J_pᵀ (s² I + J_p C J_pᵀ)⁻¹ J_p C, so a
    target q's fit variance tr(J_q C J_qᵀ) drops by |J_q C J_pᵀ S_p^(-1/2)|²: the candidates are scored
    without refitting (a linearised prediction: the noise level stays the fit's)."""
    L = uncertainty.factor
    cz = np.broadcast_to(np.asarray(candidates_z, float), (len(candidates_px),))
    tz = np.broadcast_to(np.asarray(targets_z, float), (len(targets_px),))
    A = param_jacobian(model, np.asarray(targets_px, float), tz) @ L  # (N, c, D)
    B = param_jacobian(model, np.asarray(candidates_px, float), cz) @ L  # (K, c, D)
    s2 = uncertainty.noise_mm**2
    base = np.einsum("ncd,ncd->n", A, A)  # tr(J_q C J_qᵀ)
    noise = uncertainty.n_coords * s2
    c = A.shape[1]
    means = np.empty(len(B))
    for k in range(len(B)):
        S = s2 * np.eye(c) + B[k] @ B[k].T
        w, V = np.linalg.eigh(S)
        Sih = (V / np.sqrt(np.maximum(w, 1e-300))) @ V.T  # S^(-1/2)
        M = np.einsum("ncd,ed->nce", A, B[k]) @ Sih  # (N, c, c)
        drop = np.einsum("nce,nce->n", M, M)
        means[k] = float(np.mean(np.sqrt(np.maximum(base - drop, 0.0) + noise)))
    return int(np.argmin(means)), means
