"""A distortion-aware camera for pairs at two or more heights: pinhole + Brown–Conrady lens + pose.

The mapping, robot → image (OpenCV's conventions)::

    Xc = R·(X − X0) + t                          camera frame; X0 = the training points' centroid
    n  = Xc[:2] / Xc[2]                          ideal normalised point
    d  = distort(n; k1, k2, p1, p2)              OpenCV's lens (eyetohand.geometry.lens), r² = |n|²
    uv = (fx·d_x + cx, fy·d_y + cy)

and image → robot at a known height z: undistort (:func:`eyetohand.geometry.lens.undistort`: fixed-point
start, Newton on the 2×2 Jacobian, each point to its tolerance, NaN where the lens cannot be
inverted; a whole swarm of parameter vectors at once), cast the ray from the camera centre, and
intersect it with the plane z. Parameters (class ``PinholeCamera``, name ``camera``):
``fx, fy, cx, cy, k1, k2, p1, p2, rx, ry, rz, tx, ty, tz`` (14), or with square pixels
``f, cx, cy, k1, k2, p1, p2, rx, ry, rz, tx, ty, tz`` (13, fx = fy = f; ``constants["aspect"]`` says
which) — radial k1, k2 and tangential p1, p2, the pose as a Rodrigues vector and a translation.

The aspect ratio: real sensors' fy/fx differ from 1 by parts in 10⁴..10³, which square pixels turn
into millimetre-level errors at other heights; a free fy costs 5–15 % in variance on a camera whose
pixels are square. So :meth:`PinholeCamera.from_pairs` (``aspect="auto"``) fits both and keeps fy
free only when the free fit's fy/fx differs from 1 by more than ``ASPECT_Z`` = 3 standard errors
(a Wald test on the reprojection fit's covariance; ``diagnostics["aspect_z"]``). Measured on simulated
two-height cells in docs/simulator.md (``benchmarks/study_sim.py --only aspect``). k3 is left out:
it over-fits a few dozen pairs (2.5× worse on 18, measured before; docs/simulator.md); the tangential
terms cost ≤ 3 % on a lens with little of them and halve the error on a lens with p ≈ 5e-4.

Estimation: normalised DLT (the paper's equation 5) → RQ decomposition into K, R, t; then
Levenberg–Marquardt on the image reprojection error (the maximum-likelihood fit when the pixel
centres carry the noise), started from that and from a second start with the principal point at the
image centre and the pose from ``cv2.solvePnP``; the lower cost wins. The solvers (``lm``, the PSOs)
then refine all parameters on the robot-space residuals (the paper's equation 16).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from eyetohand.core import DegenerateError, InputError
from eyetohand.geometry import (
    distort,
    levenberg_marquardt,
    matrix_to_rodrigues,
    rodrigues_to_matrix,
    undistort,
)
from eyetohand.models.base import (
    MAP_CHUNK,
    Choice,
    HeightRule,
    Model,
    as_uv,
    batch_jacobian,
    check_enough,
    one_point,
)
from eyetohand.models.dlt3d import dlt_projection

# The full parameter row, free aspect: fx fy cx cy | k1 k2 p1 p2 (OpenCV's order) | rx ry rz | tx ty tz.
# Square pixels drop fy (fy = fx): 13 parameters.
FREE_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "rx", "ry", "rz", "tx", "ty", "tz")
SQUARE_NAMES = ("f", "cx", "cy", "k1", "k2", "p1", "p2", "rx", "ry", "rz", "tx", "ty", "tz")
ASPECTS = ("auto", "free", "square")


# ---------------------------------------------------------------- vectorised camera over parameter rows


def project_full(full: np.ndarray, xyz_rel: np.ndarray) -> np.ndarray:
    """Pixels (P, N, 2) of points (N, 3) (relative to X0) for full parameter rows (P, 14)."""
    R = rodrigues_to_matrix(full[:, 8:11])
    Xc = np.einsum("pij,nj->pni", R, xyz_rel) + full[:, None, 11:14]
    with np.errstate(divide="ignore", invalid="ignore"):
        n = Xc[..., :2] / Xc[..., 2:3]
    return distort(n, full[:, 4:8]) * full[:, None, 0:2] + full[:, None, 2:4]


def backproject_full(full: np.ndarray, uv_px: np.ndarray, z_rel: np.ndarray) -> np.ndarray:
    """Points (P, N, 3) (relative to X0) on the planes z = ``z_rel`` (N,) seen at pixels (N, 2);
    NaN where the lens cannot be inverted (:func:`eyetohand.geometry.lens.undistort`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (uv_px[None] - full[:, None, 2:4]) / full[:, None, 0:2]
    # one parameter row: a single lens (plain-float path for a few points)
    n = undistort(d[0], full[0, 4:8])[0][None] if len(full) == 1 else undistort(d, full[:, 4:8])[0]
    R = rodrigues_to_matrix(full[:, 8:11])  # camera ← robot
    # ray directions in the robot frame: Rᵀ (x, y, 1)
    w = np.einsum("pji,pnj->pni", R[:, :2], n) + R[:, None, 2]
    C = -np.einsum("pji,pj->pi", R, full[:, 11:14])  # camera centres
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z_rel[None, :] - C[:, None, 2]) / w[..., 2]
    return C[:, None, :] + s[..., None] * w


def expand(params: np.ndarray, square: bool) -> np.ndarray:
    """Full rows (P, 14) from model parameter rows (P, 13) (square pixels: fy = fx) or (P, 14)."""
    p = np.asarray(params, float)
    return np.concatenate([p[:, :1], p], axis=1) if square else p


# ---------------------------------------------------------------- initial estimate


def decompose_projection(P: np.ndarray):
    """K (K[2,2] = 1), R (det +1) and t of a 3×4 projection matrix P ~ K [R | t]."""
    from scipy.linalg import rq  # lazily: SciPy costs ~0.4 s of start-up

    P = np.asarray(P, float)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    Kr, Q = rq(P[:, :3])
    D = np.diag(np.sign(np.diag(Kr)))
    Kr, R = Kr @ D, D @ Q
    t = np.linalg.solve(Kr, P[:, 3])
    return Kr / Kr[2, 2], R, t


class PinholeCamera(Model):
    """Pinhole camera with distortion k1, k2, p1, p2 and a free pose, fx and fy free or square pixels
    (chosen in :meth:`from_pairs`): see the module docstring. ``constants["aspect"]`` says which."""

    name = "camera"
    n_params = 14  # free aspect; an instance with square pixels has 13 (``self.n_params``)
    min_pairs = 8
    height_rule = HeightRule.GIVEN
    corrects_lens = True  # pixels are undistorted (k1, k2, p1, p2) before the ray is cast
    constant_shapes = MappingProxyType({"origin_mm": (3,), "aspect": Choice("free", "square")})
    summary = (
        "14 unknowns: pinhole camera fx fy cx cy, lens k1 k2 p1 p2 and pose; pairs at 2+ heights, "
        "lens distortion"
    )

    # -------------------------------------------------------------- estimation
    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None, aspect: str = "auto") -> PinholeCamera:
        """Fit on the image reprojection error (see the module docstring). ``aspect``: "free" (fx, fy),
        "square" (fx = fy) or "auto": free when the fitted fy/fx differs from 1 by more than
        ``ASPECT_Z`` standard errors, square otherwise."""
        if aspect not in ASPECTS:
            raise InputError(f"aspect: expected one of {', '.join(ASPECTS)}, got {aspect!r}")
        uv = np.asarray(uv_px, float)
        xyz = np.asarray(xyz_mm, float)
        check_enough(cls.name, cls.min_pairs, len(uv))
        x0 = xyz.mean(axis=0)
        rel = xyz - x0
        P_n, T_uv, T3, _ = dlt_projection(
            uv, rel, cls.name, what="a pinhole camera with lens", z_offset_mm=float(x0[2])
        )
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
            starts.append(
                ("DLT", np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(4), matrix_to_rodrigues(R), t])
            )
        else:
            f_dlt = 2.0 * size
        pnp = _pnp_start(uv, rel, centre, f_dlt)
        if pnp is not None:
            starts.append(("image centre + PnP", pnp))
        if not starts:
            raise DegenerateError(f"model '{cls.name}': could not find a starting camera for these pairs")
        fits = {}
        for square in (False, True) if aspect == "auto" else (aspect == "square",):
            best = _fit_reprojection(uv, rel, starts, square)
            if best is not None:
                fits[square] = best
        if not fits:
            raise DegenerateError(f"model '{cls.name}': the camera fit did not converge on these pairs")
        aspect_z = None
        if aspect == "auto" and False in fits:
            aspect_z = _aspect_z(uv, rel, fits[False][2])
            square = not (np.isfinite(aspect_z) and aspect_z > ASPECT_Z) and True in fits
        else:
            square = next(iter(fits))
        cost, label, params = fits[square]
        rms_px = float(np.sqrt(2 * cost))
        meta = {
            "origin_mm": x0.tolist(),
            "heights_mm": sorted({round(float(v), 6) for v in xyz[:, 2]}),
            "image_size": list(image_size) if image_size is not None else None,
            "reprojection_rms_px": rms_px,
            "init": f"camera fitted on image reprojection from the {label} start: rms {rms_px:.3f} px",
            "terms": [n for n in (SQUARE_NAMES if square else FREE_NAMES) if n[0] not in "rt"],
            "aspect": "square" if square else "free",
        }
        if aspect_z is not None:
            meta["aspect_z"] = aspect_z
        return cls(params, meta)

    @classmethod
    def unobservable(cls, uv_px, xyz_mm, *, image_size=None) -> str | None:
        """Why the pairs cannot show the camera's depth (:func:`depth_test`: the perspective of the
        pairs' linear projection within ``DEPTH_Z`` standard errors of none), or None. Without it the
        focal length and the distance are one number seen twice, and the reprojection fits crawl along
        that ridge to their evaluation limit (66 fits, 8 s on 16 pairs at two heights 1 mm apart)."""
        xyz = np.asarray(xyz_mm, float)
        if len(xyz) < cls.min_pairs:
            return None  # the count is refused elsewhere, in its own words
        test = pairs_depth_test(uv_px, xyz)
        if test is None or test.p_value < DEPTH_ALPHA:
            return None
        return (
            f"model '{cls.name}': these pairs do not show the camera's depth (their perspective is within "
            f"{DEPTH_Z:g} standard errors of none: chi-square {test.chi2:.3g} on 3 degrees of freedom, "
            f"p = {test.p_value:.2g}; heights span {np.ptp(xyz[:, 2]):.3g} mm seen from about "
            f"{test.distance_mm:.3g} mm with {test.noise_px:.2g} px of noise), so its focal length and "
            "distance cannot be told apart; pairs over a taller height span would show it"
        )

    def __init__(self, params, constants=None, diagnostics=None):
        consts = dict(constants or {})
        if diagnostics is None and "aspect" not in consts:  # files written before fy was estimated
            consts["aspect"] = "free" if "fy" in consts.get("terms", ()) else "square"
        if consts.get("aspect") not in ("free", "square"):
            raise InputError(
                f"model 'camera': constant 'aspect': expected 'free' or 'square', got "
                f"{consts.get('aspect')!r}"
            )
        self._square = consts["aspect"] == "square"
        # per instance: the aspect decides (13 with square pixels, 14 with fx and fy)
        self.n_params = 13 if self._square else 14  # type: ignore[misc]
        super().__init__(params, consts, diagnostics)

    def _prepare(self) -> None:
        self._x0 = np.asarray(self.constants["origin_mm"], float)
        # what the parameters fix, computed as the batch map computes it (one parameter row)
        full = self.full_params(self.params)
        R = rodrigues_to_matrix(full[:, 8:11])
        C = -np.einsum("pji,pj->pi", R, full[:, 11:14])[0]
        self._lens_k = full[0, 4:8].copy()
        self._intr = tuple(full[0, :4].tolist())  # fx fy cx cy
        self._Rt = tuple(tuple(row) for row in R[0].tolist())  # R[j][i]: ray w_i = Σ_j R[j][i] n_j
        self._C = tuple(C.tolist())
        self._x0f = tuple(self._x0.tolist())

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of ``params`` (13 with square pixels, 14 with fx and fy)."""
        return SQUARE_NAMES if self._square else FREE_NAMES

    # -------------------------------------------------------------- mapping
    def full_params(self, params) -> np.ndarray:
        """Rows (P, 14) of fx fy cx cy k1 k2 p1 p2 rx ry rz tx ty tz."""
        return expand(np.asarray(params, float).reshape(-1, self.n_params), self._square)

    def batch_image_to_robot(self, params, uv_px, z_mm):
        uv = np.asarray(uv_px, float)
        z = np.asarray(z_mm, float)
        out = backproject_full(self.full_params(params), uv, z - self._x0[2]) + self._x0
        out[..., 2] = np.where(np.isnan(out[..., 2]), np.nan, z)  # exact, not x0 + (z - x0)
        return out

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        return project_full(self.full_params(self.params), xyz - self._x0)[0]

    def image_to_robot(self, uv_px, z_mm=None) -> np.ndarray:
        """Back-projection with the precomputed rotation, centre and lens: one point on plain floats,
        many in cache-sized chunks; ``batch_image_to_robot``'s answer to rounding."""
        pt = one_point(uv_px)
        if pt is not None:
            plain = isinstance(z_mm, (int, float)) and not isinstance(z_mm, bool) and math.isfinite(z_mm)
            z = np.array([float(z_mm)]) if plain else self._z_for(1, z_mm)
            d = np.array([[(pt[0] - self._intr[2]) / self._intr[0], (pt[1] - self._intr[3]) / self._intr[1]]])
            return self._backproject_one(d, z)
        uv = as_uv(uv_px)
        z = self._z_for(len(uv), z_mm)
        out = np.empty((len(uv), 3))
        fx, fy, cx, cy = self._intr
        for s in range(0, len(uv), MAP_CHUNK):
            chunk = uv[s : s + MAP_CHUNK]
            d = np.empty(chunk.shape)
            with np.errstate(divide="ignore", invalid="ignore"):
                np.divide(chunk[:, 0] - cx, fx, out=d[:, 0])
                np.divide(chunk[:, 1] - cy, fy, out=d[:, 1])
            out[s : s + MAP_CHUNK] = self._backproject(d, z[s : s + MAP_CHUNK])
        return out

    def _backproject_one(self, d: np.ndarray, z: np.ndarray) -> np.ndarray:
        """:meth:`_backproject` of one point on plain floats: the same :meth:`_ray` and :meth:`_hit`
        after the lens's few-point undistortion (equal to rounding: each point stops its own Newton
        steps); the array path where the ray runs parallel to the plane (w2 = 0)."""
        n, _ = undistort(d, self._lens_k)  # plain floats inside for one point
        x, y = n[0].tolist()
        w = self._ray(x, y)
        if w[2] == 0.0:
            return self._backproject(d, z)
        zf = float(z[0])
        X, Y, zc = self._hit(w, zf)
        return np.array([[X, Y, math.nan if math.isnan(zc) else zf]])

    def _backproject(self, d: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Robot points (n, 3) on the planes ``z`` (n,) of distorted normalised points ``d`` (n, 2)."""
        n, _ = undistort(d, self._lens_k)
        with np.errstate(divide="ignore", invalid="ignore"):
            X, Y, zc = self._hit(self._ray(n[:, 0], n[:, 1]), z)
        out = np.empty((len(d), 3))
        out[:, 0] = X
        out[:, 1] = Y
        out[:, 2] = np.where(np.isnan(zc), np.nan, z)
        return out

    def _ray(self, x, y):
        """The ray's direction in the robot frame, Rᵀ (x, y, 1), of undistorted normalised (x, y):
        floats or arrays, the same operations."""
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._Rt
        return r00 * x + r10 * y + r20, r01 * x + r11 * y + r21, r02 * x + r12 * y + r22

    def _hit(self, w, z):
        """Where the ray ``w`` from the camera centre meets the plane z (robot mm): x, y, and the
        z it reaches (NaN where it does not: the caller then answers NaN)."""
        C0, C1, C2 = self._C
        s = ((z - self._x0f[2]) - C2) / w[2]
        return (C0 + s * w[0]) + self._x0f[0], (C1 + s * w[1]) + self._x0f[1], C2 + s * w[2]

    # -------------------------------------------------------------- the camera, for people
    @property
    def camera(self) -> dict:
        """Intrinsics, distortion (OpenCV order k1 k2 p1 p2 k3) and pose in the robot frame."""
        f = self.full_params(self.params)[0]
        R = rodrigues_to_matrix(f[8:11])
        t = f[11:14] - R @ self._x0  # Xc = R X + t in robot coordinates
        return {
            "K": [[f[0], 0.0, f[2]], [0.0, f[1], f[3]], [0.0, 0.0, 1.0]],
            "dist": [f[4], f[5], f[6], f[7], 0.0],
            "R": R.tolist(),
            "t_mm": t.tolist(),
            "centre_mm": (-R.T @ t).tolist(),
        }


ASPECT_Z = 3.0  # "auto": fy/fx − 1 must exceed this many standard errors for a free aspect ratio


# "auto" offers the camera only where the pairs show its depth: the perspective of their linear
# projection differs from none (an orthographic view) by DEPTH_Z standard errors, the two-sided
# normal level of ASPECT_Z's test, taken as the chi-square level of the three-number perspective
DEPTH_Z = 3.0
DEPTH_ALPHA = math.erfc(DEPTH_Z / math.sqrt(2.0))  # 0.0027


@dataclass(frozen=True)
class DepthTest:
    """:func:`depth_test`'s answer: the Wald ``chi2`` (3 degrees of freedom) of "no perspective", its
    ``p_value``, the distance ``distance_mm`` to the pairs' centroid along the view and the pixel
    noise ``noise_px`` it was measured against."""

    chi2: float
    p_value: float
    distance_mm: float
    noise_px: float


def depth_test(uv: np.ndarray, rel: np.ndarray, P: np.ndarray) -> DepthTest | None:
    """Does the projection ``P`` (3×4, robot points ``rel`` relative to their centroid → pixels ``uv``)
    show depth? Written ``uv = A·(X, 1) / (1 + q·X)``, an orthographic view is q = 0, and |q| is one
    over the distance to the centroid along the view: q's component along z is the magnification that
    changes with the height span, its x, y components the in-plane perspective of a tilted view. The
    Wald statistic ``qᵀ cov(q)⁻¹ q`` on the reprojection fit's covariance (σ² from its residuals,
    2n − 11 degrees of freedom) is chi-square with 3 degrees of freedom under q = 0. None when P
    leaves no residual degrees of freedom or its Jacobian is singular."""
    n = len(uv)
    if 2 * n <= 11 or P[2, 3] == 0:
        return None
    P = P / P[2, 3]
    Xh = np.column_stack([rel, np.ones(n)])
    w = 1.0 + rel @ P[2, :3]
    proj = (Xh @ P[:2].T) / w[:, None]
    r = (proj - uv).ravel()
    s2 = float(r @ r) / (2 * n - 11)
    J3 = np.zeros((n, 2, 11))  # d(proj)/d(A row 1, A row 2, q)
    J3[:, 0, 0:4] = Xh / w[:, None]
    J3[:, 1, 4:8] = Xh / w[:, None]
    J3[:, :, 8:11] = -proj[:, :, None] * rel[:, None, :] / w[:, None, None]
    J = J3.reshape(2 * n, 11)
    scale = np.linalg.norm(J, axis=0)
    if not (np.isfinite(J).all() and (scale > 0).all()):
        return None
    Js = J / scale
    try:
        cov_q = np.linalg.inv(Js.T @ Js)[8:, 8:] / np.outer(scale[8:], scale[8:])  # per unit σ²
        q = P[2, :3]
        chi2 = float(q @ np.linalg.solve(cov_q, q)) / s2 if s2 > 0 else math.inf
    except np.linalg.LinAlgError:
        return None
    norm_q = float(np.linalg.norm(q))
    return DepthTest(chi2, chi2_tail_3(chi2), 1.0 / norm_q if norm_q > 0 else math.inf, math.sqrt(s2))


def chi2_tail_3(x: float) -> float:
    """P(χ² > x) with 3 degrees of freedom, in closed form (SciPy's ``chi2.sf(x, 3)``)."""
    if math.isinf(x):
        return 0.0
    return math.erfc(math.sqrt(x / 2.0)) + math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)


def pairs_depth_test(uv_px, xyz_mm) -> DepthTest | None:
    """:func:`depth_test` of the pairs' normalised DLT (the camera's linear start); None where the
    DLT is refused (coplanar pairs: the camera's fit then says so itself)."""
    uv = np.asarray(uv_px, float)
    rel = np.asarray(xyz_mm, float) - np.mean(xyz_mm, axis=0)
    try:
        P_n, T_uv, T3, _ = dlt_projection(uv, rel, PinholeCamera.name, what="a pinhole camera with lens")
    except InputError:
        return None
    return depth_test(uv, rel, np.linalg.inv(T_uv) @ P_n @ T3)


def _fit_reprojection(uv, rel, starts, square: bool):
    """Levenberg–Marquardt on the image reprojection error from each start; the best converged fit as
    (mean squared residual, start label, parameters) or None. A start whose fit ran out of evaluations
    (``LMResult.converged`` False) is dropped: it stopped somewhere along a ridge, not at a minimum."""
    best = None
    for label, full0 in starts:
        full0 = np.array(full0, float)
        p0 = np.r_[np.sqrt(abs(full0[0] * full0[1])), full0[2:]] if square else full0

        def fun_batch(p):
            return (project_full(expand(p, square), rel) - uv).reshape(len(p), -1)

        try:  # least_squares(method="lm", x_scale="jac"): its routine and iterates (eyetohand.geometry.lm)
            sol = levenberg_marquardt(
                lambda p: fun_batch(p[None])[0], p0, lambda p: batch_jacobian(fun_batch, p)
            )
        except ValueError:
            continue
        if not sol.converged:
            continue
        cost = float(np.mean(sol.fun**2)) if np.isfinite(sol.fun).all() else np.inf
        if np.isfinite(cost) and (best is None or cost < best[0]):
            best = (cost, label, sol.x)
    return best


def _aspect_z(uv, rel, full) -> float:
    """|fy/fx − 1| in standard errors at the free-aspect reprojection fit ``full`` (14,)."""

    def fun_batch(p):
        return (project_full(p, rel) - uv).reshape(len(p), -1)

    r = fun_batch(full[None])[0]
    J = batch_jacobian(fun_batch, full)
    dof = max(r.size - full.size, 1)
    s2 = float(r @ r) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float("nan")
    g = np.zeros(full.size)  # gradient of fy/fx
    g[0], g[1] = -full[1] / full[0] ** 2, 1.0 / full[0]
    se = float(np.sqrt(max(g @ cov @ g, 0.0)))
    return abs(full[1] / full[0] - 1.0) / se if se > 0 else float("inf")


def _pnp_start(uv, rel, centre, f):
    """Full parameter row from the principal point at ``centre`` and the pose from solvePnP."""
    import cv2

    K = np.array([[f, 0, centre[0]], [0, f, centre[1]], [0, 0, 1.0]])
    try:
        ok, rvec, tvec = cv2.solvePnP(
            rel.astype(np.float64), uv.astype(np.float64), K, None, flags=cv2.SOLVEPNP_ITERATIVE
        )
    except cv2.error:
        return None
    if not ok:
        return None
    return np.r_[f, f, centre, np.zeros(4), rvec.ravel(), tvec.ravel()]
