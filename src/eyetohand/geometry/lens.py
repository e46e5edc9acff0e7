"""The one lens model of the package (OpenCV's), and Rodrigues rotations, vectorised over parameter sets.

Coefficients are in **OpenCV's order** ``k = (k1, k2, p1, p2[, k3])`` — the order of ``cv2``'s
``distCoeffs`` and of :attr:`eyetohand.geometry.camera.Camera.dist` — so that an OpenCV array can be passed as
is. On ideal normalised image coordinates ``(x, y)`` (``X/Z, Y/Z`` in the camera frame)::

    r² = x² + y²,  g = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x_d = x g + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y g + p1 (r² + 2 y²) + 2 p2 x y

Shapes broadcast the NumPy way: points ``(..., 2)`` against coefficients ``(P, 4|5)`` (one row per
parameter set, e.g. per swarm particle) give ``(P, N, 2)`` from ``(N, 2)`` or ``(P, N, 2)`` points;
one coefficient row ``(4|5,)`` keeps the points' shape.

:func:`undistort` inverts the map for every point at once: a few of OpenCV's fixed-point steps (a
robust start for strong distortion), then Newton's method with the analytic 2×2 Jacobian (1-D
Newton on the radius when the lens has no tangential terms), each point stopping at its own
tolerance, the loop ending as soon as all have. A point is accepted only if it is a true root where
the lens map is locally invertible (positive Jacobian determinant, residual ≤ 1e-10) and not
mirrored through the centre (1 + k1 r² + k2 r⁴ + k3 r⁶ > 0); any other —
beyond the fold of a strongly barrel-distorting lens, or not converged — comes back NaN, and the
returned mask says which.
"""

from __future__ import annotations

import math

import numpy as np

from eyetohand.core import InputError

TOL = 1e-14  # normalised units; × a 5000 px focal length ≈ 5e-11 px
MAX_ITER = 30
FIXED_POINT_STEPS = 5
ACCEPT_RESIDUAL = 1e-10  # |distort(n) - d| accepted as a root, relative to 1 + |d|
SCALAR_MAX_POINTS = 4  # up to this many points and one lens: plain floats (NumPy's per-call cost
# dominates there: one point in ~10 µs instead of ~100 µs)


def _coeffs(k) -> tuple:
    """(k1, k2, p1, p2, k3) as scalars (one row) or (P, 1) columns (P rows)."""
    k = np.asarray(k, dtype=float)
    if k.ndim not in (1, 2) or k.shape[-1] not in (4, 5):
        raise InputError(
            f"lens coefficients: expected (k1, k2, p1, p2[, k3]) as shape (4|5,) or (P, 4|5), got {k.shape}"
        )
    if k.ndim == 1:
        c = [float(v) for v in k] + [0.0] * (5 - k.size)
        return tuple(c)
    cols = [k[:, i, None] for i in range(k.shape[1])]
    if k.shape[1] == 4:
        cols.append(np.zeros((len(k), 1)))
    return tuple(cols)


def _points(p, what: str) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.shape[-1:] != (2,):
        raise InputError(f"{what}: expected normalised points of shape (..., 2), got {p.shape}")
    return p


def distort(n, k) -> np.ndarray:
    """Distorted normalised points from ideal ones ``n`` (..., 2) for coefficients ``k`` in OpenCV's
    order (k1, k2, p1, p2[, k3]), shape (4|5,) or (P, 4|5) → (P, N, 2) (see the module docstring)."""
    n = _points(n, "n")
    k1, k2, p1, p2, k3 = _coeffs(k)
    if not isinstance(k1, np.ndarray) and n.size <= 2 * SCALAR_MAX_POINTS:  # plain floats: faster
        out = []
        for x, y in n.reshape(-1, 2).tolist():
            r2 = x * x + y * y
            g = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            out.append(
                (
                    x * g + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
                )
            )
        return np.array(out, dtype=float).reshape(n.shape)
    x, y = n[..., 0], n[..., 1]
    r2 = x * x + y * y
    g = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    xd = x * g + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    return np.stack([xd, yd], axis=-1)


def _is_zero(c) -> bool:
    return not np.any(c) if isinstance(c, np.ndarray) else c == 0.0


def undistort(
    d, k, *, tol: float = TOL, max_iter: int = MAX_ITER, fixed_point_steps: int = FIXED_POINT_STEPS
) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised points from distorted ones ``d`` (..., 2) for coefficients ``k`` (OpenCV
    order, (4|5,) or (P, 4|5)). Returns ``(n, converged)``: ``n`` of the broadcast shape (P, N, 2)
    with NaN where ``converged`` (P, N) is False. ``tol``: Newton step size at which a point stops
    (normalised units, relative to 1 + |n|); ``max_iter``: Newton steps at most."""
    d = _points(d, "d")
    k1, k2, p1, p2, k3 = _coeffs(k)
    xd, yd = d[..., 0], d[..., 1]
    if all(_is_zero(c) for c in (k1, k2, p1, p2, k3)):
        shape = np.broadcast_shapes(xd.shape, np.shape(k1))
        n = np.broadcast_to(d, shape + (2,)).copy()
        return n, np.isfinite(n).all(axis=-1)
    if not isinstance(k1, np.ndarray) and d.size <= 2 * SCALAR_MAX_POINTS:
        return _undistort_few(d, (k1, k2, p1, p2, k3), tol, max_iter, fixed_point_steps)
    if _is_zero(p1) and _is_zero(p2):
        return _undistort_radial(xd, yd, k1, k2, k3, tol, max_iter, fixed_point_steps)
    x, y = xd, yd
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(fixed_point_steps):  # OpenCV's scheme: a robust start
            r2 = x * x + y * y
            g = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xy = x * y
            x = (xd - 2 * p1 * xy - p2 * (r2 + 2 * x * x)) / g
            y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * xy) / g
        x, y = np.broadcast_arrays(x, y)
        x, y = x.copy(), y.copy()
        for _ in range(max_iter):
            _, fx, fy, a, b, c = _newton_terms(x, y, xd, yd, k1, k2, k3, p1, p2)
            det = a * c - b * b
            sx = (c * fx - b * fy) / det
            sy = (a * fy - b * fx) / det
            x -= sx
            y -= sy
            if not (np.abs(sx) + np.abs(sy) > tol * (1 + np.abs(x) + np.abs(y))).any():
                break  # NaN steps compare False: such points are rejected below
        g, fx, fy, a, b, c = _newton_terms(x, y, xd, yd, k1, k2, k3, p1, p2)
        res = np.abs(fx) + np.abs(fy)
        ok = (res <= ACCEPT_RESIDUAL * (1 + np.abs(xd) + np.abs(yd))) & (a * c - b * b > 0) & (g > 0)
    x[~ok] = np.nan
    y[~ok] = np.nan
    return np.stack([x, y], axis=-1), ok


def _newton_terms(x, y, xd, yd, k1, k2, k3, p1, p2):
    """g, the residual (fx, fy) of distort(x, y) − (xd, yd), and its Jacobian [[a, b], [b, c]]: on
    plain floats or arrays (the same expressions for both paths of :func:`undistort`)."""
    r2 = x * x + y * y
    g = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dg = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # dg / d(r²)
    xy = x * y
    fx = x * g + 2 * p1 * xy + p2 * (r2 + 2 * x * x) - xd
    fy = y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * xy - yd
    a = g + 2 * x * x * dg + 2 * p1 * y + 6 * p2 * x
    b = 2 * xy * dg + 2 * p1 * x + 2 * p2 * y
    c = g + 2 * y * y * dg + 6 * p1 * y + 2 * p2 * x
    return g, fx, fy, a, b, c


def _undistort_few(d, k, tol, max_iter, fixed_point_steps):
    """The same iteration as :func:`undistort` on plain floats, for a handful of points, one lens."""
    k1, k2, p1, p2, k3 = k
    out, oks = [], []
    for xd, yd in d.reshape(-1, 2).tolist():
        x, y, ok = xd, yd, False
        try:
            for _ in range(fixed_point_steps):
                r2 = x * x + y * y
                g = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xy = x * y
                x, y = (
                    (xd - 2 * p1 * xy - p2 * (r2 + 2 * x * x)) / g,
                    (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * xy) / g,
                )
            for it in range(max_iter + 1):
                g, fx, fy, a, b, c = _newton_terms(x, y, xd, yd, k1, k2, k3, p1, p2)
                det = a * c - b * b
                if it == max_iter:
                    break
                sx, sy = (c * fx - b * fy) / det, (a * fy - b * fx) / det
                x, y = x - sx, y - sy
                if abs(sx) + abs(sy) <= tol * (1 + abs(x) + abs(y)):
                    # the residual and determinant at the new point (one more evaluation)
                    g, fx, fy, a, b, c = _newton_terms(x, y, xd, yd, k1, k2, k3, p1, p2)
                    det = a * c - b * b
                    break
            ok = abs(fx) + abs(fy) <= ACCEPT_RESIDUAL * (1 + abs(xd) + abs(yd)) and det > 0 and g > 0
        except (ZeroDivisionError, OverflowError):
            ok = False
        ok = ok and math.isfinite(x) and math.isfinite(y)
        out.append((x, y) if ok else (math.nan, math.nan))
        oks.append(ok)
    return np.array(out, dtype=float).reshape(d.shape), np.array(oks).reshape(d.shape[:-1])


def _undistort_radial(xd, yd, k1, k2, k3, tol, max_iter, fixed_point_steps):
    """Radial-only lens: 1-D Newton on the radius r, r·g(r²) = r_d, then scale the point."""
    rd = np.sqrt(xd * xd + yd * yd)
    r = rd
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(fixed_point_steps):
            r2 = r * r
            r = rd / (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        r = np.array(np.broadcast_to(r, np.broadcast_shapes(np.shape(r), np.shape(k1))))
        for _ in range(max_iter):
            r2 = r * r
            f = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) - rd
            fp = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2))  # d(r g)/dr
            s = f / fp
            r -= s
            if not (np.abs(s) > tol * (1 + r)).any():
                break
        r2 = r * r
        res = np.abs(r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) - rd)
        fp = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2))
        # fp > 0 with g > 0: the radial map is increasing there, the root is the one on the lens's
        # invertible branch (and r > 0, the point is not mirrored through the centre)
        ok = (res <= ACCEPT_RESIDUAL * (1 + rd)) & (fp > 0) & (r >= 0)
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
    scale[~ok] = np.nan
    return np.stack([xd * scale, yd * scale], axis=-1), ok


# ---------------------------------------------------------------- Rodrigues


def rodrigues_to_matrix(rvec) -> np.ndarray:
    """Rotation matrices (P, 3, 3) from Rodrigues vectors (P, 3) (axis × angle, rad); one vector (3,)
    gives one matrix (3, 3). As ``cv2.Rodrigues``; smooth through zero rotation (series there)."""
    r = np.asarray(rvec, dtype=float)
    single = r.shape == (3,)
    if r.shape[-1:] != (3,) or r.ndim > 2:
        raise InputError(f"rvec: expected Rodrigues vectors of shape (3,) or (P, 3), got {r.shape}")
    r = r.reshape(-1, 3)
    if len(r) == 1:  # one rotation: plain floats (NumPy's per-call cost dominates), same formula
        x, y, z = r[0].tolist()
        t2 = x * x + y * y + z * z
        if t2 < 1e-8:
            a1, b1 = 1 - t2 / 6 + t2 * t2 / 120, 0.5 - t2 / 24 + t2 * t2 / 720
            c1 = 1 - b1 * t2
        else:
            t = math.sqrt(t2)
            c1 = math.cos(t)  # = 1 - b θ², exactly -1 at θ = π
            a1, b1 = math.sin(t) / t, (1 - c1) / t2
        # I + a K + b K² with K² = r rᵀ - θ² I
        M1 = np.array(
            [
                [c1 + b1 * x * x, b1 * x * y - a1 * z, b1 * x * z + a1 * y],
                [b1 * x * y + a1 * z, c1 + b1 * y * y, b1 * y * z - a1 * x],
                [b1 * x * z - a1 * y, b1 * y * z + a1 * x, c1 + b1 * z * z],
            ]
        )
        return M1 if single else M1[None]
    th2 = np.einsum("pi,pi->p", r, r)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1 - th2 / 6 + th2 * th2 / 120, np.sin(ths) / ths)  # sin θ / θ
    b = np.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, (1 - np.cos(ths)) / (ths * ths))  # (1-cos θ)/θ²
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -r[:, 2], r[:, 1]
    K[:, 1, 0], K[:, 1, 2] = r[:, 2], -r[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -r[:, 1], r[:, 0]
    R = np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)
    return R[0] if single else R


def matrix_to_rodrigues(R, *, atol: float = 1e-6) -> np.ndarray:
    """Rodrigues vectors (P, 3) of rotation matrices (P, 3, 3) (one (3, 3) gives (3,)); the angle in
    [0, π]. Refuses matrices that are not rotations (orthonormal within ``atol``, determinant +1)."""
    M = np.asarray(R, dtype=float)
    single = M.shape == (3, 3)
    if M.shape[-2:] != (3, 3) or M.ndim > 3:
        raise InputError(f"rotation: expected 3x3 rotation matrices, (3, 3) or (P, 3, 3), got {M.shape}")
    M = M.reshape(-1, 3, 3)
    err = np.abs(M @ np.swapaxes(M, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bad = ~(np.isfinite(M).all(axis=(1, 2)) & (err <= atol) & (np.linalg.det(M) > 0))
    if bad.any():
        i = int(np.argmax(bad))
        where = "" if single else f" {i}"
        raise InputError(f"rotation{where}: expected a 3x3 rotation matrix, got {M[i].tolist()!r}")
    v = 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], axis=1)
    s = np.linalg.norm(v, axis=1)  # sin θ
    c = np.clip(0.5 * (np.trace(M, axis1=1, axis2=2) - 1), -1.0, 1.0)  # cos θ
    th = np.arctan2(s, c)
    small = s < 1e-12
    out = v * np.where(small, 1.0, th / np.where(small, 1.0, s))[:, None]  # θ → 0: θ/sin θ → 1
    far = c < 0  # past 90°: the axis from the symmetric part (well conditioned up to θ = π)
    if far.any():
        Mf, cf = M[far], c[far]
        B = (0.5 * (Mf + np.swapaxes(Mf, 1, 2)) - cf[:, None, None] * np.eye(3)) / (1 - cf)[:, None, None]
        i = np.argmax(np.diagonal(B, axis1=1, axis2=2), axis=1)
        rows = np.arange(len(Mf))
        axis = B[rows, :, i] / np.sqrt(B[rows, i, i])[:, None]
        sign = np.where(np.einsum("pi,pi->p", axis, v[far]) < 0, -1.0, 1.0)
        out[far] = axis * (sign * th[far])[:, None]
    return out[0] if single else out


__all__ = ["distort", "matrix_to_rodrigues", "rodrigues_to_matrix", "undistort"]
