"""A rigid placement from a few touched points: least squares (Kabsch, no scale), its implied scale
(Umeyama), and its covariance — the systematic error the touches' noise puts on every mapped point.

``X_i = R·P_i + t + e_i``: P the points in an object's frame (a plate's corners), X the robot's
readings, e ~ N(0, s²) per axis. The least-squares R, t: the SVD of the centred cross-covariance,
with the determinant forced to +1 (for points on a plane the flip across it costs nothing: a
plate's face is told apart by the camera, not here). The covariance of a small rigid change
(ω, δt) about the touches' centroid c — ``δX = ω × (X − c) + δt`` — is s²·(AᵀA)⁻¹ with the Jacobian
A stacked over the touches; s² from the residuals (RSS / (3n − 6)) where there are spare degrees of
freedom, never below ``noise_floor_mm``² (a robot's readings are not exact however well 3 touches
agree).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices [v]× of (N, 3)."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], -1),
            np.stack([v[:, 2], z, -v[:, 0]], -1),
            np.stack([-v[:, 1], v[:, 0], z], -1),
        ],
        -2,
    )


@dataclass(frozen=True)
class RigidFit:
    """``X ≈ R·P + t``; ``scale``: the best similarity's scale (1 for a rigid set); residuals (N, 3)."""

    R: np.ndarray
    t_mm: np.ndarray
    residuals_mm: np.ndarray
    scale: float
    scaled_rms_mm: float  # the residuals' RMS (mm, per point) of the best similarity
    centre_mm: np.ndarray  # the touches' centroid, robot frame
    plate_mm: np.ndarray  # the points fitted, object frame

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals_mm**2, axis=1))))

    def apply(self, P_mm: np.ndarray) -> np.ndarray:
        return np.asarray(P_mm, float) @ self.R.T + self.t_mm

    def covariance(self, noise_mm: float) -> np.ndarray:
        """(6, 6) covariance of (ω rad, δt mm) about ``centre_mm`` for readings with ``noise_mm`` σ
        per axis."""
        A = rigid_jacobian(self.apply(self.plate_mm), self.centre_mm).reshape(-1, 6)
        return noise_mm**2 * np.linalg.pinv(A.T @ A)


def rigid_fit(P_mm, X_mm) -> RigidFit:
    """The least-squares rigid transform taking ``P_mm`` (N, 3) to ``X_mm`` (N, 3), N ≥ 3."""
    P = np.asarray(P_mm, float)
    X = np.asarray(X_mm, float)
    pc, xc = P.mean(axis=0), X.mean(axis=0)
    P0, X0 = P - pc, X - xc
    H = P0.T @ X0
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = Vt.T @ D @ U.T
    t = xc - R @ pc
    res = X - (P @ R.T + t)
    var_p = float((P0**2).sum())
    s = float((S * np.diag(D)).sum() / var_p) if var_p > 0 else 1.0
    scaled = X0 - s * (P0 @ R.T)
    return RigidFit(R, t, res, s, float(np.sqrt(np.mean(np.sum(scaled**2, axis=1)))), xc, P)


def rigid_jacobian(xyz_mm: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """(N, 3, 6) B = [−[X − c]×, I]: how points move under a small rigid change (ω, δt) about c."""
    X = np.asarray(xyz_mm, float).reshape(-1, 3)
    return np.concatenate([-_skew(X - centre_mm), np.broadcast_to(np.eye(3), (len(X), 3, 3))], axis=2)


def placement_variance_mm2(
    cov6: np.ndarray, centre_mm: np.ndarray, xyz_mm: np.ndarray, n_coords: int
) -> np.ndarray:
    """(N,) tr(B C Bᵀ) over the first ``n_coords`` coordinates of the points ``xyz_mm`` (N, 3), with
    B = [−[X − c]×, I]: the variance a rigid placement's covariance ``cov6`` puts on each point."""
    X = np.asarray(xyz_mm, float).reshape(-1, 3)
    B = np.concatenate([-_skew(X - centre_mm), np.broadcast_to(np.eye(3), (len(X), 3, 3))], axis=2)[
        :, :n_coords
    ]
    return np.einsum("nci,ij,ncj->n", B, cov6, B)


__all__ = ["RigidFit", "placement_variance_mm2", "rigid_fit", "rigid_jacobian"]
