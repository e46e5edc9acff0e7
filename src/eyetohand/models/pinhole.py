"""A distortion-aware camera for pairs at two or more heights: pinhole + Brown–Conrady lens + pose.

The mapping, robot → image (OpenCV's conventions)::

    Xc = R·(X − X0) + t                          camera frame; X0 = the training points' centroid
    n  = Xc[:2] / Xc[2]                          ideal normalised point
    d  = n·(1 + k1 r² + k2 r⁴ [+ k3 r⁶]) [+ tangential p1, p2]     r² = |n|²
    uv = (fx·d_x + cx, fy·d_y + cy)

and image → robot at a known height z: undistort (Newton on the 2×2 Jacobian, a fixed number of
steps so that a whole swarm of parameter vectors is mapped at once), cast the ray from the camera
centre, and intersect it with the plane z. Parameters (class ``PinholeCamera``, name ``camera``, 13):
``f, cx, cy, k1, k2, p1, p2, rx, ry, rz, tx, ty, tz`` — square pixels (fx = fy = f), radial k1, k2
and tangential p1, p2, the pose as a Rodrigues vector and a translation. Chosen by evidence on the
simulator (docs/simulator.md): a free aspect ratio and k3 cost more in variance than they gain on a
few dozen pairs; the tangential terms cost ≤ 3 % on a lens with little of them and halve the error
on a lens with p ≈ 5e-4.

Estimation: normalised DLT (the paper's equation 5) → RQ decomposition into K, R, t; then
Levenberg–Marquardt on the image reprojection error (the maximum-likelihood fit when the pixel
centres carry the noise), started from that and from a second start with the principal point at the
image centre and the pose from ``cv2.solvePnP``; the lower cost wins. The solvers (``lm``, the PSOs)
then refine all parameters on the robot-space residuals (the paper's equation 16).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import ClassVar

import numpy as np
from scipy.linalg import rq
from scipy.optimize import least_squares

from ..errors import DegenerateError
from .base import HeightRule, Model, _as_uv, batch_jacobian, check_enough
from .dlt3d import dlt_projection
from .radial import rodrigues_batch, rotation_to_rodrigues

NEWTON_STEPS = 10
FULL = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "rx", "ry", "rz", "tx", "ty", "tz")
_IDX = {name: i for i, name in enumerate(FULL)}


# ---------------------------------------------------------------- vectorised lens and pose


def distort(n: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Distorted normalised points (P, N, 2) from ideal ones, ``k`` (P, 5) = (k1, k2, k3, p1, p2)."""
    x, y = n[..., 0], n[..., 1]
    k1, k2, k3, p1, p2 = (k[:, i : i + 1] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort(d: np.ndarray, k: np.ndarray, steps: int = NEWTON_STEPS) -> np.ndarray:
    """Ideal normalised points (P, N, 2) from distorted ones by Newton's method on the 2×2 Jacobian,
    for per-row lens coefficients ``k`` (P, 5); ``steps`` iterations for every point at once."""
    k1, k2, k3, p1, p2 = (k[:, i : i + 1] for i in range(5))
    n = np.array(d, dtype=float, copy=True)
    for _ in range(steps):
        x, y = n[..., 0], n[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
        fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - d[..., 0]
        fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - d[..., 1]
        jxx = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        jyy = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
        jxy = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        det = jxx * jyy - jxy * jxy
        with np.errstate(divide="ignore", invalid="ignore"):
            n = n - np.stack([(jyy * fx - jxy * fy) / det, (jxx * fy - jxy * fx) / det], axis=-1)
    return n


def project_full(full: np.ndarray, xyz_rel: np.ndarray) -> np.ndarray:
    """Pixels (P, N, 2) of points (N, 3) (relative to X0) for full parameter rows (P, 15)."""
    R = rodrigues_batch(full[:, 9:12])
    Xc = np.einsum("pij,nj->pni", R, xyz_rel) + full[:, None, 12:15]
    with np.errstate(divide="ignore", invalid="ignore"):
        n = Xc[..., :2] / Xc[..., 2:3]
    d = distort(n, full[:, 4:9])
    return d * full[:, None, 0:2] + full[:, None, 2:4]


def backproject_full(full: np.ndarray, uv_px: np.ndarray, z_rel: np.ndarray) -> np.ndarray:
    """Points (P, N, 3) (relative to X0) on the planes z = ``z_rel`` (N,) seen at pixels (N, 2)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (uv_px[None] - full[:, None, 2:4]) / full[:, None, 0:2]
    n = undistort(d, full[:, 4:9])
    R = rodrigues_batch(full[:, 9:12])  # camera ← robot
    ray = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], axis=-1)
    w = np.einsum("pji,pnj->pni", R, ray)  # ray directions in the robot frame
    C = -np.einsum("pji,pj->pi", R, full[:, 12:15])  # camera centres
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z_rel[None, :] - C[:, None, 2]) / w[..., 2]
    return C[:, None, :] + s[..., None] * w


# ---------------------------------------------------------------- initial estimate


def decompose_projection(P: np.ndarray):
    """K (K[2,2] = 1), R (det +1) and t of a 3×4 projection matrix P ~ K [R | t]."""
    P = np.asarray(P, float)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    Kr, Q = rq(P[:, :3])
    D = np.diag(np.sign(np.diag(Kr)))
    Kr, R = Kr @ D, D @ Q
    t = np.linalg.solve(Kr, P[:, 3])
    return Kr / Kr[2, 2], R, t


class PinholeCamera(Model):
    """Pinhole camera (square pixels) with distortion k1, k2, p1, p2 and a free pose: see the module
    docstring. ``terms`` names the camera parameters estimated (``fx`` without ``fy``: fy = fx)."""

    name = "camera"
    terms: ClassVar[tuple[str, ...]] = ("fx", "cx", "cy", "k1", "k2", "p1", "p2")
    n_params = 13
    min_pairs = 8
    height_rule = HeightRule.GIVEN
    constant_shapes = MappingProxyType({"origin_mm": (3,)})
    summary = ("13 unknowns: pinhole camera f cx cy, lens k1 k2 p1 p2 and pose; pairs at 2+ heights, "
               "lens distortion")

    # -------------------------------------------------------------- estimation
    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> PinholeCamera:
        uv = np.asarray(uv_px, float)
        xyz = np.asarray(xyz_mm, float)
        check_enough(cls.name, cls.min_pairs, len(uv))
        x0 = xyz.mean(axis=0)
        rel = xyz - x0
        P_n, T_uv, T3, _ = dlt_projection(uv, rel, cls.name)
        P = np.linalg.inv(T_uv) @ P_n @ T3
        if image_size is not None:
            w, h = image_size
            centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
            size = float(max(w, h))
        else:
            centre = 0.5 * (uv.min(axis=0) + uv.max(axis=0))
            size = 2.0 * float(np.abs(uv - centre).max())
        starts = []
        K, R, t = decompose_projection(P)
        f_dlt = float(np.sqrt(abs(K[0, 0] * K[1, 1])))
        if np.isfinite(K).all() and 0.05 * size < f_dlt < 100 * size:
            starts.append(("DLT", np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(5),
                                        rotation_to_rodrigues(R), t]))
        else:
            f_dlt = 2.0 * size
        pnp = _pnp_start(uv, rel, centre, f_dlt)
        if pnp is not None:
            starts.append(("image centre + PnP", pnp))
        if not starts:
            raise DegenerateError(f"model '{cls.name}': could not find a starting camera for these pairs")
        mask = _mask(cls.terms)
        best = None
        for label, full0 in starts:
            if "fy" not in cls.terms:
                full0[0] = full0[1] = np.sqrt(abs(full0[0] * full0[1]))

            def fun_batch(p):
                return (project_full(_expand(p, mask, cls.terms), rel) - uv).reshape(len(p), -1)

            try:
                sol = least_squares(lambda p: fun_batch(p[None])[0], full0[mask], method="lm",
                                    jac=lambda p: batch_jacobian(fun_batch, p), x_scale="jac")
            except ValueError:
                continue
            cost = float(np.mean(sol.fun**2)) if np.isfinite(sol.fun).all() else np.inf
            if best is None or cost < best[0]:
                best = (cost, label, sol.x)
        if best is None or not np.isfinite(best[0]):
            raise DegenerateError(f"model '{cls.name}': the camera fit did not converge on these pairs")
        cost, label, params = best
        rms_px = float(np.sqrt(2 * cost))
        meta = {
            "origin_mm": x0.tolist(),
            "heights_mm": sorted({round(float(v), 6) for v in xyz[:, 2]}),
            "image_size": list(image_size) if image_size is not None else None,
            "reprojection_rms_px": rms_px,
            "init": f"camera fitted on image reprojection from the {label} start: rms {rms_px:.3f} px",
            "terms": list(cls.terms),
        }
        return cls(params, meta)

    def _prepare(self) -> None:
        self._x0 = np.asarray(self.meta["origin_mm"], float)
        self._mask = _mask(self.terms)

    # -------------------------------------------------------------- mapping
    def full_params(self, params) -> np.ndarray:
        """Rows (P, 15) of fx fy cx cy k1 k2 k3 p1 p2 rx ry rz tx ty tz (absent terms are 0)."""
        return _expand(np.asarray(params, float).reshape(-1, self.n_params), self._mask, self.terms)

    def batch_image_to_robot(self, params, uv_px, z_mm):
        uv = np.asarray(uv_px, float)
        z = np.asarray(z_mm, float)
        out = backproject_full(self.full_params(params), uv, z - self._x0[2]) + self._x0
        out[..., 2] = z  # exact, not x0 + (z - x0)
        return out

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        return project_full(self.full_params(self.params), xyz - self._x0)[0]

    def image_to_robot(self, uv_px, z_mm=None) -> np.ndarray:
        return super().image_to_robot(_as_uv(uv_px), z_mm)

    # -------------------------------------------------------------- the camera, for people
    @property
    def camera(self) -> dict:
        """Intrinsics, distortion (OpenCV order k1 k2 p1 p2 k3) and pose in the robot frame."""
        f = self.full_params(self.params)[0]
        R = rodrigues_batch(f[None, 9:12])[0]
        t = f[12:15] - R @ self._x0  # Xc = R X + t in robot coordinates
        return {
            "K": [[f[0], 0.0, f[2]], [0.0, f[1], f[3]], [0.0, 0.0, 1.0]],
            "dist": [f[4], f[5], f[7], f[8], f[6]],
            "R": R.tolist(),
            "t_mm": t.tolist(),
            "centre_mm": (-R.T @ t).tolist(),
        }


def _mask(terms) -> np.ndarray:
    return np.array([n in terms or n[0] in "rt" for n in FULL])


def _expand(p: np.ndarray, mask: np.ndarray, terms) -> np.ndarray:
    """Full rows (P, 15) from model parameter rows; without ``fy`` the pixels are square."""
    full = np.zeros((len(p), len(FULL)))
    full[:, mask] = p
    if "fy" not in terms:
        full[:, 1] = full[:, 0]
    return full


def _pnp_start(uv, rel, centre, f):
    """Full parameter row from the principal point at ``centre`` and the pose from solvePnP."""
    import cv2

    K = np.array([[f, 0, centre[0]], [0, f, centre[1]], [0, 0, 1.0]])
    try:
        ok, rvec, tvec = cv2.solvePnP(rel.astype(np.float64), uv.astype(np.float64), K, None,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not ok:
        return None
    return np.r_[f, f, centre, np.zeros(5), rvec.ravel(), tvec.ravel()]
