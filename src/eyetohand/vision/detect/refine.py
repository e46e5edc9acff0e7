"""Stages 2 and 3 of the detection (see the package docstring): a candidate's sub-pixel ellipse from
edge points along radial profiles (an algebraic conic fitted, outliers dropped, profiles cast again),
then the intensity model of a blurred solid ellipse under smooth light fitted to the pixels of its
edge band (Levenberg–Marquardt, analytic Jacobian), kept only when it stays near the edge points'
ellipse."""

from __future__ import annotations

import math

import numpy as np

from eyetohand.vision.detect.quality import (
    Detection,
    Miss,
    _cut_by_border,
    _not_clean,
    _score,
    _too_few_edges,
)
from eyetohand.vision.detect.search import _Cand


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    x0 = np.clip(x0, 0, img.shape[1] - 2)
    y0 = np.clip(y0, 0, img.shape[0] - 2)
    a = img[y0, x0]
    b = img[y0, x0 + 1]
    c = img[y0 + 1, x0]
    d = img[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def fit_ellipse(pts: np.ndarray):
    """Normalised algebraic conic fit to points (N, 2) px. Returns (centre (2,), axes (full lengths,
    major first), angle deg, conic coefficients in the normalised frame, mean, scale), or None when
    the best conic is not an ellipse."""
    m = pts.mean(axis=0)
    s = math.sqrt(((pts - m) ** 2).sum(axis=1).mean())
    if s == 0:
        return None
    x, y = ((pts - m) / s).T
    D = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, c, d, e, f0 = np.linalg.svd(D, full_matrices=False)[2][-1]
    if 4 * a * c - b * b <= 0:
        return None
    cx, cy = np.linalg.solve(np.array([[2 * a, b], [b, 2 * c]]), [-d, -e])
    k = f0 + 0.5 * (d * cx + e * cy)
    ev, evec = np.linalg.eigh(np.array([[a, b / 2], [b / 2, c]]))
    if np.any(-k / ev <= 0):
        return None
    semi = np.sqrt(-k / ev) * s  # semi-axes along evec[:, 0], evec[:, 1]
    j = int(np.argmax(semi))
    ang = math.degrees(math.atan2(evec[1, j], evec[0, j])) % 180.0
    return (
        m + s * np.array([cx, cy]),
        (2 * float(semi.max()), 2 * float(semi.min())),
        ang,
        np.array([a, b, c, d, e, f0]),
        m,
        s,
    )


def _ellipse_distance(fit, pts: np.ndarray) -> np.ndarray:
    """Sampson approximation of each point's distance (px) from a fitted conic."""
    a, b, c, d, e, f0 = fit[3]
    x, y = ((pts - fit[4]) / fit[5]).T
    F = a * x * x + b * x * y + c * y * y + d * x + e * y + f0
    gx, gy = 2 * a * x + b * y + d, b * x + 2 * c * y + e
    return F / np.maximum(np.hypot(gx, gy), 1e-300) * fit[5]


def _shape_matrix(centre_axes_angle) -> np.ndarray:
    """Q with xᵀQx = 1 on the ellipse boundary (x from the centre)."""
    (_, _), (A, B), ang = centre_axes_angle
    t = math.radians(ang)
    Rm = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    return Rm @ np.diag([4 / A**2, 4 / B**2]) @ Rm.T


def _edge_points(img, centre, Q, sign: float, half_window: float, step: float = 0.25):
    """Sub-pixel edge points along radial profiles: (points (n, 2), valid (n,) bool, peak gradients)."""
    h, w = img.shape
    rho_min = 1 / math.sqrt(np.linalg.eigvalsh(Q).max())
    n = int(np.clip(round(2 * math.pi / math.sqrt(np.linalg.eigvalsh(Q).min())), 64, 1440))
    phi = 2 * np.pi * np.arange(n) / n
    e = np.column_stack([np.cos(phi), np.sin(phi)])
    rho = 1 / np.sqrt(np.einsum("ni,ij,nj->n", e, Q, e))
    W = min(half_window, 0.7 * rho_min)
    s = np.arange(-W, W + step / 2, step)
    r = rho[:, None] + s[None, :]
    X = centre[0] + r * e[:, :1]
    Y = centre[1] + r * e[:, 1:]
    inside = (X.min(axis=1) >= 0) & (X.max(axis=1) <= w - 1) & (Y.min(axis=1) >= 0) & (Y.max(axis=1) <= h - 1)
    p = _bilinear(img, X, Y)
    g = sign * np.gradient(p, step, axis=1)
    k = np.argmax(g, axis=1)
    gmax = g[np.arange(n), k]
    above = g > 0.25 * gmax[:, None]
    seg = np.cumsum(~above, axis=1)
    mask = above & (seg == seg[np.arange(n), k][:, None])
    wgt = np.where(mask, g - 0.25 * gmax[:, None], 0.0)
    tot = wgt.sum(axis=1)
    s_edge = (wgt * s[None, :]).sum(axis=1) / np.where(tot > 0, tot, 1)
    # the edge must lie inside the window, away from its ends
    valid = inside & (gmax > 0) & (k > 1) & (k < len(s) - 2) & (np.abs(s_edge) < W - step)
    pts = centre + (rho + s_edge)[:, None] * e
    return pts, valid, gmax, inside


def _refine(img, cand: _Cand, sigma: float, full: float, refine: str = "intensity") -> Detection:
    """Sub-pixel ellipse of a candidate (see the package docstring), or the refusal of it."""
    sign = 1.0 if cand.polarity == "dark" else -1.0
    ev, evec = np.linalg.eigh(cand.cov)
    axes = 4 * np.sqrt(np.maximum(ev, 1e-6))  # full axes of the moment-equivalent ellipse
    ang = math.degrees(math.atan2(evec[1, 1], evec[0, 1]))
    ell = ((cand.x, cand.y), (float(axes[1]), float(axes[0])), ang)
    centre = np.array([cand.x, cand.y])
    r0 = cand.diameter / 2
    windows = (max(4.0, 0.25 * r0), max(3.0, min(6.0, 0.2 * r0)), max(3.0, min(6.0, 0.2 * r0)))
    fit = None
    why = ""
    for W in windows:
        pts, valid, gmax, inside = _edge_points(img, centre, _shape_matrix(ell), sign, W)
        cut = _cut_by_border(cand, inside)
        if cut is not None:
            return cut
        why = _too_few_edges(cand, valid)
        if why:
            fit = None
            break
        use = valid.copy()
        for _ in range(3):
            fit = fit_ellipse(pts[use])
            if fit is None:
                break
            dist = np.abs(_ellipse_distance(fit, pts))
            sd = 1.4826 * np.median(dist[use]) + 1e-6
            new = valid & (dist < max(3.5 * sd, 0.05))
            if (new == use).all():
                break
            use = new
        if fit is None:
            why = f"the edge points of the candidate at ({cand.x:.1f}, {cand.y:.1f}) px fit no ellipse"
            break
        centre = fit[0]
        ell = (tuple(centre), fit[1], fit[2])
    if fit is None:
        return Detection(False, reason=why, polarity=cand.polarity, miss=Miss.NOT_FOUND)
    frac = float(use.mean())
    dist = _ellipse_distance(fit, pts[use])
    rms = float(np.sqrt(np.mean(dist**2)))
    (A, B), ang = fit[1], fit[2]
    mean_r = (A + B) / 4
    refused = _not_clean(centre, frac, rms, mean_r, cand.polarity)
    if refused is not None:
        return refused
    contrast = float(cand.contrast)
    score = _score(frac, rms, contrast, sigma)
    method, blur = "edge", None
    fine = (
        None
        if refine == "edge"
        else _fit_intensity(
            img, ((float(centre[0]), float(centre[1])), (float(A), float(B)), float(ang)), sign, sigma
        )
    )
    if fine is not None:
        (centre, (A, B), ang), blur = fine
        method = "intensity"
    return Detection(
        True,
        float(centre[0]),
        float(centre[1]),
        float(math.sqrt(A * B)),
        ((float(centre[0]), float(centre[1])), (float(A), float(B)), float(ang)),
        float(np.clip(score, 0, 1)),
        "",
        cand.polarity,
        rms,
        int(use.sum()),
        contrast,
        blur,
        method,
    )


def _ellipse_distance_px(p: np.ndarray, dx: np.ndarray, dy: np.ndarray, R: float) -> np.ndarray:
    """Signed distance (px, + outside) of points from the ellipse p = (cx, cy, q11, q12, q22) with
    ``(x − c)ᵀ (q / R²) (x − c) = 1``; ``dx``, ``dy`` from the initial centre. The radial distance
    times the cosine between ray and normal, ``(ρ − 1) ρ / |Q x|``: exact for a circle, and off by the
    square of the ray-normal angle for an ellipse (immaterial for the near-circles seen here)."""
    x, y = dx - p[0], dy - p[1]
    R2 = R * R
    qx = (p[2] * x + p[3] * y) / R2
    qy = (p[3] * x + p[4] * y) / R2
    rho = np.sqrt(np.maximum(x * qx + y * qy, 1e-300))
    return (rho - 1) * rho / np.maximum(np.hypot(qx, qy), 1e-300)


GEO_TOL = 1e-6  # px (and log s): the intensity fit stops when a step moves the ellipse less than this
N_HARMONICS = 4  # angular harmonics of the outer level in the intensity model (a textured surround)
_CHUNK = 256  # rows per product in the normal equations (see _normal_equations)


def _edge_model(
    p: np.ndarray, dx: np.ndarray, dy: np.ndarray, R: float, harmonics: np.ndarray, jacobian: bool = False
):
    """The intensity model of :func:`_fit_intensity` at points (dx, dy) from the initial centre, for the
    parameters p = (cx, cy, q11, q12, q22, a_in, a_out, log s, gx, gy, c1, s1, …, cK, sK): the outer
    level is a_out + Σ c_k cos kφ + s_k sin kφ around the initial centre (``harmonics`` (2K, N) holds
    the cos/sin rows). With ``jacobian`` also ∂I/∂p as a (len(p), N) array, all analytic (the
    geometry's through the distance of :func:`_ellipse_distance_px`)."""
    from scipy.special import ndtr

    s = math.exp(p[7])
    x, y = dx - p[0], dy - p[1]
    R2 = R * R
    qx = (p[2] * x + p[3] * y) / R2
    qy = (p[3] * x + p[4] * y) / R2
    rho2 = np.maximum(x * qx + y * qy, 1e-300)
    rho = np.sqrt(rho2)
    n = np.maximum(np.hypot(qx, qy), 1e-300)
    d = (rho - 1) * rho / n
    Phi = ndtr(d / s)
    g = 1 + (p[8] * dx + p[9] * dy) / R
    outer = p[6] + sum(p[10 + k] * harmonics[k] for k in range(len(harmonics)))  # no BLAS (see below)
    m = p[5] + (outer - p[5]) * Phi
    if not jacobian:
        return g * m
    z = d / s
    k = g * (outer - p[5]) * np.exp(-0.5 * z * z) / (math.sqrt(2 * math.pi) * s)  # ∂I/∂d
    # ∂d = (1 − 1/(2ρ)) ∂ρ² / n − d ∂n / n, with ∂n = (qx ∂qx + qy ∂qy) / n
    a_r = k * (1 - 0.5 / rho) / n
    b_r = k * d / (n * n)
    J = np.empty((len(p), len(d)))
    J[0] = a_r * (-2 * qx) - b_r * (-(p[2] * qx + p[3] * qy) / R2)
    J[1] = a_r * (-2 * qy) - b_r * (-(p[3] * qx + p[4] * qy) / R2)
    J[2] = a_r * (x * x / R2) - b_r * (qx * x / R2)
    J[3] = a_r * (2 * x * y / R2) - b_r * ((qx * y + qy * x) / R2)
    J[4] = a_r * (y * y / R2) - b_r * (qy * y / R2)
    J[5] = g * (1 - Phi)
    J[6] = g * Phi
    J[7] = -k * d  # ∂/∂ log s
    J[8] = m * dx / R
    J[9] = m * dy / R
    J[10:] = (g * Phi)[None, :] * harmonics
    return g * m, J


def _normal_equations(J: np.ndarray, w: np.ndarray, r: np.ndarray):
    """(J W Jᵀ, J W r) for J (P, N), weights w and residuals r (N,), as sums of products over blocks
    of ``_CHUNK`` samples. One (P × N)·(N × P) product is large enough for a multi-threaded BLAS to
    split it over threads, whose start-up and busy-waiting cost 10–80× the product itself on a
    loaded 2-core machine (measured: 0.13 ms with 1 OpenBLAS thread, 2–11 ms with 2); the blocks are
    below any threading threshold, so the time does not depend on the BLAS settings."""
    Jw = J * w
    H = np.zeros((len(J), len(J)))
    for i in range(0, J.shape[1], _CHUNK):
        H += Jw[:, i : i + _CHUNK] @ J[:, i : i + _CHUNK].T
    return H, Jw @ r


def _fit_edge_model(p0, dx, dy, val, R: float, scale: float, f_scale: float = 3.0, max_iter: int = 50):
    """Robust (soft-L1, ``f_scale`` 3 noise σ) least squares of :func:`_edge_model` to the values:
    Levenberg–Marquardt on the iteratively reweighted normal equations (P × P, P = 18), steps scaled
    by the diagonal. Returns the parameters, or None when it does not converge in ``max_iter``
    iterations or meets a singular system."""
    phi = np.arctan2(dy, dx)
    kphi = np.arange(1, N_HARMONICS + 1)[:, None] * phi[None, :]
    harmonics = np.vstack([np.cos(kphi), np.sin(kphi)])
    f2 = f_scale * f_scale

    def cost(res):
        return float(f2 * np.sum(np.sqrt(1 + res * res / f2) - 1))

    p = np.asarray(p0, float).copy()
    model, J = _edge_model(p, dx, dy, R, harmonics, jacobian=True)
    res = (model - val) / scale
    c = cost(res)
    lam = 1e-3
    for _ in range(max_iter):
        w = 1 / np.sqrt(1 + res * res / f2)  # ρ'(z) of soft-L1: the IRLS weights
        H, grad = _normal_equations(J, w, res)
        H /= scale * scale
        grad /= scale
        dg = np.maximum(np.diag(H), 1e-300)
        while True:
            try:
                step = np.linalg.solve(H + lam * np.diag(dg), -grad)
            except np.linalg.LinAlgError:
                return None
            q = p + step
            if not np.isfinite(q).all():
                return None
            # the Jacobian with the trial's value: steps are nearly always accepted, and then the
            # next iteration needs both (one evaluation instead of two)
            m_new, J_new = _edge_model(q, dx, dy, R, harmonics, jacobian=True)
            r_new = (m_new - val) / scale
            c_new = cost(r_new)
            if c_new <= c:
                break
            lam *= 10
            if lam > 1e12:  # no step lowers the cost: converged at a minimum
                return p
        # converged: a step that moves the centre, the axes (q · R / 2 px) and log s by < 1e-6 (the
        # iterations shrink the step ~10× each: what is left is ~1e-7 px), or that changes nothing
        small = (
            max(abs(step[0]), abs(step[1]), 0.5 * R * float(np.abs(step[2:5]).max()), abs(step[7])) <= GEO_TOL
            or np.all(np.abs(step) <= 1e-8 * (np.abs(q) + 1e-8))
            or c - c_new <= 1e-12 * max(c, 1e-300)
        )
        p, c = q, c_new
        lam = max(lam / 10, 1e-9)
        if small:
            return p
        J, res = J_new, r_new
    return None


def _fit_intensity(img, ellipse, sign: float, sigma: float):
    """Refine an ellipse by fitting the pixels within a few px of its edge with a model of a blurred
    solid ellipse under smooth light: ``I = (1 + gx·x + gy·y) · (a_in + (a_out(φ) − a_in) · Φ(d / s))``,
    ``d`` the signed distance from the ellipse, ``Φ`` the normal CDF, ``s`` the edge spread (blur and
    pixel), ``a_out(φ)`` the outer level with ``N_HARMONICS`` angular harmonics. Robust (soft-L1)
    least squares over 18 parameters, seeded by the edge-point fit, in a band of ±5 px (widened to
    ±(3 s + 1.5) px when the edge is wider; a narrower band helps a textured surround but costs
    accuracy on the strip: measured, see docs/detection.md). Returns ((centre, (major, minor),
    angle), s) or None when the fit fails or strays from the seed (the caller keeps the edge-point
    fit)."""
    (cx0, cy0), (A, B), ang = ellipse
    Q0 = _shape_matrix(ellipse)
    R = (A + B) / 4
    h, w = img.shape
    W = min(5.0, 0.6 * R)  # px each side of the edge; small circles keep an inner plateau
    ext = int(math.ceil(max(A, B) / 2 + 12))
    x0, x1 = max(int(cx0) - ext, 0), min(int(cx0) + ext + 1, w)
    y0, y1 = max(int(cy0) - ext, 0), min(int(cy0) + ext + 1, h)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    DX = (xx - cx0).ravel().astype(float)
    DY = (yy - cy0).ravel().astype(float)
    VAL = img[y0:y1, x0:x1].ravel().astype(float)
    p_geo = np.array([0.0, 0.0, Q0[0, 0] * R * R, Q0[0, 1] * R * R, Q0[1, 1] * R * R])
    D_all = _ellipse_distance_px(p_geo, DX, DY, R)
    result = None
    for _ in range(2):  # the second pass widens the band when the edge is wider than assumed
        sel = np.abs(D_all) <= W
        dx, dy, val, d0 = DX[sel], DY[sel], VAL[sel], D_all[sel]
        inner, outer = d0 < -0.5 * W, d0 > 0.5 * W
        if inner.sum() < 8 or outer.sum() < 8:
            return None
        a_in, a_out = float(np.median(val[inner])), float(np.median(val[outer]))
        if sign * (a_out - a_in) <= 0:
            return None
        scale = max(sigma, 1e-3 * abs(a_out - a_in))

        if result is None:
            p0 = np.concatenate([p_geo, [a_in, a_out, math.log(1.0), 0.0, 0.0], np.zeros(2 * N_HARMONICS)])
        else:  # the wider band starts from the narrower band's fit: fewer iterations, the same minimum
            p0 = result
        p = _fit_edge_model(p0, dx, dy, val, R, scale)
        if p is None:
            return None
        s = math.exp(p[7])
        if not np.isfinite(p).all() or not 0.1 < s < 0.5 * R:
            return None
        result = p
        if W >= 3 * s + 1.5 or W >= 0.6 * R:
            break
        W = min(3 * s + 1.5, 0.6 * R)
    if result is None:
        return None
    p = result
    if math.hypot(p[0], p[1]) > max(0.5, 0.02 * R):  # strayed from the edge fit: not trusted
        return None
    Q = np.array([[p[2], p[3]], [p[3], p[4]]]) / (R * R)
    ev, evec = np.linalg.eigh(Q)
    if ev[0] <= 0:
        return None
    major, minor = 2 / math.sqrt(ev[0]), 2 / math.sqrt(ev[1])
    if abs(major / A - 1) > 0.05 or abs(minor / B - 1) > 0.05:
        return None
    angle = math.degrees(math.atan2(evec[1, 0], evec[0, 0])) % 180.0
    return ((cx0 + p[0], cy0 + p[1]), (major, minor), angle), s
