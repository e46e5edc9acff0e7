"""Homography plus radial lens distortion: the paper's own remark that its linear model ignores the
lens, answered.

Mapping, image → robot: undistort the pixel (radial k1, k2 about the distortion centre c, in
f-normalised units as OpenCV), then a free homography H from ideal pixels to the robot's plane::

    n_d = (uv - c) / f,   n_d = n·(1 + k1 r² + k2 r⁴),   uv_ideal = c + f·n,   (x, y, 1) ~ H·(uv_ideal, 1)

Estimation follows what OpenCV's single-view ``calibrateCamera`` + ``findHomography`` does, because
with few points a physically constrained fit of the lens generalises better than a free one:

1. the lens: a camera with the principal point fixed at c, square pixels, no tangential terms —
   focal length f, k1, k2 and the plane's pose (9 unknowns) — fitted by Levenberg–Marquardt on the
   image-space reprojection error, started from the DLT homography's decomposition (f from Zhang's
   two constraints, or a default when the view is too straight-on to tell);
2. the plane: a homography from the undistorted pixels to the robot's (x, y), normalised DLT.
   The solvers (``lm``, the PSOs) refine its 8 elements on the robot-space residuals (eq. 16);
   f, k1, k2 stay as estimated in step 1 (``meta``).

Which lens terms step 1 fits is the pairs' to say (:func:`choose_lens`, issue 31): k1 alone, k2 only
when a nested F-test of the image-space residual sums of squares says it pays, then the distortion
centre (also the principal point) when a second test says so strongly — a k2 or a centre fitted to
noise costs accuracy (k2 cost 5–17 % on a cell whose lens has k1 alone, docs/limit.md), a real one
left out is a bias. ``constants["lens_terms"]`` records the choice (absent in older files: "k1 k2");
the covariance (sigma_mm) covers exactly those terms (``fitted_constants``).

Distortion centre c: the image centre ((W−1)/2, (H−1)/2) when the image size is known (then fitted
when the pairs support it), otherwise the centre of the training points' bounding box
(``diagnostics["centre_source"]`` says which). Seen straight on,
f and the camera's distance cannot be told apart; the lens fit then settles on one of the equivalent
(f, k1, k2) and the mapping is the same. Leave-one-out there keeps the full fit's f in each held-out
lens fit (a fit from the subset's own start would end wherever that start put it along the valley).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import ClassVar

import numpy as np

from eyetohand.core import DegenerateError
from eyetohand.geometry import (
    distort,
    fit_height_plane,
    hartley,
    levenberg_marquardt,
    matrix_to_rodrigues,
    rodrigues_to_matrix,
    undistort,
)
from eyetohand.models.base import Choice, plane_constants
from eyetohand.models.homography import Homography, dlt_homography
from eyetohand.models.planar import PLANAR_CONSTANTS, PLANE_SLOPE, planar_setup


def focal_from_homography(H_plane_to_image: np.ndarray, centre: np.ndarray) -> float | None:
    """Focal length (px) from a plane→image homography with known principal point and square
    pixels (Zhang's two constraints, least squares); None when the view is too straight-on."""
    T = np.array([[1, 0, -centre[0]], [0, 1, -centre[1]], [0, 0, 1.0]])
    H = T @ H_plane_to_image
    H = H / np.linalg.norm(H[:, 0])
    h1, h2 = H[:, 0], H[:, 1]
    A = np.array([h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    B = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    denom = A @ A
    if denom < 1e-30 or np.linalg.norm(B) < 1e-9 * np.linalg.norm(A):
        return None
    a = -(A @ B) / denom  # 1 / f^2
    if not np.isfinite(a) or a <= 0:
        return None
    return float(1.0 / np.sqrt(a))


def pose_from_homography(H_plane_to_image: np.ndarray, centre: np.ndarray, f: float):
    """(rvec, tvec) of the plane in the camera from its homography and the intrinsics."""
    Kinv = np.array([[1 / f, 0, -centre[0] / f], [0, 1 / f, -centre[1] / f], [0, 0, 1.0]])
    G = Kinv @ H_plane_to_image
    lam = 2.0 / (np.linalg.norm(G[:, 0]) + np.linalg.norm(G[:, 1]))
    if G[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * G[:, 0], lam * G[:, 1], lam * G[:, 2]
    U, _, Vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return matrix_to_rodrigues(R), t


def project_plane(p: np.ndarray, xy_mm: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Pixels of plane points (x, y, 0) for camera parameters p = (f, k1, k2, r(3), t(3))."""
    R = rodrigues_to_matrix(p[3:6])
    Xc = np.column_stack([xy_mm, np.zeros(len(xy_mm))]) @ R.T + p[6:9]
    n = Xc[:, :2] / Xc[:, 2:3]
    return centre + p[0] * distort(n, np.array([p[1], p[2], 0.0, 0.0]))


def project_plane_rows(P: np.ndarray, xy_mm: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """:func:`project_plane` for each row of P (S, 9) → (S, N, 2) px, equal to it bit for bit: the
    same matrix product per distinct rotation and the same elementwise arithmetic as
    :func:`eyetohand.geometry.lens.distort` (k1, k2 only), on all rows at once."""
    XY0 = np.column_stack([xy_mm, np.zeros(len(xy_mm))])
    M = np.empty((len(P), len(XY0), 3))
    M[:] = XY0 @ rodrigues_to_matrix(P[0, 3:6]).T
    for i in np.flatnonzero((P[1:, 3:6] != P[0, 3:6]).any(axis=1)) + 1:  # rows turned (a few)
        M[i] = XY0 @ rodrigues_to_matrix(P[i, 3:6]).T
    Xc = M + P[:, None, 6:9]
    n = Xc[..., :2] / Xc[..., 2:3]
    x, y = n[..., 0], n[..., 1]
    k1, k2 = P[:, 1, None], P[:, 2, None]
    r2 = x * x + y * y
    g = 1 + r2 * (k1 + r2 * (k2 + r2 * 0.0))  # distort's k3 = 0 term: NaN where r² is not finite
    # distort's tangential terms (p1 = p2 = 0) add ±0 where all is finite, where x·g + ±0 = x·g but
    # for the sign of a zero, which centre + f·(±0) does not keep; elsewhere g is NaN already
    return centre + P[:, 0, None, None] * np.stack([x * g, y * g], axis=-1)


_FD_STEP = float(np.finfo(float).eps ** 0.5)  # SciPy's forward-difference step, relative


def _lens_least_squares(p0: np.ndarray, uv_px: np.ndarray, xy_mm: np.ndarray, centre, free: np.ndarray):
    """SciPy's Levenberg–Marquardt on the image-space residuals over the parameters ``free`` (the
    rest held at ``p0``), with its own forward differences (``approx_derivative``'s steps and
    arithmetic) computed in one :func:`project_plane_rows` call instead of one projection per
    parameter: the same iterates as its default Jacobian (run by :func:`levenberg_marquardt`, the
    routine least_squares calls)."""
    p_all = np.asarray(p0, float).copy()
    target = uv_px.ravel()

    def rows(q: np.ndarray, dq: np.ndarray | None) -> np.ndarray:
        P = np.tile(p_all, (1 if dq is None else len(q) + 1, 1))
        P[:, free] = q
        if dq is not None:
            P[1 + np.arange(len(q)), free] += dq
        return project_plane_rows(P, xy_mm, centre).reshape(len(P), -1) - target

    def jacobian(q: np.ndarray) -> np.ndarray:
        h = _FD_STEP * ((q >= 0).astype(float) * 2 - 1) * np.maximum(1.0, np.abs(q))
        out = rows(q, h)
        dx = (q + h) - q
        return ((out[1:] - out[0]) / dx[:, None]).T

    return levenberg_marquardt(lambda q: rows(q, None)[0], p_all[free], jacobian, tol=LENS_FIT_TOL)


LENS_FIT_TOL = 1e-8  # least_squares' ftol, xtol, gtol for the lens fit (SciPy's defaults)
_LENS_CACHE: dict[tuple, tuple[np.ndarray, float]] = {}  # the last few fits (auto repeats them)
_LENS_CACHE_SIZE = 8


def lens_start(uv_px, xy_mm, centre, f_default) -> tuple[np.ndarray, bool]:
    """The lens fit's start (f, 0, 0, pose) from the DLT homography, and whether the homography told
    f (False: the view is too straight-on, f is the default)."""
    T_uv, uv_n = hartley(uv_px)
    T_xy, xy_n = hartley(xy_mm)
    Hn, _ = dlt_homography(xy_n, uv_n, "homography-radial")
    H = np.linalg.inv(T_uv) @ Hn @ T_xy
    f_told = focal_from_homography(H, centre)
    told = f_told is not None and 0.1 * f_default < f_told < 10 * f_default
    f = f_told if f_told is not None and told else float(f_default)
    rvec, tvec = pose_from_homography(H, centre, f)
    return np.r_[f, 0.0, 0.0, rvec, tvec], told


def lens_free(k2: bool) -> np.ndarray:
    """Indices of the lens fit's parameters (f, k1, k2, pose) it fits: k2 held at 0 unless ``k2``."""
    return np.arange(9) if k2 else np.r_[0, 1, 3:9]


def fit_lens(uv_px, xy_mm, centre, f_default, k2: bool = True, start: np.ndarray | None = None):
    """Single-view camera fit (f, k1, k2, pose; k2 held at 0 unless ``k2``) on image-space residuals;
    returns (params, rms_px). ``start``: the parameters to start from (default: :func:`lens_start`'s;
    ``choose_lens`` starts the k2 fit at the k1 fit's optimum, a few steps from its own). Memoised on
    the inputs (the last few: ``auto`` fits the same set twice)."""
    uv_px, xy_mm = np.asarray(uv_px, float), np.asarray(xy_mm, float)
    key = (
        uv_px.tobytes(),
        xy_mm.tobytes(),
        tuple(np.asarray(centre, float).tolist()),
        float(f_default),
        LENS_FIT_TOL,
        k2,
        None if start is None else np.asarray(start, float).tobytes(),
    )
    hit = _LENS_CACHE.get(key)
    if hit is not None:
        return hit[0].copy(), hit[1]
    p0 = lens_start(uv_px, xy_mm, centre, f_default)[0] if start is None else np.asarray(start, float).copy()
    sol = _lens_least_squares(p0, uv_px, xy_mm, centre, lens_free(k2))
    rms = float(np.sqrt(np.mean(sol.fun**2) * 2))
    while len(_LENS_CACHE) >= _LENS_CACHE_SIZE:  # oldest first; tolerant of another thread's pop
        try:
            _LENS_CACHE.pop(next(iter(_LENS_CACHE)), None)
        except (StopIteration, RuntimeError):
            break
    p = p0.copy()
    p[lens_free(k2)] = sol.x
    _LENS_CACHE[key] = (p.copy(), rms)
    return p, rms


# significance levels of the nested F-tests that admit k2, then the distortion centre. k2 is let in
# easily: a real k2 left out is a bias (on the real photos of tests/test_models.py, a strong lens's
# k2 at p = 0.08 with 12 points, left out, costs 35 % of the held-out error); the centre needs strong
# evidence (two numbers, identified by the distortion alone: on those photos α = 0.01 admitted a
# centre at p = 0.0065 that cost 20 %)
LENS_ALPHA_K2 = 0.15
LENS_ALPHA_CENTRE = 0.001
LENS_TERMS = ("k1", "k1 k2", "k1 centre", "k1 k2 centre")  # the lens terms a fit may have fitted


def lens_f_test(rss0: float, rss1: float, extra: int, dof1: int) -> float:
    """p-value of "the ``extra`` added terms are zero" from the image-space residual sums of squares
    (px²) of the nested lens fits without (rss0) and with them (rss1, ``dof1`` residual degrees of
    freedom): F = ((rss0 − rss1)/extra) / (rss1/dof1)."""
    if dof1 <= 0:
        return 1.0
    if rss1 <= 0:
        return 0.0 if rss0 > 0 else 1.0
    from scipy import stats  # lazily: SciPy costs ~0.4 s of start-up

    return float(stats.f.sf(max(rss0 - rss1, 0.0) / extra / (rss1 / dof1), extra, dof1))


def fit_lens_centre(p_lens: np.ndarray, uv_px, xy_mm, centre, k2: bool):
    """The lens fit with the distortion centre (= principal point) free too, from ``p_lens`` about
    ``centre``: (params (9,), centre (2,), rss_px2), by SciPy's Levenberg–Marquardt."""
    from scipy.optimize import least_squares  # lazily: SciPy costs ~0.4 s of start-up

    free = lens_free(k2)
    p_all = np.asarray(p_lens, float).copy()
    target = np.asarray(uv_px, float)

    def fun(q: np.ndarray) -> np.ndarray:
        p = p_all.copy()
        p[free] = q[:-2]
        return (project_plane(p, xy_mm, q[-2:]) - target).ravel()

    sol = least_squares(fun, np.r_[p_all[free], centre], method="lm", x_scale="jac")
    p_all[free] = sol.x[:-2]
    return p_all, sol.x[-2:], float(sol.fun @ sol.fun)


def choose_lens(uv_px, xy_mm, centre, f_default, centre_test: bool = True):
    """The lens terms the pairs support, by nested F-tests on the image-space residuals: k1 alone; k2
    when it pays (``LENS_ALPHA_K2``); then, if ``centre_test``, the distortion centre (= the principal
    point; 2 more; ``LENS_ALPHA_CENTRE``) when it pays. Without the image size the assumed centre is the
    points' (a guess of no optical meaning) and is not tested: it stays where it was.
    Returns (params (9,), centre (2,), terms — one of ``LENS_TERMS``, rms_px)."""
    n2 = 2 * len(uv_px)
    p1, rms1 = fit_lens(uv_px, xy_mm, centre, f_default, k2=False)
    p2, rms2 = fit_lens(uv_px, xy_mm, centre, f_default, k2=True, start=p1)
    rss1, rss2 = rms1**2 * n2 / 2, rms2**2 * n2 / 2
    k2 = lens_f_test(rss1, rss2, 1, n2 - 9) < LENS_ALPHA_K2
    p, rss, n_fit = (p2, rss2, 9) if k2 else (p1, rss1, 8)
    terms = "k1 k2" if k2 else "k1"
    if centre_test and n2 - n_fit - 2 > 0:
        try:
            pc, c, rss_c = fit_lens_centre(p, uv_px, xy_mm, centre, k2)
        except ValueError:  # SciPy refuses a start whose residuals are not finite: keep the centre
            pc, c, rss_c = p, centre, rss
        if np.isfinite(rss_c) and lens_f_test(rss, rss_c, 2, n2 - n_fit - 2) < LENS_ALPHA_CENTRE:
            return pc, np.asarray(c, float), terms + " centre", float(np.sqrt(2 * rss_c / n2))
    return p, np.asarray(centre, float), terms, float(np.sqrt(2 * rss / n2))


def project_plane_batch(P: np.ndarray, xy_mm: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """:func:`project_plane` for (S, 9) camera parameter rows at once → (S, N, 2) px."""
    R = rodrigues_to_matrix(P[:, 3:6])  # (S, 3, 3)
    x, y = xy_mm[:, 0], xy_mm[:, 1]
    Xc = [R[:, i, 0, None] * x + R[:, i, 1, None] * y + P[:, 6 + i, None] for i in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.stack([Xc[0] / Xc[2], Xc[1] / Xc[2]], axis=-1)
    k = np.column_stack([P[:, 1], P[:, 2], np.zeros(len(P)), np.zeros(len(P))])
    return centre + P[:, 0, None, None] * distort(n, k)


LENS_LOO_MAX_STEPS = 30
LENS_LOO_TOL_PX = 1e-6  # the held-out lens fits stop when no step moves a pixel by more than this (the
# steps settle at ~2e-7 px: rounding in the gradient)


def lens_leave_one_out(
    p_full: np.ndarray, uv_px: np.ndarray, xy_mm: np.ndarray, centre, k2: bool = True
) -> np.ndarray | None:
    """The n held-out lens fits (f, k1, k2, pose; k2 held unless ``k2``), each without one pair, by
    Gauss–Newton from the full fit ``p_full``, all at once (central-difference Jacobians in one batched
    projection); (n, 9) or None when a held-out fit is ill-conditioned or does not settle (the caller
    refits)."""
    n, D_all = len(uv_px), len(p_full)
    free = lens_free(k2)
    D = len(free)
    keep = 1.0 - np.eye(n)
    P_all = np.tile(p_full, (n, 1))
    P = P_all[:, free]
    eye = np.eye(D_all)[free]
    with np.errstate(all="ignore"):
        for _ in range(LENS_LOO_MAX_STEPS):
            P_all[:, free] = P
            h = 1e-5 * np.maximum(np.abs(P), 1.0)
            rows = np.concatenate(
                [P_all[:, None] + h[:, :, None] * eye, P_all[:, None] - h[:, :, None] * eye], axis=1
            )
            out = project_plane_batch(np.vstack([P_all, rows.reshape(-1, D_all)]), xy_mm, centre)
            r = (out[:n] - uv_px) * keep[:, :, None]  # (n, N, 2)
            F = out[n:].reshape(n, 2 * D, n, 2)
            J = ((F[:, :D] - F[:, D:]) / (2 * h)[:, :, None, None]) * keep[:, None, :, None]  # (n, D, N, 2)
            Jf = J.reshape(n, D, -1)
            A = Jf @ Jf.transpose(0, 2, 1)
            g = (Jf @ r.reshape(n, -1, 1))[..., 0]
            s = np.sqrt(np.einsum("idd->id", A))
            if not (np.isfinite(A).all() and np.isfinite(g).all() and (s > 0).all()):
                return None
            As = A / (s[:, :, None] * s[:, None, :])
            ev = np.linalg.eigvalsh(As)
            if not (ev[:, 0] > 1e-10 * ev[:, -1]).all():
                return None  # f, k1, k2 and the distance are not told apart: refits say which
            scaled = -np.linalg.solve(As, (g / s)[..., None])[..., 0]
            P = P + scaled / s
            if (np.abs(scaled) <= LENS_LOO_TOL_PX).all():
                P_all[:, free] = P
                return P_all
    return None


def lens_refit_holding_focal(
    p_full: np.ndarray, uv_px: np.ndarray, xy_mm: np.ndarray, centre, k2: bool = True
) -> np.ndarray:
    """One held-out lens fit for a view that does not tell f: k1, k2 and the pose by the lens fit's
    Levenberg–Marquardt from the full fit, f held at the full fit's. Where f is not told, a refit
    from its own start ends wherever that start puts it along the valley of equal (f, k1, k2);
    this one is the full fit refined on the held-out subset, as every other model's leave-one-out is."""
    free = lens_free(k2)[1:]
    sol = _lens_least_squares(p_full, uv_px, xy_mm, centre, free)
    p = np.asarray(p_full, float).copy()
    p[free] = sol.x
    return p


class HomographyRadial(Homography):
    """The homography, seen through a radial lens: pixels are undistorted (f, k1, k2 about the
    distortion centre, fixed by the lens fit) before the same planar matrix map; the solvers refine
    the homography's 8 elements."""

    name = "homography-radial"
    nests = ("homography", "affine")  # k1 = k2 = 0
    n_params = 8  # the homography; f, k1, k2 are fixed by the lens fit
    # ... and fitted from the pairs, so the covariance includes k1, k2 (f only sets their units: a
    # change of f with k1 f², k2 f⁴ held undistorts every pixel alike, so it is no error of the map)
    fitted_constants: ClassVar[tuple[str, ...]] = ("k1", "k2")  # per fit: the terms it fitted (_prepare)
    unknowns = 10  # 8 + k1, k2 (f only sets k's units)
    min_pairs = 6
    summary = "10 unknowns: homography plus radial lens distortion k1, k2"
    loo_warm_start = False  # the lens (f, k1, k2) is re-fitted on each subset of pairs
    corrects_lens = True  # _ideal_px undistorts the pixels before the matrix
    constant_shapes = MappingProxyType(
        {**PLANAR_CONSTANTS, "centre_px": (2,), "focal_px": (), "k1": (), "k2": ()}
    )
    # which lens terms the lens fit fitted (choose_lens); absent in files written before it: "k1 k2"
    optional_constant_shapes = MappingProxyType({**PLANE_SLOPE, "lens_terms": Choice(*LENS_TERMS)})

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> HomographyRadial:
        uv, xyz, plane, *_ = planar_setup(cls.name, cls.min_pairs, uv_px, xyz_mm)
        centre0, f_default, source = _centre(uv, image_size)
        lens, centre, terms, rms_px = choose_lens(
            uv, xyz[:, :2], centre0, f_default, centre_test=source == "image-size"
        )
        f, k1, k2 = (float(v) for v in lens[:3])
        ideal = undistort_px(uv, centre, f, k1, k2)
        folded = ~np.isfinite(ideal).all(axis=1)
        if folded.any():
            raise DegenerateError(
                f"model '{cls.name}': the lens fitted to these pairs (k1 {k1:.3g}, k2 {k2:.3g}) folds back "
                f"inside them ({int(folded.sum())} of {len(uv)} pixels cannot be undistorted): the pairs do "
                "not determine a radial lens (give more pairs across the image, the image size, or use "
                "the homography)"
            )
        T_uv, ideal_n = hartley(ideal)
        T_xy, xy_n = hartley(xyz[:, :2])
        H, cond = dlt_homography(ideal_n, xy_n, cls.name)
        constants = {
            "T_uv": T_uv.tolist(),
            "T_xy": T_xy.tolist(),
            **plane,
            "centre_px": centre.tolist(),
            "focal_px": f,
            "k1": k1,
            "k2": k2,
            "lens_terms": terms,
        }
        if "centre" in terms:
            source = f"fitted (from the {source} centre {centre0[0]:.1f}, {centre0[1]:.1f} px)"
        diagnostics = {"centre_source": source, "lens_fit_rms_px": rms_px, "condition_number": cond}
        return cls(H.reshape(-1)[:8], constants, diagnostics)

    @classmethod
    def leave_one_out(cls, uv_px, xyz_mm, *, image_size=None) -> np.ndarray | None:
        """Held-out residuals (N, 3) mm of the least-squares (``lm``) fits without each pair: the
        lens fits warm-started from the full one (:func:`lens_leave_one_out`; where the view does
        not tell f, :func:`lens_refit_holding_focal` with the full fit's f), each held-out
        homography by Gauss–Newton on its own pairs from its DLT; the held-out lens fits keep the full
        fit's lens terms (``choose_lens``; with a fitted centre, None: the refits choose their own);
        None where that cannot be trusted (the caller then refits). Checked against refits, and
        against SciPy's own fits with f held, in tests/test_speed_paths.py."""
        uv, xyz, _, *_ = planar_setup(cls.name, cls.min_pairs, uv_px, xyz_mm)
        n = len(uv)
        if n - 1 < cls.min_pairs:
            return None
        centre, f_default, source = _centre(uv, image_size)
        p_full, _, terms, _ = choose_lens(
            uv, xyz[:, :2], centre, f_default, centre_test=source == "image-size"
        )
        if "centre" in terms:  # the held-out fits choose their own terms and centre: the caller refits
            return None
        k2 = terms == "k1 k2"
        if lens_start(uv, xyz[:, :2], centre, f_default)[1]:
            lenses = lens_leave_one_out(p_full, uv, xyz[:, :2], centre, k2)
            if lenses is None:
                return None
        else:  # seen too straight on to tell f: the held-out fits keep the full fit's f
            try:
                lenses = np.array(
                    [
                        lens_refit_holding_focal(p_full, uv[keep], xyz[keep, :2], centre, k2)
                        for keep in (np.r_[0:i, i + 1 : n] for i in range(n))
                    ]
                )
            except ValueError:  # SciPy refuses a start whose residuals are not finite: refits say why
                return None
            if not np.isfinite(lenses).all():
                return None
        res = np.empty((n, 3))
        for i in range(n):
            keep = np.r_[0:i, i + 1 : n]
            f, k1, k2_i = (float(v) for v in lenses[i, :3])
            ideal = undistort_px(uv[keep], centre, f, k1, k2_i)
            if not np.isfinite(ideal).all():
                return None
            T_uv, ideal_n = hartley(ideal)
            T_xy, xy_n = hartley(xyz[keep, :2])
            H, _ = dlt_homography(ideal_n, xy_n, cls.name)
            plane = {
                "T_uv": T_uv.tolist(),
                "T_xy": T_xy.tolist(),
                **plane_constants(fit_height_plane(xyz[keep])),
            }
            # the homography's Gauss–Newton on the subset's ideal pixels, undistorted once: the same
            # steps as on the radial model, which undistorts them again at every step
            fitted = _gauss_newton(Homography(H.reshape(-1)[:8], plane, {}), ideal, xyz[keep])
            if fitted is None:
                return None
            lens = {"centre_px": centre.tolist(), "focal_px": f, "k1": k1, "k2": k2_i, "lens_terms": terms}
            m = cls(fitted.params, {**plane, **lens}, {})
            res[i] = m.image_to_robot(uv[i : i + 1], None)[0] - xyz[i]
        return res if np.isfinite(res).all() else None

    def _prepare(self) -> None:
        super()._prepare()
        self._c = np.asarray(self.constants["centre_px"], float)
        c = self.constants
        self._lens = (float(c["focal_px"]), float(c["k1"]), float(c["k2"]))
        self._k = np.array([self._lens[1], self._lens[2], 0.0, 0.0])
        self._cu, self._cv = (float(x) for x in self._c)
        terms = str(c.get("lens_terms", "k1 k2")).split()
        # the covariance's fitted constants: the lens terms the lens fit fitted (f only sets their units)
        names: list[str] = [t for t in ("k1", "k2") if t in terms]
        names += ["centre_u", "centre_v"] if "centre" in terms else []
        self.fitted_constants = tuple(names)  # type: ignore[misc]

    def fitted_constant_steps(self) -> np.ndarray:
        """k1, k2 act through r², r⁴ (r the f-normalised radius): steps that move k1 r², k2 r⁴ by 1e-6
        at the training pixels' spread (√2 / the Hartley scale of the ideal pixels), whatever f the lens
        fit settled on (seen straight on, f is free along its valley and can be a few px); the centre's
        coordinates by 1e-3 px."""
        radius = np.sqrt(2.0) / float(np.asarray(self.constants["T_uv"], float)[0][0]) / self._lens[0]
        steps = {"k1": radius**-2, "k2": radius**-4, "centre_u": 1e3, "centre_v": 1e3}
        return 1e-6 * np.array([steps[k] for k in self.fitted_constants])

    def with_constant_moved(self, key: str, step: float) -> HomographyRadial:
        """The centre's coordinates (``centre_u``, ``centre_v``) move ``constants["centre_px"]``."""
        if key not in ("centre_u", "centre_v"):
            return super().with_constant_moved(key, step)  # type: ignore[return-value]
        c = list(self._c)
        c[key == "centre_v"] += step
        return type(self)(self.params, {**self.constants, "centre_px": c}, self.diagnostics)

    def _ideal_one(self, u: float, v: float) -> tuple[float, float]:
        f = self._lens[0]
        n, _ = undistort(np.array([(u - self._cu) / f, (v - self._cv) / f]), self._k)
        x, y = n.tolist()
        return self._cu + f * x, self._cv + f * y

    @property
    def distortion(self) -> tuple[float, float]:
        """(k1, k2) in OpenCV's f-normalised convention, with f = ``constants["focal_px"]``."""
        return self._lens[1], self._lens[2]

    def _ideal_px(self, uv_px: np.ndarray) -> np.ndarray:
        return undistort_px(uv_px, self._c, *self._lens)

    def _distorted_px(self, uv_px: np.ndarray) -> np.ndarray:
        f, k1, k2 = self._lens
        return self._c + f * distort((uv_px - self._c) / f, np.array([k1, k2, 0.0, 0.0]))


def _gauss_newton(model, uv: np.ndarray, xyz: np.ndarray, max_steps: int = 12, tol_mm: float = 1e-7):
    """The least-squares refinement of ``model``'s parameters on the pairs by Gauss–Newton with the
    closed-form Jacobian (the ``lm`` solver's minimum); None when it does not settle."""
    p = model.params.copy()
    with np.errstate(all="ignore"):
        for _ in range(max_steps):
            out, J = model.batch_map_and_jacobian(p[None], uv, xyz[:, 2])
            r = (out[0] - xyz)[:, :2].reshape(-1)
            Jf = J[0, :, :2].reshape(-1, len(p))
            s = np.sqrt((Jf * Jf).sum(axis=0))
            if not (np.isfinite(Jf).all() and (s > 0).all()):
                return None
            step, *_ = np.linalg.lstsq(Jf / s, -r, rcond=None)
            p = p + step / s
            if np.abs(step).max() <= tol_mm:
                return model.with_params(p)
    return None


def _centre(uv: np.ndarray, image_size):
    """Distortion centre, default focal length (px) and where the centre came from."""
    if image_size is not None:
        w, h = image_size
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0]), 1.2 * max(w, h), "image-size"
    centre = 0.5 * (uv.min(axis=0) + uv.max(axis=0))
    return centre, 2.4 * float(np.abs(uv - centre).max()), "points"


def undistort_px(uv_px: np.ndarray, centre, f: float, k1: float, k2: float) -> np.ndarray:
    """Ideal pixels from distorted ones for one lens (N, 2) (:func:`eyetohand.geometry.lens.undistort`); NaN
    where the lens cannot be inverted (beyond its fold)."""
    d = (np.asarray(uv_px, float) - centre) / f
    return centre + f * undistort(d, np.array([k1, k2, 0.0, 0.0]))[0]
